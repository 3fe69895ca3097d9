"""Options and helpers of the commands that run the pipeline over many recordings (estimate, extract, sweep):
the engine (local / ray), the failure policy and the run report. The work itself is ``massviz.runners.dataset``."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

ENGINE_HELP = """
engines (--engine):
  local     in this process, one recording after another (default; no extra dependency)
  ray       one Ray task per recording on a pool of Ray actors that load the weights once (pip install
            'massviz[ray]'); --ray-address: none = start a local Ray instance with this machine's cores,
            auto = join the cluster started with `ray start --head`, HOST:PORT = that cluster's head. Workers read
            the frames from the recordings' paths and write traces to --cache: both must be on storage every node
            sees, at the same path.

exit status: 0 every recording processed (a recording without detection is a result: "not estimated");
  2 bad input or options, or a recording failed under --on-error stop (nothing written but --report);
  3 the run finished but some recordings failed (--on-error skip): their rows are "not estimated" and their
    one-line errors are on stderr and in --report; 130 interrupted (Ctrl-C: nothing written; finished traces stay
    in the cache and the next run reuses them).
"""


def add_engine_args(p: argparse.ArgumentParser) -> None:
    """--engine, --ray-address, --workers, --threads, --on-error, --report (``--quiet`` is a pipeline option)."""
    from massviz.runners.dataset import ENGINES, ON_ERROR

    g = p.add_argument_group("engine")
    g.add_argument("--engine", choices=ENGINES, default="local",
                   help="where the recordings are processed: local (default, in this process) or ray")
    g.add_argument("--ray-address", metavar="ADDR",
                   help="with --engine ray: 'auto' (join the running cluster) or HOST:PORT of its head (default: "
                   "start a local Ray instance with this machine's cores); nothing answering there within 10 s is "
                   "an error")
    g.add_argument("--workers", type=int, metavar="N",
                   help="with --engine ray: number of worker actors (default: one per GPU when the cluster has "
                   "GPUs, else one per CPU)")
    g.add_argument("--threads", type=int, metavar="N",
                   help="torch and OpenCV (NanoDet) threads per worker (default: local = their default, ray = CPUs / "
                   "workers). Mask "
                   "R-CNN's floats depend on the thread count: equal --threads give identical outputs on both engines")
    g.add_argument("--on-error", choices=ON_ERROR,
                   help="a recording that fails (unreadable, corrupt mid-way): stop = stop the run (exit 2, nothing "
                   "written); skip = its row is 'not estimated', its error goes to stderr and --report, exit 3. "
                   "Default: stop for one recording, skip for a dataset (more than one recording)")
    g.add_argument("--report", metavar="JSON",
                   help="write a run report: per recording status (done, cached, failed), error, seconds, worker")


def open_dataset(args):
    """(tasks, failed outcomes, opened recordings by input index, on_error) for ``args.recordings``.

    Dataset roots are expanded (an unusable root is an error at once); each recording is opened (checked) here; one
    that cannot be opened becomes a failed outcome under --on-error skip (the default for a dataset), an error under
    stop. Task paths are absolute: Ray workers open the recordings themselves; the local engine takes the opened
    ones (pass them to ``run_tasks(recordings=)``)."""
    from massviz.commands._warm import cache_root
    from massviz.errors import MassvizError
    from massviz.io.identity import open_remembered
    from massviz.io.recording import find_recordings
    from massviz.runners.dataset import Outcome, Task, default_on_error

    paths = [p for path in args.recordings for p in find_recordings(path, view=args.view)]
    on_error = args.on_error or default_on_error(len(paths))
    tasks, failed, recordings = [], [], {}
    for i, path in enumerate(paths):
        try:
            # unchanged since last opened (file identities): no frame decoded (massviz.io.identity); else opened,
            # and remembered after the run when that needs the frame files read (run_tasks: each read once)
            rec = open_remembered(path, cache_root(args), allow_partial=getattr(args, "allow_partial", False),
                                  defer=True)
        except MassvizError as err:
            if on_error == "stop":
                raise
            failed.append(Outcome(i, Path(path).stem if Path(path).is_file() else Path(path).name, str(path),
                                  "failed", error=str(err)))
            continue
        recordings[i] = rec
        tasks.append(Task(i, str(Path(path).resolve()), rec.id))
    return tasks, failed, recordings, on_error


def run_tasks(args, command: str, pipeline, tasks, failed, on_error, collect, desc: str = "recordings",
              recordings: dict | None = None):
    """Run the tasks on --engine; write --report (also when the run stops on a failure); failed recordings are
    listed on stderr. Returns the outcomes in input order. ``recordings``: the ones ``open_dataset`` opened (by
    task index): the local engine processes them as opened, without opening them again."""
    try:
        return _run_tasks(args, command, pipeline, tasks, failed, on_error, collect, desc, recordings)
    finally:
        _settle(pipeline, recordings)


def _settle(pipeline, recordings: dict | None) -> None:
    """Remember the recordings ``open_dataset`` opened but could not remember before their frames were read
    (``massviz.io.identity.settle``; with the trace cache's digests, which the run filled: no file read)."""
    from massviz.io.identity import settle

    cache = getattr(pipeline, "cache", None)
    for rec in (recordings or {}).values():
        settle(rec, cache.hasher if cache is not None else None)


def _run_tasks(args, command: str, pipeline, tasks, failed, on_error, collect, desc: str, recordings):
    from massviz.runners.dataset import RunStopped, portable_options, run_dataset, write_report

    stats: dict = {}
    options = portable_options(pipeline) if args.engine != "local" else pipeline.options
    info = {"command": command, "engine": args.engine, "ray_address": args.ray_address}
    try:
        outcomes = run_dataset(tasks, options, collect, engine=args.engine, workers=args.workers,
                               threads=args.threads, ray_address=args.ray_address, on_error=on_error,
                               progress=not args.quiet, desc=desc, failed=failed, pipeline=pipeline, stats=stats,
                               recordings=recordings)
    except RunStopped as stop:
        if args.report:
            done = {o.index for o in stop.outcomes}
            rest = [{"index": t.index, "id": t.id, "path": t.path, "status": "not run", "error": None,
                     "seconds": 0.0, "worker": "", "frames": 0} for t in tasks if t.index not in done]
            entries = sorted([o.report_entry() for o in stop.outcomes] + rest, key=lambda e: e["index"])
            write_report(args.report, entries, **info, **_stats(stats), stopped=True)
        raise
    if args.report:
        write_report(args.report, outcomes, **info, **_stats(stats), stopped=False)
    bad = [o for o in outcomes if not o.ok]
    for o in bad[:20]:
        print(f"massviz {command}: failed: {o.error}", file=sys.stderr)
    if len(bad) > 20:
        print(f"massviz {command}: ... and {len(bad) - 20} more failed recording(s) (see --report)", file=sys.stderr)
    return outcomes


def _stats(stats: dict) -> dict:
    keep = ("on_error", "workers", "threads", "startup_s", "seconds")
    return {k: (round(v, 3) if isinstance(v, float) else v) for k, v in stats.items() if k in keep}


def exit_status(outcomes) -> int:
    from massviz.runners.dataset import EXIT_SOME_FAILED

    return EXIT_SOME_FAILED if any(not o.ok for o in outcomes) else 0
