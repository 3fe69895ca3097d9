"""Where a recording stream goes: an .rrd file (written atomically), a spawned viewer, a running viewer or server
(gRPC URL), a caller's stream, or the inline viewer of a notebook. One output (``Output``, a context manager) for
``massviz log`` (``trace_logger``, ``massviz.runners.logged``) and ``massviz live`` (``live_logger``)."""
from __future__ import annotations

import contextlib
import logging
import os
import sys
import time
import uuid
from datetime import timedelta
from pathlib import Path

import rerun as rr

from massviz.errors import MassvizError
from massviz.io.atomic import atomic_path, check_room
from massviz.logs import ROOT

APPLICATION_ID = "massviz"
#: seconds one wait for Rerun's file writer lasts; between waits massviz checks that the file still grows (a writer
#: that died on a full disk never answers a flush).
FLUSH_WAIT_S = 2.0
#: streams whose file writer died and never answers: kept (never dropped, which would wait for the writer).
_STUCK: list = []
#: free bytes below which a failed write of an .rrd is reported as a full disk.
LOW_SPACE_BYTES = 1 << 20


def file_batcher() -> rr.ChunkBatcherConfig:
    """The batching of a stream that only writes an .rrd file: flushed by size (Rerun's default thresholds) and at
    the end, never by time, so the same data gives the same chunks."""
    config = rr.ChunkBatcherConfig.DEFAULT()
    config.flush_tick = timedelta(days=1)
    return config


class RerunLogHandler(logging.Handler):
    """massviz's log records (the ``massviz`` logger) into a Rerun stream's ``/log`` as ``TextLog`` entries at the
    stream's current time, as Rerun's logging-handler example routes Python's ``logging``; ``Output`` attaches one
    while its stream is open."""

    LEVELS = ((logging.ERROR, "ERROR"), (logging.WARNING, "WARN"), (logging.INFO, "INFO"), (0, "DEBUG"))

    def __init__(self, stream: rr.RecordingStream, path: str = "/log"):
        super().__init__()
        self.stream, self.path = stream, path

    def emit(self, record: logging.LogRecord) -> None:
        try:
            level = next(name for at, name in self.LEVELS if record.levelno >= at)
            self.stream.log(self.path, rr.TextLog(record.getMessage(), level=getattr(rr.TextLogLevel, level)))
        except Exception:  # noqa: BLE001 - logging must never raise into the caller
            self.handleError(record)


