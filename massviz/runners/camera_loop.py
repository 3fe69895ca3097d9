"""The live runner: frames from a RealSense source go through the per-frame pipeline step and out to Rerun as they
arrive (``massviz live``).

    stream = open_file_stream("x.db3")               # or open_camera(serial), open_device_stream(device)
    fp = pipeline.frame_pipeline()                   # massviz.app.Pipeline: FramePipeline.step per frame
    result = run_live(stream, fp, logger=LiveLogger(...), duration=10, save="rec/")
    result.trace, result.stats.dropped

librealsense's threads hand each colour+depth pair to a one-slot buffer (``LatestSlot``) that keeps only the newest:
when the detector is slower than the camera, the frames that arrive meanwhile are dropped and counted, and nothing
queues (memory stays flat however long the session). The main thread takes the newest pair, aligns and copies it
(``read``), runs ``FramePipeline.step`` (detect, features, predict, the K nearest so far) and logs the frame. Ctrl-C,
SIGTERM or SIGHUP (the first one), ``duration`` or the end of a file ends the session cleanly: the trace is
finished, ``save`` writes the processed frames as a massviz recording folder (so ``massviz log`` and notebooks replay
the session exactly). A second signal interrupts at once and leaves no output.
"""
from __future__ import annotations

import dataclasses
import queue
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from tqdm.auto import tqdm

from massviz.core.trace import analyse_trace
from massviz.errors import MassvizError
from massviz.io.formats.folder import FolderFrameWriter

#: seconds without any frame from a camera before the session gives up on it.
SILENCE_S = 5.0


class LatestSlot:
    """Holds only the newest item: ``put`` replacing an item nobody took counts a drop. Thread-safe."""

    def __init__(self):
        self._cond = threading.Condition()
        self._item = None
        self.arrived = 0
        self.dropped = 0

    def put(self, item) -> None:
        with self._cond:
            if self._item is not None:
                self.dropped += 1
            self._item = item
            self.arrived += 1
            self._cond.notify()

    def take(self, timeout: float):
        """The newest item (and empty the slot), or None after ``timeout`` seconds."""
        with self._cond:
            if self._item is None:
                self._cond.wait(timeout)
            item, self._item = self._item, None
            return item

    def __len__(self) -> int:
        return 0 if self._item is None else 1


def rss_mb() -> float:
    """Resident memory of this process (MB; Linux /proc, else the peak from getrusage)."""
    try:
        with open("/proc/self/statm") as fh:
            import os

            return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except OSError:
        import resource

        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


@dataclass
class LiveStats:
    """What a session did: frames that ``arrived`` from the source, were ``processed`` or ``dropped`` (replaced by a
    newer one while the pipeline was busy), ``unpaired`` frames (colour without depth or back), why it
    ``stopped``, its ``seconds``, per-frame latency (ms: stage -> list, one per processed frame) and resident memory
    (MB) sampled after every processed frame."""

    arrived: int = 0
    processed: int = 0
    dropped: int = 0
    unpaired: int = 0
    stopped: str = ""
    seconds: float = 0.0
    latency_ms: dict = field(default_factory=dict)
    rss_mb: list = field(default_factory=list)
    frame_numbers: list = field(default_factory=list)
    timestamps_ms: list = field(default_factory=list)

    def median_ms(self, stage: str) -> float:
        values = self.latency_ms.get(stage) or [float("nan")]
        return float(np.median(values))

    def summary(self) -> str:
        line = (f"{self.processed} frames processed of {self.arrived} received, {self.dropped} dropped "
                f"(detector slower than the source)" if self.dropped else
                f"{self.processed} frames processed of {self.arrived} received, none dropped")
        if self.unpaired:
            line += f", {self.unpaired} unpaired colour/depth frames skipped"
        if self.processed:
            line += (f"; per frame (median): {self.median_ms('total'):.0f} ms from arrival to logged, "
                     f"{self.median_ms('overhead'):.1f} ms of it massviz's own work beyond detect + predict "
                     "(read, align, features, select, log)")
        return line


@dataclass
class LiveResult:
    trace: object
    stats: LiveStats
    saved: Path | None = None
    #: the saved recording (``save``) as the folder writer wrote it: what ``open_recording(saved)`` returns
    recording: object = None


