"""What every engine of ``massviz.runners.dataset.run_dataset`` runs: one ``RecordingWorker`` per process over
``Task`` values, each giving back an ``Outcome`` (shared by the local engine and ``massviz.runners.ray_engine``)."""
from __future__ import annotations

import os
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from massviz.errors import MassvizError
from massviz.io.identity import LocatedRecording

#: test-only fault injection (Ray engine): the worker process that gets the recording with this id dies once,
#: after reading its first frame (``os._exit``, as a crash); Ray restarts it and retries the recording.
FAULT_ENV = "MASSVIZ_TEST_KILL_WORKER"

@dataclass(frozen=True)
class Task:
    """One recording to process: its position in the input, its path (absolute: workers open it themselves), its
    id and a small picklable ``extra`` handed to ``collect`` (e.g. the recording's label for ``extract``)."""

    index: int
    path: str
    id: str
    extra: Any = None


@dataclass
class Outcome:
    """What came back for one task. ``status``: "done" (computed), "cached" (trace reused from the cache) or
    "failed" (``error``: the one-line reason); ``value``: what ``collect`` returned (None when failed); ``frames``:
    frames run through the detector (0 when cached); ``worker``: "host:pid" of the process that made it."""

    index: int
    id: str
    path: str
    status: str
    error: str | None = None
    seconds: float = 0.0
    worker: str = ""
    frames: int = 0
    value: Any = None
    internal: bool = False

    @property
    def ok(self) -> bool:
        return self.status != "failed"

    def report_entry(self) -> dict:
        return {"index": self.index, "id": self.id, "path": self.path, "status": self.status, "error": self.error,
                "seconds": round(self.seconds, 3), "worker": self.worker, "frames": self.frames}


def worker_name() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


class RecordingWorker:
    """Builds the pipeline once from ``options`` (or takes a built ``pipeline``) and processes tasks: what every
    engine's worker runs.

    ``collect(trace, recording, extra)`` runs where the trace was made and returns what the driver needs (keep it
    small: it travels back). ``threads``: torch intra-op threads in this worker (None: leave torch's setting)."""

    def __init__(self, options, collect: Callable | None = None, threads: int | None = None, pipeline=None):
        from massviz.app import build_pipeline

        if threads:
            import cv2
            import torch

            torch.set_num_threads(int(threads))
            cv2.setNumThreads(int(threads))  # NanoDet runs in cv2.dnn
        self.pipeline = pipeline if pipeline is not None else build_pipeline(options)
        self.collect = collect
        self.name = worker_name()

    def ready(self) -> str:
        return self.name

    def run(self, task: Task, *, collect: Callable | None = None, fault: Callable | None = None,
            debug: bool = False, progress: bool = False, recording=None) -> Outcome:
        """Process one task (``collect``: instead of the worker's own); errors become a failed ``Outcome``.
        ``recording``: the task's recording already opened in this process (the local engine), else it is opened
        from ``task.path`` here (a Ray worker)."""
        from massviz.io.recording import open_recording

        collect = collect if collect is not None else self.collect

        t0 = time.perf_counter()
        out = Outcome(task.index, task.id, task.path, "failed", worker=self.name)
        try:
            # a pipeline may open recordings its own way (the warm path: recognised from file identities)
            opener = getattr(self.pipeline, "open_recording", open_recording)
            # the recording opened up front is used when it was opened (a LocatedRecording, recognised from file
            # identities, has no frames: the pipeline's opener opens it its own way)
            rec = recording if recording is not None and not isinstance(recording, LocatedRecording) else \
                opener(task.path, allow_partial=self.pipeline.options.allow_partial)
            if fault is not None:
                fault(rec)
            trace = self.pipeline.process(rec, progress=progress)
            out.value = collect(trace, rec, task.extra) if collect is not None else None
            out.status = "cached" if "cache" in trace.timings else "done"
            out.frames = 0 if out.status == "cached" else len(trace.frames)
        except MassvizError as err:
            out.error = str(err)
        except Exception as err:  # noqa: BLE001 - a bug or an unexpected library error: one line in the report
            if debug:
                raise
            out.error, out.internal = f"{task.path}: internal error: {type(err).__name__}: {err}", True
        out.seconds = time.perf_counter() - t0
        return out


__all__ = ["FAULT_ENV", "Task", "Outcome", "worker_name", "RecordingWorker"]