class Output:
    """A new ``RecordingStream`` of application ``massviz`` (never the global one) pointed at ``rrd`` (a file,
    written to a temporary name and renamed into place by ``close`` only when logging succeeded: nothing is left at
    ``rrd`` otherwise), ``spawn`` (a native viewer, spawned or connected on the default port), ``connect`` (a gRPC
    URL), any combination; or ``stream``: a caller's stream, whose sinks are left as they are and which is not
    disconnected. While it is open, massviz's log records also go to the stream's ``/log``.

    As a context manager (``with Output(...) as out:``), leaving the block delivers what was logged (``flush``) and
    closes the output; an error or a signal in the block closes it as failed (nothing is left at ``rrd``) and is
    raised on. ``stats()`` and ``seconds`` report on it.
    """

    def __init__(self, *, rrd: str | Path | None = None, spawn: bool = False, connect: str | None = None,
                 stream: rr.RecordingStream | None = None, recording_id: str | None = None):
        #: ``time.perf_counter()`` when the output was opened.
        self.opened = time.perf_counter()
        self._closed: float | None = None
        if stream is not None and (rrd is not None or spawn or connect):
            raise ValueError("give either stream or rrd/spawn/connect: a caller's stream keeps its own sinks")
        if stream is None and rrd is None and not spawn and not connect:
            raise ValueError("nothing to log to: give rrd, spawn=True, connect or stream")
        self.rrd = None if rrd is None else Path(rrd)
        self.spawn = spawn
        self._stack = contextlib.ExitStack()
        self._tmp: Path | None = None
        self.own = stream is None
        self._handler: RerunLogHandler | None = None
        if stream is not None:
            self.stream = stream
            self._route_logs()
            return
        # a file alone: chunks cut by size, not by a clock tick (Rerun's default flushes every few ms, so the chunking
        # — and an .rrd's size, ±10 % — depended on how busy the machine was); a viewer keeps the low-latency default
        batcher = file_batcher() if (self.rrd is not None and not spawn and not connect) else None
        self.stream = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id or str(uuid.uuid4()),
                                         batcher_config=batcher)
        if batcher is not None:  # a file's rows are placed by their own timelines (frame, time), not the wall clock
            self.stream.set_log_time_enabled(False)
        sinks = []
        if self.rrd is not None:
            self._tmp = self._stack.enter_context(atomic_path(self.rrd))
        try:  # an error or a signal from here on: the temporary .rrd goes
            if self._tmp is not None:
                try:
                    check_room(self._tmp)  # Rerun's file sink hangs when its first write fails (a full disk)
                except OSError as err:
                    raise MassvizError(f"cannot write ({err.strerror or err})", self.rrd) from None
                sinks.append(rr.FileSink(os.fspath(self._tmp)))
            if spawn:
                rr.spawn(connect=False)
                sinks.append(rr.GrpcSink())
            if connect:
                sinks.append(rr.GrpcSink(connect))
            self.stream.set_sinks(*sinks)
        except BaseException as err:
            self._abandon(err)
            raise
        self._route_logs()

    def __enter__(self) -> Output:
        return self

    def __exit__(self, kind, err, traceback) -> bool:
        if err is None:
            try:
                self.flush()
            except BaseException as failed:
                self.close(failed)
                raise
            self.close()
        else:
            self.close(err)
        return False

    @property
    def seconds(self) -> float:
        """Wall seconds since the output was opened, until it was closed."""
        return (time.perf_counter() if self._closed is None else self._closed) - self.opened

    def stats(self) -> dict:
        """``recording_id`` (the stream's) and ``rrd`` (the file's path, or None)."""
        return {"recording_id": self.stream.get_recording_id(), "rrd": None if self.rrd is None else str(self.rrd)}

    def _route_logs(self) -> None:
        """massviz's log records also go to this stream's ``/log`` until ``close``."""
        self._handler = RerunLogHandler(self.stream)
        logging.getLogger(ROOT).addHandler(self._handler)

    def _unroute_logs(self) -> None:
        if self._handler is not None:
            logging.getLogger(ROOT).removeHandler(self._handler)
            self._handler = None

    def flush(self, what: str = "the recording") -> None:
        """Deliver what was logged; an unreachable viewer (the gRPC sink reports it here) is one clear line, and so
        is a file that cannot be written (a full disk: "No space left on device"), also when Rerun's file writer
        died without a word (it then never answers: massviz waits while the file still grows)."""
        file_only = self._tmp is not None and not self.spawn
        size = -1
        while True:
            try:
                self.stream.flush(timeout_sec=FLUSH_WAIT_S if file_only else 1e38)
                return
            except RuntimeError as err:
                if self.rrd is not None and not self.spawn:  # the file sink: a full disk or a failing write
                    if "timed out" in str(err) and (grown := self._tmp_size()) > size and self._room():
                        size = grown  # still writing onto a disk with room: wait on
                        continue
                    raise MassvizError(f"cannot write {what} ({self._why(err)})", self.rrd) from None
                where = "the spawned Rerun viewer" if self.spawn else "Rerun"
                raise MassvizError(f"could not deliver {what} to {where} ({err}); without a display, log to a file "
                                   "(--rrd FILE.rrd) and open it in a browser with 'massviz view FILE.rrd'") from None

    def _tmp_size(self) -> int:
        try:
            return self._tmp.stat().st_size
        except OSError:
            return -1

    def _room(self) -> bool:
        try:
            st = os.statvfs(self._tmp.parent)
        except OSError:
            return True
        return st.f_bavail * st.f_frsize >= LOW_SPACE_BYTES

    def _why(self, err: RuntimeError) -> str:
        """What went wrong writing the file: a full disk said in the OS's words (Rerun's own message names no
        cause), else Rerun's message."""
        import errno
        import resource

        if self._tmp is not None and not self._room():
            return os.strerror(errno.ENOSPC)  # "No space left on device"
        limit = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
        if self._tmp is not None and limit != resource.RLIM_INFINITY and self._tmp_size() + (1 << 16) > limit:
            return os.strerror(errno.EFBIG)  # "File too large": the file-size limit (ulimit -f) is reached
        return f"{err}; is the disk full?"

    def _disconnect(self, failed: bool) -> None:
        """Disconnect the own stream; after a failed write without waiting more than FLUSH_WAIT_S (a file writer
        that died never answers, and the stream's temporary file is removed either way)."""
        if not failed:
            self.stream.disconnect()
            return
        import threading

        done = threading.Thread(target=self.stream.disconnect, name="massviz-rerun-disconnect", daemon=True)
        done.start()
        done.join(FLUSH_WAIT_S)
        if done.is_alive():  # the writer is gone for good: Rerun's own flush at exit would wait for it for ever
            rr.unregister_shutdown()
            _STUCK.append(self.stream)

    def close(self, err: BaseException | None = None) -> None:
        """Disconnect an own stream; with ``err`` None rename the .rrd into place (a ``MassvizError`` when Rerun wrote
        nothing), else leave nothing at its path (the caller re-raises ``err``)."""
        try:
            self._unroute_logs()
            if self.own:
                self._disconnect(err is not None)
            if err is None and self._tmp is not None and (not self._tmp.is_file() or self._tmp.stat().st_size == 0):
                empty = MassvizError("Rerun wrote nothing (is logging disabled with RERUN=off?)", self.rrd)
                self._abandon(empty)
                raise empty
            if err is None:
                self._stack.close()
            else:
                self._abandon(err)
        finally:
            self._closed = time.perf_counter()

    def _abandon(self, err: BaseException) -> None:
        self._unroute_logs()
        with contextlib.suppress(BaseException):
            self._stack.__exit__(type(err), err, err.__traceback__)