class FolderWriter:
    """Writes processed frames as a massviz recording folder (``rgb/NNNNNN.png``, ``depth/NNNNNN.png`` 16-bit mm,
    ``intrinsics.json``, ``meta.json``) from a writer thread with a bounded queue, into a temporary folder beside
    ``path`` that ``finish`` renames into place (``abort`` removes it): never a half-written recording."""

    def __init__(self, path: str | Path, queue_size: int = 8):
        from massviz.io.atomic import atomic_dir

        self.path = Path(path)
        if self.path.exists() and (not self.path.is_dir() or any(self.path.iterdir())):
            raise MassvizError("exists and is not an empty folder; --save needs a new folder", self.path)
        self._ctx = atomic_dir(self.path)
        self.tmp = self._ctx.__enter__()
        self._queue: queue.Queue = queue.Queue(maxsize=queue_size)
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._work, name="massviz-save", daemon=True)
        try:  # a signal or an error from here on: the temporary folder goes
            self._folder = FolderFrameWriter(self.tmp, compression=1)  # the folder format's writer; level 1: fast
            self._thread.start()
        except BaseException as err:
            self.abort(err)
            raise

    def write(self, frame) -> None:
        if self.error is not None:
            raise MassvizError(f"cannot write the frames ({self.error})", self.path)
        self._queue.put(frame)  # blocks when the disk is slower than the camera (more frames dropped, counted)

    def _work(self) -> None:
        while True:
            frame = self._queue.get()
            if frame is None:
                return
            try:
                self._folder.write(frame.index, frame.rgb, frame.depth)
            except BaseException as err:  # noqa: BLE001 - reported by write()/finish() on the main thread
                self.error = err

    def finish(self, intrinsics, meta: dict) -> Path:
        self._queue.put(None)
        self._thread.join()
        if self.error is not None:
            err = MassvizError(f"cannot write the frames ({self.error})", self.path)
            self.abort(err)
            raise err
        self._folder.finish(intrinsics, meta)
        self._ctx.__exit__(None, None, None)
        return self.path

    def recording(self):
        """The saved recording (after ``finish``), as ``open_recording`` would open it, without reading it back."""
        return self._folder.written(self.path)

    def abort(self, err: BaseException | None = None) -> None:
        if self._thread.is_alive():
            try:
                self._queue.put_nowait(None)
            except queue.Full:
                pass
            self._thread.join(timeout=10)
        err = err or MassvizError("session aborted")
        try:
            self._ctx.__exit__(type(err), err, err.__traceback__)
        except BaseException:  # noqa: BLE001 - the context re-raises what it was given
            pass


class _StopFlag:
    """Ctrl-C, SIGTERM or SIGHUP ends the session after the current frame, as the end of a file does (the outputs
    are written); a second one interrupts at once, as every command ends (``massviz.signals``) (nothing half-written is left).
    """

    def __init__(self):
        self.reason = ""
        self._old: dict = {}

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            from massviz.signals import install_handlers

            install_handlers(self._handle, self._old)  # nohup's SIGHUP stays ignored
        return self

    def _handle(self, signum, frame):
        if self.reason:
            from massviz.signals import end_like_ctrl_c

            end_like_ctrl_c(signum, frame)  # KeyboardInterrupt or Terminated (once an import under way is done)
            return
        self.reason = "interrupted" if signum == signal.SIGINT else f"interrupted ({signal.Signals(signum).name})"

    def __exit__(self, *exc):
        for sig, old in self._old.items():
            if signal.getsignal(sig) == self._handle:  # not when the command line has since set it (a clean-up runs)
                signal.signal(sig, old)


