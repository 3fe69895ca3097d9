"""Log a live session to Rerun frame by frame, as ``massviz live`` computes it (the entity tree of ``massviz.views.rerun``).

``LiveLogger.log_step`` is called once per processed frame with that frame's step result (``FrameResult`` of
``massviz.core.pipeline``: the frame, its detections with d/a/b/pred, the K nearest so far and the running
estimate, the stage timings) and logs it at once on the ``frame`` timeline (sequence = index of the processed frame)
and on ``capture_time`` (seconds since the first frame, from the camera's timestamps):

- ``/camera/rgb`` (JPEG ``EncodedImage``), ``/camera/depth`` (``DepthImage``: the 3D view back-projects it through the
  ``/camera`` ``Pinhole``; ``/world/points`` is not logged live unless ``points=True``: an Open3D back-projection
  per frame and 2-3x the .rrd size, see benchmarks/live_latency.py), ``/camera/detections`` and ``/camera/masks``
  (the K nearest *so far* marked ★rank), ``/patches/<rank>`` (``PatchTiles``: every rank whose occupant changed,
  when the K nearest change, so each tile shows the current K nearest);
- ``/predictions/running_estimate`` (the mean of the K nearest so far) each frame;
- ``/latency/<stage>`` (ms): ``read`` (aligning and copying the newest frame), ``detect``, ``features``,
  ``predict``, ``select``, ``log`` (this logging), ``wait`` (the frame's time in the one-frame buffer while the
  previous one was processed), ``total`` (arrival to logged) and ``overhead`` (read + features + select + log:
  massviz's own work beyond detect and predict);
- ``/log``: skipped detections, changes of the K nearest, dropped frames.

What each frame shares with ``massviz log`` (its time, the camera, RGB, depth, points) is logged by the one
per-frame mapping, ``massviz.views.rerun.frame_logger.FrameLogger``.

``close(trace, ...)`` logs what only the end knows: the flags (at the last processed frame, each flagged patch's tile
again with its flag), then, as every path from a trace to Rerun does (``trace_logger.log_conclusion``),
``/predictions/patch_<rank>``, ``/predictions/estimate`` and the flag warnings in ``/log``; ``/summary`` and
``/timings``. This module reads results only; it runs no stage.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import rerun as rr

from massviz.core.trace import Trace, describe_detection
from massviz.core.types import Intrinsics
from massviz.errors import MassvizError
from massviz.views.rerun.blueprint import default_blueprint
from massviz.views.rerun.entities import (
    RUNNING_COLOUR,
    PatchTiles,
    RgbLogger,
    detection_class_ids,
    log_annotation_context,
    log_detections,
    log_masks,
    log_patch,
    log_summary,
    log_timings,
    summary_markdown,
    text_log,
)
from massviz.views.rerun.frame_logger import FrameLogger
from massviz.views.rerun.output import Output
from massviz.views.rerun.trace_logger import log_conclusion


class LiveLogger:
    """Rerun output of a live session: ``rrd`` (file, written atomically at ``close``), ``spawn`` (a native
    viewer), ``connect`` (a running viewer or server's gRPC URL) — any combination — or ``stream`` (a caller's).
    ``k``: the selection's K (the layout's tiles, before the first frame); everything else comes with each frame's
    ``FrameResult`` and the final trace."""

    def __init__(self, *, name: str, k: int, intrinsics: Intrinsics | None,
                 rrd: str | Path | None = None, spawn: bool = False, connect: str | None = None,
                 stream: rr.RecordingStream | None = None, jpeg_quality: int = 85, points: bool = False):
        if stream is None and rrd is None and not spawn and not connect:
            raise ValueError("nothing to log to: give rrd, spawn, connect or stream")
        self.k, self.intrinsics = k, intrinsics
        self.out = Output(rrd=rrd, spawn=spawn, connect=connect, stream=stream)
        self.rrd = self.out.rrd
        self.stream = self.out.stream
        try:  # an error or a signal from here on: nothing is left at the .rrd path
            # each frame's RGB as a JPEG (a camera's frames have no file); /world/points as massviz log logs them
            # (costly; off by default)
            self.frame_logger = FrameLogger(self.stream, intrinsics,
                                            RgbLogger(None, "images", jpeg_quality=jpeg_quality), points=points)
            self.stream.send_recording_name(f"massviz live {name}")
            self._size = None if intrinsics is None else (int(intrinsics.width), int(intrinsics.height))
            self.stream.send_blueprint(default_blueprint(k, has_3d=intrinsics is not None, image_size=self._size),
                                       make_active=True, make_default=True)
            log_annotation_context(self.stream, k)
            self.stream.log("/predictions/running_estimate", rr.SeriesLines(
                names="running estimate (K nearest so far)", colors=RUNNING_COLOUR, widths=2), static=True)
        except BaseException as err:
            self.out.close(err)
            raise
        self._t0_ms: float | None = None
        self._held: dict[int, tuple] = {}  # trace index -> (detections, index, patch, flag) of the K nearest so far
        self.tiles = PatchTiles(self._held_source)

    # ------------------------------------------------------------------------------------------------ per frame
    def log_step(self, res, *, latency: dict | None = None, timestamp_ms: float | None = None,
                 notes: list[tuple[str, str]] = ()) -> float:
        """Log one processed frame (``res``: a ``FrameResult``); ``latency``: extra per-frame seconds
        (e.g. ``total``, ``overhead``); ``notes``: (level, text) for ``/log``. Returns the seconds logging took."""
        t0 = time.perf_counter()
        stream, frame, dets = self.stream, res.frame, res.detections
        if timestamp_ms is not None:
            self._t0_ms = timestamp_ms if self._t0_ms is None else self._t0_ms
        entered = self.frame_logger.log(res, capture_s=None if timestamp_ms is None
                                        else (timestamp_ms - self._t0_ms) / 1000.0)
        n = len(dets)
        rank_global = {int(g): r for r, g in enumerate(res.selection)}
        rank_of = {i: rank_global[g] for g, i in entered.items()}
        idx = list(range(n))
        active = np.zeros(n, dtype=bool)
        active[np.asarray(res.active, dtype=np.int64)] = True  # above the selection's threshold (the step's)
        class_ids = detection_class_ids(dets, idx, rank_of, active)
        log_detections(stream, dets, idx, class_ids, rank_of)
        log_masks(stream, dets, idx, class_ids, frame.depth.shape[:2])
        for g, i in entered.items():  # a detection of this frame entered the K nearest: keep what its tile shows
            self._held[g] = (dets, i, res.patches[i] if i < len(res.patches) else None, None)
        self._held = {g: v for g, v in self._held.items() if g in rank_global}
        self.tiles.update(stream, res.selection)  # every rank whose occupant changed (entered or moved), now
        for e in res.events:
            stream.log("/log", text_log(e.message, e.level))
        if rank_of:
            text = "; ".join(f"★{r} {describe_detection(dets, i)}"
                             for i, r in sorted(rank_of.items(), key=lambda x: x[1]))
            stream.log("/log", text_log(f"new among the K={self.k} nearest so far: {text}", "debug"))
        for level, text in notes:
            stream.log("/log", text_log(text, level))
        if res.running_estimate >= 0:
            stream.log("/predictions/running_estimate", rr.Scalars(float(res.running_estimate)))
        spent = time.perf_counter() - t0  # (what follows is a few scalars)
        for stage, seconds in {**res.timings, **(latency or {})}.items():
            # overhead and total include this logging, which only now is known
            stream.log(f"/latency/{stage}", rr.Scalars(1000.0 * (seconds + (spent if stage in ("overhead", "total")
                                                                             else 0.0))))
        stream.log("/latency/log", rr.Scalars(1000.0 * spent))
        return spent

    @property
    def frames(self) -> int:
        """How many frames were logged."""
        return self.frame_logger.frames

    def _held_source(self, i: int) -> tuple:
        return self._held[int(i)]

    def note(self, text: str, level: str = "info") -> None:
        self.stream.log("/log", text_log(text, level))

    # ------------------------------------------------------------------------------------------------------ end
    def close(self, trace: Trace | None, *, timings: dict | None = None, summary: str = "") -> None:
        """Log the end of the session (``trace`` None: an aborted session) and finish the outputs: the .rrd is
        renamed into place only here, so an aborted session leaves no half-written file."""
        try:
            if trace is not None:
                self._log_final_flags(trace)
                # the predictions and the flags' /log entries as every trace path logs them (the running estimate
                # and the decisions were logged as they came)
                log_conclusion(self.stream, trace, running=False, events=False)
                if summary:
                    self.stream.log("/summary", rr.TextDocument(_summary_doc(trace, summary),
                                                                media_type=rr.MediaType.MARKDOWN), static=True)
                else:
                    log_summary(self.stream, trace)
                log_timings(self.stream, {**trace.timings, **(timings or {})}, len(trace.frames))
            self.out.flush("the live session")
        except BaseException as err:
            self._finish(err)
            raise
        self._finish(None if trace is not None else MassvizError("session aborted"))

    def _log_final_flags(self, trace: Trace) -> None:
        """The flags are known when the session ends (they need its last frames): at the last processed frame, each
        tile of a flagged patch is logged again with its flag (outline and label in the flagged colour, ``flagged``
        true), as ``massviz log`` shows them (``/log`` gets the flag warnings from ``log_conclusion``)."""
        if not trace.flags.flagged or not len(trace.frames):
            return
        self.stream.set_time("frame", sequence=int(trace.frames[-1]))
        dets = trace.detections
        for rank, i in enumerate(trace.selection):
            flag = trace.flags.of(int(i))
            if flag is None or not flag.flagged:
                continue
            held = self._held.get(int(i))
            patch = dets.patches[int(i)] if dets.patches[int(i)] is not None else (held[2] if held else None)
            if patch is not None and patch.size:
                log_patch(self.stream, rank, dets, int(i), patch, flag)
        # the layout's tile titles say it too ("★0 ⚑ flagged"), as in massviz log's layout
        self.stream.send_blueprint(default_blueprint(self.k, has_3d=self.intrinsics is not None,
                                                     image_size=self._size,
                                                     flagged=[p.rank for p in trace.flags.flagged]),
                                   make_active=True, make_default=True)

    def abort(self, err: BaseException) -> None:
        """End without finishing: nothing is left at the .rrd path."""
        self._finish(err)

    def _finish(self, err: BaseException | None) -> None:
        self.out.close(err)


def _summary_doc(trace: Trace, live: str) -> str:
    return summary_markdown(trace) + "\n## Live session\n\n" + live + "\n"


__all__ = ["LiveLogger"]