#: how rerun-notebook loads the inline viewer's code (its ``widget.js`` + wasm); read once, when it is imported.
NOTEBOOK_ASSET_ENV = "RERUN_NOTEBOOK_ASSET"


def use_local_notebook_assets() -> str:
    """Make the inline (notebook) Rerun viewer load its code from this machine, so it works offline.

    rerun-notebook's default fetches the viewer from ``app.rerun.io``; massviz sets ``RERUN_NOTEBOOK_ASSET=serve-local``
    instead (a small asset server inside the kernel, on localhost) unless the variable is already set — set it
    yourself to Rerun's hosted ``widget.js`` URL or to ``inline`` when the browser is not on the kernel's machine.
    Must run before ``rerun_notebook`` is first imported; returns the setting in effect."""
    if "rerun_notebook" in sys.modules and NOTEBOOK_ASSET_ENV not in os.environ:
        return "hosted (rerun_notebook was imported before massviz could choose local assets)"
    return os.environ.setdefault(NOTEBOOK_ASSET_ENV, "serve-local")


def notebook_stream(name: str, blueprint, *, width: int = 1000, height: int = 640) -> rr.RecordingStream:
    """A new stream shown in an inline Rerun viewer (rerun-notebook) in the current notebook cell with ``blueprint``;
    the viewer's code is served locally (``use_local_notebook_assets``), so no network is needed."""
    use_local_notebook_assets()
    stream = rr.RecordingStream(APPLICATION_ID, recording_id=f"notebook-{name}-{uuid.uuid4().hex[:8]}")
    stream.notebook_show(width=width, height=height, blueprint=blueprint)
    return stream


__all__ = ["APPLICATION_ID", "Output", "RerunLogHandler", "NOTEBOOK_ASSET_ENV", "use_local_notebook_assets", "notebook_stream"]
