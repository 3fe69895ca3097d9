"""A trace -> a Rerun recording stream: what ``massviz log`` shows, from the trace and the recording's frames.
``TraceLogger`` is the sink: it is given each frame's ``FrameResult`` and the final trace; it never runs the pipeline,
filters, crops or measures (``massviz.runners.logged.log_run`` runs the pipeline with it). ``log_trace_with_clouds``
logs a finished trace with the clouds it is given (``massviz.runners.trace_to_rerun.log_trace`` measures and gives them)."""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import rerun as rr
from tqdm.auto import tqdm

from massviz.core.trace import FrameResult, Trace, frame_results
from massviz.errors import MassvizError
from massviz.views.rerun.blueprint import blueprint_for
from massviz.views.rerun.entities import (
    MAX_POINTS,
    POINT_STEP,
    PatchTiles,
    RgbLogger,
    detection_class_ids,
    log_annotation_context,
    log_cloud_overlays,
    log_detection_clouds,
    log_detections,
    log_events,
    log_flags,
    log_masks,
    log_predictions,
    log_running,
    log_summary,
    log_timings,
    text_log,
)
from massviz.views.rerun.frame_logger import FrameLogger
from massviz.views.rerun.output import Output


def _check_match(trace: Trace, recording) -> None:
    w, h = trace.recording.width, trace.recording.height
    if (w, h) != (recording.width, recording.height):
        raise MassvizError(f"the trace was made on {w}x{h} frames but this recording is "
                           f"{recording.width}x{recording.height}", recording.path)
    if len(trace.frames) and int(np.max(trace.frames)) >= recording.num_frames:
        raise MassvizError(f"the trace has frame {int(np.max(trace.frames))} but the recording has "
                           f"{recording.num_frames} frames", recording.path)