def run_live(stream, frame_pipeline, *, logger=None, duration: float | None = None, save: str | Path | None = None,
             max_frames: int | None = None, progress: bool = False, name: str = "live", source: str = "") -> LiveResult:
    """Run a live session (see the module docstring). ``stream``: a started-or-not ``massviz.io.formats.realsense_live
    .LiveStream``; ``frame_pipeline``: a fresh ``FramePipeline``; ``logger``: a ``LiveLogger`` or None;
    ``duration``: seconds (None: until Ctrl-C or the end of a file); ``max_frames``: stop after that many processed
    frames; ``save``: folder for the processed frames. The stream is stopped and the logger closed on return."""
    stats = LiveStats()
    slot = LatestSlot()
    info = stream.info
    fp = frame_pipeline
    writer = bar = None
    started = time.perf_counter()
    last_arrival = started
    seen_dropped = 0

    def sink(c, d):
        slot.put((c, d, time.perf_counter()))

    trace = None
    try:  # from here on, however the session ends (an error, a signal), the stream, writer and logger are ended
        writer = FolderWriter(save) if save is not None else None
        bar = tqdm(total=None, desc=f"live {name}", unit="frame", file=sys.stderr, disable=not progress,
                   leave=False)
        warm_up(fp, info)
        # the faithful settings once for the whole session (each step's own entering only counts a user)
        with fp.stage.faithful(), _StopFlag() as flag:
            stream.start(sink)
            started = last_arrival = time.perf_counter()
            while True:
                now = time.perf_counter()
                if flag.reason:
                    stats.stopped = flag.reason
                    break
                if duration is not None and now - started >= duration:
                    stats.stopped = f"duration {duration:g} s"
                    break
                if max_frames is not None and stats.processed >= max_frames:
                    stats.stopped = f"{max_frames} frames"
                    break
                if stream.reader.error is not None:
                    raise MassvizError(f"{source_name(stream)}: cannot read frames ({stream.reader.error})")
                item = slot.take(timeout=0.05)
                if item is None:
                    if stream.is_file and stream.finished() and len(slot) == 0:
                        stats.stopped = "end of file"
                        break
                    if time.perf_counter() - last_arrival > SILENCE_S:
                        if stats.processed == 0:
                            raise MassvizError(f"{source_name(stream)}: no frame arrived in {SILENCE_S:g} s")
                        stats.stopped = f"no frame for {SILENCE_S:g} s (camera disconnected?)"
                        if logger is not None:
                            logger.note(f"session ended: {stats.stopped}", "warn")
                        break
                    continue
                c, d, arrival = item
                last_arrival = arrival
                number, stamp = int(c.get_frame_number()), float(c.get_timestamp())
                t0 = time.perf_counter()
                frame = stream.frame(c, d, stats.processed)
                del c, d, item  # release librealsense's buffers before the slow part
                read = time.perf_counter() - t0
                res = fp.step(frame, read_seconds=read)
                notes = []
                dropped_now = slot.dropped - seen_dropped
                if dropped_now:
                    notes.append(("warn", f"dropped {dropped_now} frame(s) since the previous processed frame "
                                  f"(detector slower than the source; {slot.dropped} in all)"))
                    seen_dropped = slot.dropped
                t = res.timings
                extra = {"wait": t0 - arrival, "total": time.perf_counter() - arrival,
                         "overhead": t["read"] + t["features"] + t["select"]}
                log_s = 0.0
                if logger is not None:
                    log_s = logger.log_step(res, latency=extra, timestamp_ms=stamp, notes=notes)
                    extra["total"] = time.perf_counter() - arrival
                    extra["overhead"] += log_s
                if writer is not None:
                    writer.write(frame)
                for stage, seconds in {**res.timings, "log": log_s, **extra}.items():
                    stats.latency_ms.setdefault(stage, []).append(1000.0 * seconds)
                stats.frame_numbers.append(number)
                stats.timestamps_ms.append(stamp)
                stats.processed += 1
                stats.rss_mb.append(rss_mb())
                bar.update(1)
                if res.running_estimate >= 0:
                    bar.set_postfix_str(f"running estimate {res.running_estimate:.1f} g, {slot.dropped} dropped",
                                        refresh=False)
        stream.stop()
        stats.arrived, stats.dropped, stats.unpaired = slot.arrived, slot.dropped, stream.reader.unpaired
        stats.seconds = time.perf_counter() - started
        if stats.processed == 0:
            raise MassvizError(f"{stream.description}: no frame was processed ({stats.stopped or 'stopped'})")
        fp.recording.num_frames = stats.processed
        fp.recording.meta.setdefault("live", {}).update(live_meta(stats, source or stream.description))
        trace = fp.finish(analyse=False)  # analysed once, with the saved recording's info when there is one
        saved = saved_recording = None
        if writer is not None:
            meta = dict(fp.recording.meta, id=name, fps=info.fps)
            saved = writer.finish(info.intrinsics, meta)
            # the trace is the saved folder's (what the folder writer wrote, not read back): `massviz log SAVED`
            # finds it in the cache and replays it exactly
            saved_recording = writer.recording()
            trace = dataclasses.replace(trace, recording=saved_recording.info())
            writer = None
        trace = analyse_trace(trace)
        if logger is not None:
            logger.close(trace, timings={"live_seconds": stats.seconds}, summary=stats.summary())
            logger = None
        return LiveResult(trace=trace, stats=stats, saved=saved,
                          recording=saved_recording)
    except BaseException as err:
        try:
            stream.stop()
        finally:
            if writer is not None:
                writer.abort(err)
            if logger is not None:
                logger.abort(err)
        raise
    finally:
        if bar is not None:
            bar.close()


def source_name(stream) -> str:
    """The source as its errors name it: the option that chose it (when known) and its description."""
    option = getattr(stream, "option", "")
    return f"{option}: {stream.description}" if option else stream.description


def warm_up(fp, info) -> None:
    """Run the detector and the model once on a blank frame (not recorded), so the first live frame does not pay
    for lazy initialisation (torch, Mask R-CNN) while the camera's frames are dropped."""
    from massviz.core.patches import model_view
    from massviz.core.types import Frame

    blank = Frame(index=-1, rgb=np.zeros((info.height, info.width, 3), np.uint8),
                  depth=np.zeros((info.height, info.width), np.uint16))
    fp.detector.detect(blank)
    patch = np.zeros((16, 16, 3), np.uint8)
    fp.model.predict([patch], np.array([[0.1, 0.1, 500.0]]))
    model_view(patch)  # the logger's view of a chosen patch (imports torch when the model did not)
    cv2.imencode(".jpg", blank.rgb)


def live_meta(stats: LiveStats, source: str) -> dict:
    """What a saved live recording's ``meta.json`` keeps of the session (under ``"live"``)."""
    return {"source": source, "arrived": stats.arrived, "processed": stats.processed, "dropped": stats.dropped,
            "unpaired": stats.unpaired, "stopped": stats.stopped, "seconds": round(stats.seconds, 3),
            "frame_numbers": stats.frame_numbers, "timestamps_ms": stats.timestamps_ms}


__all__ = ["LatestSlot", "LiveStats", "LiveResult", "FolderWriter", "run_live", "rss_mb", "live_meta"]
