"""Dataset runs: the per-recording pipeline over many recordings, on one of two engines.

    from massviz.runners.dataset import Task, run_dataset
    outcomes = run_dataset(tasks, options, collect)                       # local: in this process
    outcomes = run_dataset(tasks, options, collect, engine="ray")          # a pool of Ray actors

* ``local`` (default): in this process, one recording after another; no extra dependency.
* ``ray``: one Ray task per recording on a pool of actors that build the pipeline (detector + mass CNN) once; each
  actor reads its recording's frames from the recording's path (shared storage), writes the trace to the trace cache
  and returns only ``collect(trace, recording, task.extra)`` (small); see ``massviz.runners.ray_engine``.

Both engines run the same ``RecordingWorker`` over the same tasks, apply the same ``on_error`` policy and return one
``Outcome`` per task in input order, so whatever is written from them is the same whichever engine ran.
"""
from __future__ import annotations

import json
import os
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from massviz.errors import MassvizError
from massviz.runners.worker import FAULT_ENV, Outcome, RecordingWorker, Task, worker_name  # noqa: F401

ENGINES = ("local", "ray")
ON_ERROR = ("stop", "skip")
REPORT_FORMAT = "massviz.run-report/1"
#: exit status of a dataset run that finished but in which some recordings failed (their rows: "not estimated").
EXIT_SOME_FAILED = 3
STATUSES = ("done", "cached", "failed")


class RunStopped(MassvizError):
    """``on_error="stop"``: a recording failed; ``outcomes`` holds what finished before (and the failure)."""

    def __init__(self, outcome: Outcome, outcomes: list[Outcome]):
        super().__init__(outcome.error or f"{outcome.path}: failed")
        self.outcome, self.outcomes = outcome, outcomes


def portable_options(pipeline):
    """The pipeline's options with everything resolved on the driver, so that a worker in another process (or on
    another node) builds the same pipeline: the detector ``auto`` made concrete, absolute paths for the recordings'
    weights, replay file and cache (``$MASSVIZ_WEIGHTS`` / ``$MASSVIZ_CACHE_DIR`` read here, not on the worker)."""
    from massviz.io.weights import resolve_weights

    o = pipeline.options

    def absolute(p):
        return None if p is None else str(Path(p).expanduser().resolve())

    return o.replace(detector=pipeline.detector.name, weights=absolute(resolve_weights(o.weights)),
                     detector_weights=absolute(o.detector_weights), replay=absolute(o.replay),
                     cache=None if pipeline.cache is None else absolute(pipeline.cache.root),
                     no_cache=pipeline.cache is None, quiet=True)


class Progress:
    """One bar over recordings (done / cached / failed, frames/s) on stderr; ``enabled=False`` shows nothing."""

    def __init__(self, total: int, enabled: bool, desc: str = "recordings"):
        from tqdm.auto import tqdm

        self.enabled = enabled
        self.bar = tqdm(total=total, desc=desc, unit="rec", file=sys.stderr, disable=not enabled, dynamic_ncols=True)
        self.counts = dict.fromkeys(STATUSES, 0)
        self.frames = 0
        self.t0 = time.perf_counter()
        self._show()

    def _show(self) -> None:
        fps = self.frames / max(time.perf_counter() - self.t0, 1e-9)
        c = self.counts
        self.bar.set_postfix_str(f"done {c['done']}, cached {c['cached']}, failed {c['failed']}, {fps:.1f} frames/s",
                                 refresh=False)

    def update(self, outcome: Outcome) -> None:
        self.counts[outcome.status] += 1
        self.frames += outcome.frames
        self._show()
        self.bar.update(1)

    def write(self, line: str) -> None:
        if self.enabled:
            self.bar.write(line, file=sys.stderr)

    def close(self) -> None:
        self.bar.close()


def default_on_error(n_recordings: int) -> str:
    """The policy when none is given: stop for one recording, skip for a dataset (more than one recording)."""
    return "stop" if n_recordings <= 1 else "skip"