class TraceLogger:
    """Logs one run of the pipeline to ``stream`` in one pass over the frames: ``on_frame(frame, result, clouds)``
    logs what needs the frame (``FrameLogger``: its time, the camera, its RGB and depth as the reader read them, its
    points; the patches of the detections entering the running selection, the clouds of the detections above the
    threshold as the measure stage made them) as the pipeline processes it (``massviz.core.pipeline.run``'s read-only
    observer, so no frame is read twice; for a finished trace, e.g. one from the cache, the caller passes
    ``trace_frames``), and ``finish(trace)`` logs what needs the whole trace (ranks, chosen patches, predictions,
    flags, decisions, summary, timings, the layout), reading no frame.

    ``video``, ``points``, ``step``, ``max_points``, ``clouds``: see ``log_trace_with_clouds``.
    """

    def __init__(self, recording, stream: rr.RecordingStream, *, video: str = "auto", points: bool = False,
                 step: int = POINT_STEP, max_points: int = MAX_POINTS, clouds: bool = True, blueprint=None):
        self.recording, self.stream = recording, stream
        if blueprint is not None:  # a layout first, as a viewer expects it (``finish`` sends the trace's own)
            stream.send_blueprint(blueprint, make_active=True, make_default=True)
        self.intr = recording.intrinsics
        self.rgb = RgbLogger(recording, video)
        self.frame_logger = FrameLogger(stream, self.intr, self.rgb, points=points, step=step, max_points=max_points)
        self.clouds = clouds and self.intr is not None
        self.cloud_paths: dict[int, str] = {}
        self.patches: dict[int, np.ndarray] = {}  # RGB patches of the running K nearest's entrants
        self.seconds = 0.0
        self._pending: tuple[int, dict] | None = None  # (frame, its clouds), logged with the next frame's Clear
        stream.send_recording_name(f"massviz {recording.id}")
        self.rgb.log_static(stream)

    @property
    def frames(self) -> int:
        """How many frames were logged."""
        return self.frame_logger.frames

    # ------------------------------------------------------------------------------------------------ per frame
    def on_frame(self, frame, result: FrameResult, clouds: dict | None = None) -> None:
        """Log one processed frame (``result.frame``, which is ``frame``) and its ``FrameResult`` (the pipeline's, or
        ``trace_frames``' for a finished trace). ``clouds``: {detection index: cleaned cloud} of the frame's
        detections above the selection's threshold, as the measure stage made them
        (``massviz.measure3d.stage.MeasureStage``), logged with ``clouds=True``; None: no cloud."""
        t0 = time.perf_counter()
        for g, i in self.frame_logger.log(result).items():
            patch = result.patches[i]
            if patch is not None and patch.size:
                self.patches[g] = patch
        if self.clouds:
            # the last frame's clouds go out now, each with its Clear at this frame in one chunk
            self._send_clouds(cleared_at=frame.index)
            self._pending = (frame.index, clouds or {})
        self.seconds += time.perf_counter() - t0

    def _send_clouds(self, cleared_at: int | None) -> None:
        """Log the clouds held back from the last frame (shown from that frame until ``cleared_at``; None: to the
        end)."""
        if self._pending is not None:
            shown_at, clouds = self._pending
            self.cloud_paths.update(log_detection_clouds(self.stream, clouds, frame=shown_at, cleared_at=cleared_at))
            self._pending = None

    # ------------------------------------------------------------------------------------------------------ end
    def finish(self, trace: Trace, *, points: bool = False, layout: bool = True,
               timed_from: float | None = None) -> dict:
        """Log what needs the whole trace (no frame is read), ``/timings`` (the trace's and ``log``: this logger's
        own seconds, or with ``timed_from``, a ``time.perf_counter()``, the wall seconds since then) and, with
        ``layout``, its layout (``blueprint_for``); returns the stats of ``log_trace_with_clouds``."""
        t0 = time.perf_counter()
        self._send_clouds(cleared_at=None)
        stream, dets = self.stream, trace.detections
        frames = [int(f) for f in trace.frames]
        first = frames[0] if frames else 0
        rank_of = {int(i): r for r, i in enumerate(trace.selection)}
        flag_of = {p.detection: p for p in trace.flags.patches}
        if layout:
            stream.send_blueprint(blueprint_for(trace, self.recording, points=points), make_active=True,
                                  make_default=True)
        log_opening(stream, trace)
        notes = []
        if self.intr is None:
            notes.append("no camera intrinsics for this recording: no /camera Pinhole, no 3D view")
        if self.rgb.warning:
            notes.append(self.rgb.warning)
        if trace.estimate < 0 and not any(e.kind == "not_estimated" for e in trace.events):
            notes.append("not estimated: no detection with depth was selected")
        stream.set_time("frame", sequence=first)
        for note in notes:
            stream.log("/log", text_log(note, "warn"))
        log_overlays(stream, trace, masks_shape=(trace.recording.height or self.recording.height,
                                                 trace.recording.width or self.recording.width))
        # each tile shows the patch holding its rank at every frame: logged where the running selection changes
        tiles = PatchTiles(lambda i: (dets, i, dets.patches[i] if dets.patches[i] is not None else self.patches.get(i),
                                      flag_of.get(i)))
        for f, selection in zip(frames, trace.running_selections()):
            stream.set_time("frame", sequence=f)
            tiles.update(stream, selection)
        if self.cloud_paths:
            log_cloud_overlays(stream, trace, self.cloud_paths)
        log_conclusion(stream, trace)
        self.seconds += time.perf_counter() - t0
        log_timings(stream, {**trace.timings, "log": self.seconds if timed_from is None
                             else time.perf_counter() - timed_from}, len(frames))
        return {"frames": len(frames), "detections": len(dets), "chosen": len(rank_of),
                "points": self.frame_logger.n_points, "clouds": len(self.cloud_paths), "rgb": self.rgb.mode,
                "notes": notes}


# ------------------------------------------------------------------------------------- what every trace path logs
# The one way a finished trace reaches Rerun, shared by ``massviz log`` (``TraceLogger.finish``), the dataset's light
# recordings (``massviz.views.rerun_dataset.log_light``) and ``massviz live`` (``massviz.views.rerun.live_logger``).
def log_opening(stream: rr.RecordingStream, trace: Trace) -> None:
    """The annotation classes for the trace's K and ``/summary``."""
    log_annotation_context(stream, trace.k)
    log_summary(stream, trace)


def log_overlays(stream: rr.RecordingStream, trace: Trace, *, masks_shape: tuple[int, int] | None = None) -> None:
    """``/camera/detections`` of every processed frame at its frame (chosen ranks, flagged, below the threshold:
    ``Trace.active``) and, with ``masks_shape`` (height, width), ``/camera/masks``."""
    dets = trace.detections
    rank_of = {int(i): r for r, i in enumerate(trace.selection)}
    flagged = frozenset(p.detection for p in trace.flags.flagged)
    by_frame = {f: idx.tolist() for f, idx in dets.indices_by_frame().items()}
    active = trace.active()
    for f in (int(f) for f in trace.frames):
        stream.set_time("frame", sequence=f)
        idx = by_frame.get(f, [])
        class_ids = detection_class_ids(dets, idx, rank_of, active, flagged)
        log_detections(stream, dets, idx, class_ids, rank_of)
        if masks_shape is not None:
            log_masks(stream, dets, idx, class_ids, masks_shape)


