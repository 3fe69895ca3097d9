"""One processed frame -> Rerun: what ``massviz log`` (``trace_logger.TraceLogger``) and ``massviz live``
(``live_logger.LiveLogger``) both log of a frame and its ``FrameResult`` as it is processed. A sink: it reads the frame
and the result; it runs no stage."""
from __future__ import annotations

import rerun as rr

from massviz.core.trace import FrameResult
from massviz.core.types import Intrinsics
from massviz.views.rerun.entities import (
    MAX_POINTS,
    POINT_STEP,
    RgbLogger,
    frustum_depth,
    log_depth,
    log_pinhole,
    log_points,
)


def entrants(result: FrameResult) -> dict[int, int]:
    """The detections of ``result`` that are in its running K nearest: {index in the trace: index in the frame's
    detections}."""
    return {int(g): int(g) - result.offset for g in result.selection[result.selection >= result.offset]}


class FrameLogger:
    """Logs each processed frame to ``stream`` (``log``), at its index on the ``frame`` timeline (also on
    ``video_time`` when ``rgb`` logs a video asset, and on ``capture_time`` when given): the ``/camera`` ``Pinhole``
    at the first frame (only with ``intrinsics``), ``/camera/rgb`` (``rgb``, an ``RgbLogger``), ``/camera/depth``
    (the frame's PNG bytes as the reader read them, else its array) and, with ``points``, ``/world/points`` (every
    ``step``-th pixel, at most ``max_points``; only with intrinsics). ``frames``: how many frames were logged;
    ``n_points``: how many points."""

    def __init__(self, stream: rr.RecordingStream, intrinsics: Intrinsics | None, rgb: RgbLogger, *,
                 points: bool = False, step: int = POINT_STEP, max_points: int = MAX_POINTS):
        self.stream, self.intrinsics, self.rgb = stream, intrinsics, rgb
        self.points, self.step, self.max_points = points and intrinsics is not None, step, max_points
        self.frames = 0
        self.n_points = 0

    def log(self, result: FrameResult, *, capture_s: float | None = None) -> dict[int, int]:
        """Log ``result.frame``; ``capture_s``: its seconds since the first frame (``capture_time``). Returns
        ``entrants(result)``: the detections whose patches the running K nearest now holds."""
        stream, frame = self.stream, result.frame
        stream.set_time("frame", sequence=frame.index)
        ns = self.rgb.video_time_ns(frame.index)
        if ns is not None:
            stream.set_time("video_time", duration=ns * 1e-9)
        if capture_s is not None:
            stream.set_time("capture_time", duration=capture_s)
        if self.intrinsics is not None and self.frames == 0:
            log_pinhole(stream, self.intrinsics, frustum_depth(frame.depth))
        self.frames += 1
        self.rgb.log_frame(stream, frame)
        log_depth(stream, frame.depth, frame.depth_encoded)
        if self.points:
            self.n_points += log_points(stream, frame.depth, frame.rgb, self.intrinsics, self.step, self.max_points)
        return entrants(result)


__all__ = ["FrameLogger", "entrants"]
