"""Log a live session to Rerun frame by frame, as ``massviz live`` computes it (the entity tree of ``rerun_log``).

``LiveLogger.log_step`` is called once per processed frame with that frame's step result (``FrameResult`` of
``massviz.core.pipeline``: the frame, its detections with d/a/b/pred, the K nearest so far and the running
estimate, the stage timings) and logs it at once on the ``frame`` timeline (sequence = index of the processed frame)
and on ``capture_time`` (seconds since the first frame, from the camera's timestamps):

- ``/camera/rgb`` (JPEG ``EncodedImage``), ``/camera/depth`` (``DepthImage``: the 3D view back-projects it through the
  ``/camera`` ``Pinhole``; ``/world/points`` is not logged live unless ``points=True``: an Open3D back-projection
  per frame and 2-3x the .rrd size, see benchmarks/live_latency.py), ``/camera/detections`` and ``/camera/masks``
  (the K nearest *so far* marked ★rank), ``/patches/<rank>`` (when the K nearest change);
- ``/predictions/running_estimate`` (the mean of the K nearest so far) each frame;
- ``/latency/<stage>`` (ms): ``read`` (aligning and copying the newest frame), ``detect``, ``features``,
  ``predict``, ``select``, ``log`` (this logging), ``wait`` (the frame's time in the one-frame buffer while the
  previous one was processed), ``total`` (arrival to logged) and ``overhead`` (read + features + select + log:
  massviz's own work beyond detect and predict);
- ``/log``: skipped detections, changes of the K nearest, dropped frames.

``close(trace, ...)`` logs what only the end knows: ``/predictions/patch_<rank>``, ``/predictions/estimate`` (as
``massviz log`` does), ``/summary`` and ``/timings``. This module reads results only; it runs no stage.
"""
from __future__ import annotations

import contextlib
import os
import time
import uuid
from pathlib import Path

import numpy as np
import rerun as rr

from massviz.core.trace import Trace, describe_detection
from massviz.core.types import Intrinsics
from massviz.errors import MassvizError
from massviz.io.atomic import atomic_path
from massviz.views.rerun_log import (APPLICATION_ID, MAX_POINTS, POINT_STEP, RUNNING_COLOUR, default_blueprint,
                                     detection_class_ids, frustum_depth, log_annotation_context, log_depth,
                                     log_detections, log_masks, log_patch, log_pinhole, log_points, log_predictions,
                                     jpeg_bytes, log_summary, log_timings)

_LEVELS = {"debug": rr.TextLogLevel.DEBUG, "info": rr.TextLogLevel.INFO, "warn": rr.TextLogLevel.WARN}