def log_conclusion(stream: rr.RecordingStream, trace: Trace, *, running: bool = True, events: bool = True) -> None:
    """``/predictions`` (chosen predictions, estimate, without the flagged), with ``running`` the running estimate,
    with ``events`` the trace's decisions in ``/log``, then the flags' ``/log`` entries; the stream's time reset
    before and after. ``massviz live`` has logged the running estimate and the decisions as they came."""
    stream.reset_time()
    log_predictions(stream, trace)
    if running:
        log_running(stream, trace)
    if events:
        log_events(stream, trace.events, int(trace.frames[0]) if len(trace.frames) else 0)
    log_flags(stream, trace)
    stream.reset_time()


def trace_frames(trace: Trace, recording, *, progress: bool = False, frames=None):
    """(frame, ``FrameResult``, clouds) of each of ``trace``'s processed frames (``massviz.core.trace.frame_results``):
    what a ``TraceLogger`` is given for a trace that did not come from a run it observed. ``frames``: (frame, its
    clouds) pairs of the processed frames, in order, as the measure stage replays them
    (``MeasureStage.replay_frames``); None: the frames read from ``recording`` once, without clouds."""
    _check_match(trace, recording)
    indices = [int(f) for f in trace.frames]
    if frames is None:
        frames = ((frame, None) for frame in recording.frames(indices=indices))
    clouds_of: dict = {}

    def only_frames():
        for frame, clouds in frames:
            clouds_of[frame.index] = clouds
            yield frame

    bar = tqdm(only_frames(), total=len(indices), desc=f"{recording.id} → rerun", unit="frame", file=sys.stderr,
               disable=not progress, leave=False)
    try:
        for frame, result in frame_results(trace, bar):
            yield frame, result, clouds_of.pop(frame.index)
    finally:
        bar.close()


def log_trace_with_clouds(trace: Trace, recording, *, rrd: str | Path | None = None, spawn: bool = False,
                          stream: rr.RecordingStream | None = None, progress: bool = False,
                          max_points: int = MAX_POINTS, step: int = POINT_STEP, video: str = "auto",
                          clouds: bool = True, points: bool = False, frames=None) -> dict:
    """Log ``trace`` (made on ``recording``) to Rerun with the clouds it is given (``frames``); the entity tree is in
    ``massviz.views.rerun``'s docstring.

    Outputs: ``rrd`` (a file, written atomically: nothing is left at ``rrd`` if logging fails), ``spawn`` (spawn
    or connect to a viewer on the default port), both, or ``stream`` (a caller's ``rr.RecordingStream``, e.g. a
    notebook's inline viewer; its sinks are left as they are and it is not disconnected). Each call logs a new
    recording of application ``massviz`` on its own ``RecordingStream`` (never the global one).

    ``video``: how an mp4 is logged (see ``RgbLogger``). ``points``: also log ``/world/points`` (RGB-coloured
    points; by default Rerun back-projects ``/camera/depth`` itself, which keeps the recording small);
    ``step``/``max_points``: their subsampling.
    ``clouds``: also log each detection's Open3D cloud under ``/world/detections``; ``frames``: the processed frames
    with those clouds, (frame, {detection: cloud}) pairs as the measure stage replays them
    (``massviz.measure3d.stage.MeasureStage(recording, clouds="active").replay_frames(trace)``; without them, no cloud
    is logged: a view makes none). ``massviz.log_trace`` passes them.

    Returns stats: ``recording_id``, ``frames``, ``detections``, ``chosen``, ``points``, ``clouds``, ``rgb``
    ("asset", "images" or "files"), ``notes`` (warnings also in /log), ``log_seconds`` (wall time of logging,
    flushing included), ``rrd`` (path or None).
    """
    _check_match(trace, recording)
    with Output(rrd=rrd, spawn=spawn, stream=stream) as out:
        logger = TraceLogger(recording, out.stream, video=video, points=points, step=step, max_points=max_points,
                             clouds=clouds, blueprint=blueprint_for(trace, recording, points=points))
        for frame, result, frame_clouds in trace_frames(trace, recording, progress=progress, frames=frames):
            logger.on_frame(frame, result, frame_clouds)
        stats = logger.finish(trace, layout=False, timed_from=out.opened)
    stats.update(out.stats(), log_seconds=out.seconds)
    return stats


__all__ = ["TraceLogger", "log_trace_with_clouds", "trace_frames", "log_opening", "log_overlays",
           "log_conclusion"]