def run_dataset(tasks: Sequence[Task], options, collect: Callable | None = None, *, engine: str = "local",
                workers: int | None = None, threads: int | None = None, ray_address: str | None = None,
                on_error: str | None = None, progress: bool = True, desc: str = "recordings",
                failed: Sequence[Outcome] = (), pipeline=None, stats: dict | None = None,
                recordings: dict | None = None) -> list[Outcome]:
    """Process every task; one ``Outcome`` per task (and per ``failed`` outcome), in input (``index``) order.

    ``options``: a ``PipelineOptions`` a worker can build from (``portable_options``); ``pipeline``: the same
    pipeline already built, used by the local engine instead of building another. ``failed``: outcomes known
    before the run (recordings that could not even be opened); they count in the bar and obey ``on_error``.
    ``on_error``: "stop" raises ``RunStopped`` (a ``MassvizError`` with the recording's one-line error) at the
    first failure, after the workers are shut down; "skip" records it and goes on; default: ``default_on_error``.
    KeyboardInterrupt stops the run (Ray: actors killed, a Ray this call started shut down) and propagates.
    ``stats`` (a dict) receives the engine, number of workers and threads, start-up and run seconds.
    ``recordings``: {task index: the recording already opened by the caller}; the local engine uses them
    instead of opening each recording again (Ray workers open theirs from the task's path).
    """
    if engine not in ENGINES:
        raise MassvizError(f"unknown engine {engine!r} (choose from {', '.join(ENGINES)})")
    on_error = on_error or default_on_error(len(tasks) + len(failed))
    if on_error not in ON_ERROR:
        raise MassvizError(f"unknown --on-error policy {on_error!r} (choose from {', '.join(ON_ERROR)})")
    if workers is not None and workers < 1:
        raise MassvizError(f"--workers must be >= 1, got {workers}")
    if threads is not None and threads < 1:
        raise MassvizError(f"--threads must be >= 1, got {threads}")
    if engine == "local" and (workers is not None or ray_address is not None):
        raise MassvizError("--workers and --ray-address need --engine ray")
    stats = {} if stats is None else stats
    stats.update(engine=engine, on_error=on_error)
    total = len(tasks) + len(failed)
    bar = Progress(total, progress and total > 1, desc)  # one recording: its frame bar (local) says enough
    outcomes: dict[int, Outcome] = {}

    def record(outcome: Outcome) -> None:
        outcomes[outcome.index] = outcome
        bar.update(outcome)
        if not outcome.ok and on_error == "stop":
            raise RunStopped(outcome, [outcomes[i] for i in sorted(outcomes)])

    t0 = time.perf_counter()
    try:
        for o in failed:
            record(o)
        if engine == "local":
            _run_local(tasks, options, collect, threads, record, pipeline, stats,
                       frame_progress=progress and len(tasks) + len(failed) == 1, recordings=recordings or {})
        elif tasks:
            from massviz.runners.ray_engine import run_ray

            run_ray(tasks, options, collect, workers=workers, threads=threads, address=ray_address, record=record,
                    log=bar.write, stats=stats)
    finally:
        bar.close()
        stats["seconds"] = time.perf_counter() - t0
    return [outcomes[i] for i in sorted(outcomes)]


def _run_local(tasks, options, collect, threads, record, pipeline, stats, frame_progress: bool,
               recordings: dict) -> None:
    # torch only when something here uses it (a warm pipeline serving cached traces does not import it)
    torch = sys.modules.get("torch") if threads is None else __import__("torch")
    before = torch.get_num_threads() if torch is not None else None
    try:
        t0 = time.perf_counter()
        worker = RecordingWorker(options, collect, threads, pipeline=pipeline)
        built = sys.modules.get("torch")  # imported by building the pipeline, unless it serves cached traces only
        stats.update(workers=1, threads=built.get_num_threads() if built is not None else None,
                     startup_s=time.perf_counter() - t0)
        debug = bool(os.environ.get("MASSVIZ_DEBUG"))
        for task in tasks:
            record(worker.run(task, debug=debug, progress=frame_progress, recording=recordings.get(task.index)))
    finally:
        if before is not None:
            torch.set_num_threads(before)


def write_report(path: str | Path, outcomes: Sequence[Outcome], **run_info) -> Path:
    """The run report (JSON, format ``massviz.run-report/1``), written atomically: ``run_info`` (command, engine,
    workers, ...), counts per status and one entry per recording in input order (index, id, path, status
    done|cached|failed|not run, error, seconds, worker, frames)."""
    from massviz.io.atomic import atomic_path

    entries = [o.report_entry() if isinstance(o, Outcome) else dict(o) for o in outcomes]
    counts = {s: sum(e["status"] == s for e in entries) for s in (*STATUSES, "not run")}
    doc = {"format": REPORT_FORMAT, **run_info, "counts": counts, "recordings": entries}
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(doc, indent=1, default=str) + "\n", encoding="utf-8")
    return path


__all__ = ["ENGINES", "ON_ERROR", "EXIT_SOME_FAILED", "FAULT_ENV", "REPORT_FORMAT", "Task", "Outcome", "RunStopped",
           "RecordingWorker", "default_on_error", "portable_options", "run_dataset", "write_report"]