class LiveLogger:
    """Rerun output of a live session: ``rrd`` (file, written atomically at ``close``), ``spawn`` (a native
    viewer), ``connect`` (a running viewer or server's gRPC URL) — any combination — or ``stream`` (a caller's)."""

    def __init__(self, *, name: str, k: int, threshold: float, intrinsics: Intrinsics | None,
                 rrd: str | Path | None = None, spawn: bool = False, connect: str | None = None,
                 stream: rr.RecordingStream | None = None, jpeg_quality: int = 85, points: bool = False):
        if stream is None and rrd is None and not spawn and not connect:
            raise ValueError("nothing to log to: give rrd, spawn, connect or stream")
        self.k, self.threshold, self.intrinsics, self.quality = k, threshold, intrinsics, int(jpeg_quality)
        self.points = points and intrinsics is not None  # /world/points as massviz log does (costly; off by default)
        self._stack = contextlib.ExitStack()
        self.rrd = None if rrd is None else Path(rrd)
        self._own = stream is None
        if stream is None:
            stream = rr.RecordingStream(APPLICATION_ID, recording_id=str(uuid.uuid4()))
            sinks = []
            if self.rrd is not None:
                tmp = self._stack.enter_context(atomic_path(self.rrd))
                sinks.append(rr.FileSink(os.fspath(tmp)))
            if spawn:
                rr.spawn(connect=False)
                sinks.append(rr.GrpcSink())
            if connect:
                sinks.append(rr.GrpcSink(connect))
            stream.set_sinks(*sinks)
        self.rec = stream
        self.rec.send_recording_name(f"massviz live {name}")
        self.rec.send_blueprint(default_blueprint(k, has_3d=intrinsics is not None),
                                make_active=True, make_default=True)
        log_annotation_context(self.rec, k)
        self.rec.log("/predictions/running_estimate", rr.SeriesLines(
            names="running estimate (K nearest so far)", colors=RUNNING_COLOUR, widths=2), static=True)
        self._t0_ms: float | None = None
        self.frames = 0

    # ------------------------------------------------------------------------------------------------ per frame
    def log_step(self, res, *, latency: dict | None = None, timestamp_ms: float | None = None,
                 notes: list[tuple[str, str]] = ()) -> float:
        """Log one processed frame (``res``: a ``FrameResult``); ``latency``: extra per-frame seconds
        (e.g. ``total``, ``overhead``); ``notes``: (level, text) for ``/log``. Returns the seconds logging took."""
        t0 = time.perf_counter()
        rec, frame, dets = self.rec, res.frame, res.detections
        rec.set_time("frame", sequence=frame.index)
        if timestamp_ms is not None:
            self._t0_ms = timestamp_ms if self._t0_ms is None else self._t0_ms
            rec.set_time("capture_time", duration=(timestamp_ms - self._t0_ms) / 1000.0)
        if self.frames == 0 and self.intrinsics is not None:
            log_pinhole(rec, self.intrinsics, frustum_depth(frame.depth))
        rec.log("/camera/rgb", rr.EncodedImage(contents=jpeg_bytes(frame.rgb, self.quality, f"frame {frame.index}"),
                                               media_type="image/jpeg"))
        log_depth(rec, frame.depth)
        if self.points:
            log_points(rec, frame.depth, frame.rgb, self.intrinsics, POINT_STEP, MAX_POINTS)
        n = len(dets)
        rank_global = {int(g): r for r, g in enumerate(res.selection)}
        rank_of = {i: rank_global[res.offset + i] for i in range(n) if res.offset + i in rank_global}
        idx = list(range(n))
        class_ids = detection_class_ids(dets, idx, rank_of, self.threshold)
        log_detections(rec, dets, idx, class_ids, rank_of)
        log_masks(rec, dets, idx, class_ids, frame.depth.shape[:2])
        for i, r in rank_of.items():  # a detection of this frame entered the K nearest at rank r
            patch = res.patches[i] if i < len(res.patches) else None
            if patch is not None and patch.size:
                log_patch(rec, r, dets, i, patch)
        for e in res.events:
            rec.log("/log", rr.TextLog(str(e.message), level=_LEVELS.get(e.level, rr.TextLogLevel.INFO)))
        if rank_of:
            text = "; ".join(f"★{r} {describe_detection(dets, i)}"
                             for i, r in sorted(rank_of.items(), key=lambda x: x[1]))
            rec.log("/log", rr.TextLog(f"new among the K={self.k} nearest so far: {text}",
                                       level=rr.TextLogLevel.DEBUG))
        for level, text in notes:
            rec.log("/log", rr.TextLog(text, level=_LEVELS.get(level, rr.TextLogLevel.INFO)))
        if res.running_estimate >= 0:
            rec.log("/predictions/running_estimate", rr.Scalars(float(res.running_estimate)))
        spent = time.perf_counter() - t0  # (what follows is a few scalars)
        for stage, seconds in {**res.timings, **(latency or {})}.items():
            # overhead and total include this logging, which only now is known
            rec.log(f"/latency/{stage}", rr.Scalars(1000.0 * (seconds + (spent if stage in ("overhead", "total")
                                                                          else 0.0))))
        rec.log("/latency/log", rr.Scalars(1000.0 * spent))
        self.frames += 1
        return spent

    def note(self, text: str, level: str = "info") -> None:
        self.rec.log("/log", rr.TextLog(text, level=_LEVELS.get(level, rr.TextLogLevel.INFO)))

    # ------------------------------------------------------------------------------------------------------ end
    def close(self, trace: Trace | None, *, timings: dict | None = None, summary: str = "") -> None:
        """Log the end of the session (``trace`` None: an aborted session) and finish the outputs: the .rrd is
        renamed into place only here, so an aborted session leaves no half-written file."""
        try:
            if trace is not None:
                self.rec.reset_time()
                log_predictions(self.rec, trace)
                if summary:
                    self.rec.log("/summary", rr.TextDocument(_summary_doc(trace, summary),
                                                             media_type=rr.MediaType.MARKDOWN), static=True)
                else:
                    log_summary(self.rec, trace)
                log_timings(self.rec, {**trace.timings, **(timings or {})}, len(trace.frames))
            try:
                self.rec.flush()
            except RuntimeError as err:
                raise MassvizError(f"could not deliver the live session to the Rerun viewer ({err}); log to a file "
                                   "with --rrd and open it with 'rerun FILE.rrd'") from None
        except BaseException as err:
            self._finish(err)
            raise
        self._finish(None if trace is not None else MassvizError("session aborted"))

    def abort(self, err: BaseException) -> None:
        """End without finishing: nothing is left at the .rrd path."""
        self._finish(err)

    def _finish(self, err: BaseException | None) -> None:
        if self._own:
            self.rec.disconnect()
        if err is None:
            self._stack.close()
        else:
            with contextlib.suppress(BaseException):
                self._stack.__exit__(type(err), err, err.__traceback__)


def _summary_doc(trace: Trace, live: str) -> str:
    from massviz.views.rerun_log import summary_markdown

    return summary_markdown(trace) + "\n## Live session\n\n" + live + "\n"


__all__ = ["LiveLogger"]
