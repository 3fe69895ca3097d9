"""A trace -> a Rerun recording stream (``log_trace``): what ``massviz log`` shows, from the trace and the
recording's frames; it never runs the detector or the model."""
from __future__ import annotations

import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import rerun as rr
from tqdm.auto import tqdm

from massviz.errors import MassvizError
from massviz.core.patches import crop
from massviz.core.trace import Trace
from massviz.views.rerun.blueprint import blueprint_for, default_blueprint
from massviz.views.rerun.entities import (CLOUD_VOXEL_M, MAX_POINTS, POINT_STEP, PatchTiles, RgbLogger,
                                          detection_class_ids, frustum_depth, log_annotation_context,
                                          log_cloud_overlays, log_depth, log_detection_clouds, log_detections,
                                          log_events, log_flags, log_masks, log_pinhole, log_points,
                                          log_predictions, log_running, log_summary, log_timings, text_log)
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
    logs what needs the frame (its RGB and depth as the reader read them, the camera, the detections' clouds as the
    measure stage made them) as the pipeline processes it (``massviz.core.pipeline.run``'s read-only observer, so no
    frame is read twice), ``replay(trace)`` does the same pass over a finished trace's frames (a trace from the
    cache), and ``finish(trace)`` logs what needs the whole trace (ranks, chosen patches, predictions, flags,
    decisions, summary, the layout), reading no frame.

    ``video``, ``points``, ``step``, ``max_points``, ``clouds``: see ``log_trace``.
    """

    def __init__(self, recording, stream: rr.RecordingStream, *, video: str = "auto", points: bool = False,
                 step: int = POINT_STEP, max_points: int = MAX_POINTS, clouds: bool = True,
                 blueprint=None):
        self.recording, self.rec = recording, stream
        if blueprint is not None:  # a layout first, as a viewer expects it (``finish`` sends the trace's own)
            stream.send_blueprint(blueprint, make_active=True, make_default=True)
        self.intr = recording.intrinsics
        self.rgb = RgbLogger(recording, video)
        self.points, self.step, self.max_points = points and self.intr is not None, step, max_points
        self.clouds = clouds and self.intr is not None
        self.frames: list[int] = []
        self.cloud_paths: dict[int, str] = {}
        self.patches: dict[int, np.ndarray] = {}  # RGB patches of the running K nearest's entrants
        self.n_points = 0
        self.seconds = 0.0
        self._shown: list[str] = []
        self._trace: Trace | None = None
        self._tile_detections: dict[int, set] = {}
        self.rec.send_recording_name(f"massviz {recording.id}")
        self.rgb.log_static(self.rec)

    # ------------------------------------------------------------------------------------------------ per frame
    def on_frame(self, frame, result=None, clouds: dict | None = None) -> None:
        """Log one processed frame. ``result``: its ``FrameResult`` (during the pipeline's run); None during
        ``replay`` (the detections come from the trace). ``clouds``: {detection index: cleaned cloud} of the frame's
        detections above the selection's threshold (``massviz.measure.stage.MeasureStage``), logged with
        ``clouds=True``."""
        t0 = time.perf_counter()
        rec = self.rec
        rec.set_time("frame", sequence=frame.index)
        ns = self.rgb.video_time_ns(frame.index)
        if ns is not None:
            rec.set_time("video_time", duration=ns * 1e-9)
        if self.intr is not None and not self.frames:
            log_pinhole(rec, self.intr, frustum_depth(frame.depth))
        self.frames.append(frame.index)
        self.rgb.log_frame(rec, frame)
        log_depth(rec, frame.depth, frame.depth_encoded)
        if self.points:
            self.n_points += log_points(rec, frame.depth, frame.rgb, self.intr, self.step, self.max_points)
        if result is not None:
            for g in result.selection[result.selection >= result.offset]:  # entered the running K nearest
                patch = result.patches[int(g) - result.offset]
                if patch is not None and patch.size:
                    self.patches[int(g)] = patch
        else:
            trace_dets = self._trace.detections
            for i in self._tile_detections.get(frame.index, ()):  # the trace keeps the nearest patches; crop others
                if trace_dets.patches[i] is None:
                    self.patches[i] = crop(frame.rgb, trace_dets.xyxy[i])
        if self.clouds:
            for path in self._shown:
                rec.log(path, rr.Clear(recursive=True))
            paths = log_detection_clouds(rec, clouds or {}, voxel_m=CLOUD_VOXEL_M)
            self.cloud_paths.update(paths)
            self._shown = list(paths.values())
        self.seconds += time.perf_counter() - t0

    def replay(self, trace: Trace, *, progress: bool = False, frames=None) -> None:
        """The per-frame pass over ``trace``'s processed frames (a trace that did not come from a run observed by
        ``on_frame``): ``frames``, (frame, its clouds) pairs (``MeasureStage.replay_frames``), else the frames read
        from the recording once, without clouds."""
        _check_match(trace, self.recording)
        self._trace = trace
        self._tile_detections = defaultdict(set)  # frame -> detections that hold a tile at some frame
        for i in {int(i) for sel in trace.running_selections() for i in sel}:
            self._tile_detections[int(trace.detections.frame[i])].add(i)
        indices = [int(f) for f in trace.frames]
        if frames is None:
            frames = ((frame, None) for frame in self.recording.frames(indices=indices))
        bar = tqdm(frames, total=len(indices), desc=f"{self.recording.id} → rerun", unit="frame", file=sys.stderr,
                   disable=not progress, leave=False)
        try:
            for frame, clouds in bar:
                self.on_frame(frame, clouds=clouds)
        finally:
            bar.close()

    # ------------------------------------------------------------------------------------------------------ end
    def finish(self, trace: Trace, *, points: bool = False, layout: bool = True) -> dict:
        """Log what needs the whole trace (no frame is read) and, with ``layout``, its layout (``blueprint_for``);
        returns the stats of ``log_trace``."""
        t0 = time.perf_counter()
        rec, dets = self.rec, trace.detections
        frames = [int(f) for f in trace.frames]
        first = frames[0] if frames else 0
        rank_of = {int(i): r for r, i in enumerate(trace.selection)}
        flag_of = {p.detection: p for p in trace.flags.patches}
        flagged = frozenset(p.detection for p in trace.flags.flagged)
        by_frame: dict[int, list[int]] = defaultdict(list)
        for i, f in enumerate(dets.frame):
            by_frame[int(f)].append(i)
        if layout:
            rec.send_blueprint(blueprint_for(trace, self.recording, points=points), make_active=True,
                               make_default=True)
        log_annotation_context(rec, trace.k)
        log_summary(rec, trace)
        notes = []
        if self.intr is None:
            notes.append("no camera intrinsics for this recording: no /camera Pinhole, no 3D view")
        if self.rgb.warning:
            notes.append(self.rgb.warning)
        if trace.estimate < 0 and not any(e.kind == "not_estimated" for e in trace.events):
            notes.append("not estimated: no detection with depth was selected")
        rec.set_time("frame", sequence=first)
        for note in notes:
            rec.log("/log", text_log(note, "warn"))
        shape = (trace.recording.height or self.recording.height, trace.recording.width or self.recording.width)
        for f in frames:
            rec.set_time("frame", sequence=f)
            idx = by_frame.get(f, [])
            class_ids = detection_class_ids(dets, idx, rank_of, trace.threshold, flagged)
            log_detections(rec, dets, idx, class_ids, rank_of)
            log_masks(rec, dets, idx, class_ids, shape)
        # each tile shows the patch holding its rank at every frame: logged where the running selection changes
        tiles = PatchTiles(lambda i: (dets, i, dets.patches[i] if dets.patches[i] is not None else self.patches.get(i),
                                      flag_of.get(i)))
        for f, selection in zip(frames, trace.running_selections()):
            rec.set_time("frame", sequence=f)
            tiles.update(rec, selection)
        if self.cloud_paths:
            log_cloud_overlays(rec, trace, self.cloud_paths)
        rec.reset_time()
        log_predictions(rec, trace)
        log_running(rec, trace)
        log_events(rec, trace.events, first)
        log_flags(rec, trace)
        rec.reset_time()
        self.seconds += time.perf_counter() - t0
        return {"frames": len(frames), "detections": len(dets), "chosen": len(rank_of), "points": self.n_points,
                "clouds": len(self.cloud_paths), "rgb": self.rgb.mode, "notes": notes}


def log_trace(trace: Trace, recording, *, rrd: str | Path | None = None, spawn: bool = False,
              stream: rr.RecordingStream | None = None, progress: bool = False, max_points: int = MAX_POINTS,
              step: int = POINT_STEP, video: str = "auto", clouds: bool = True, points: bool = False,
              frames=None) -> dict:
    """Log ``trace`` (made on ``recording``) to Rerun; the entity tree is in ``massviz.views.rerun``'s docstring.

    Outputs: ``rrd`` (a file, written atomically: nothing is left at ``rrd`` if logging fails), ``spawn`` (spawn
    or connect to a viewer on the default port), both, or ``stream`` (a caller's ``rr.RecordingStream``, e.g. a
    notebook's inline viewer; its sinks are left as they are and it is not disconnected). Each call logs a new
    recording of application ``massviz`` on its own ``RecordingStream`` (never the global one).

    ``video``: how an mp4 is logged (see ``RgbLogger``). ``points``: also log ``/world/points`` (RGB-coloured
    points; by default Rerun back-projects ``/camera/depth`` itself, which keeps the recording small);
    ``step``/``max_points``: their subsampling.
    ``clouds``: also log each detection's Open3D cloud under ``/world/detections``; ``frames``: the processed frames
    with those clouds, (frame, {detection: cloud}) pairs as the measure stage replays them
    (``massviz.measure.stage.MeasureStage(recording, clouds="active").replay_frames(trace)``; without them, no cloud
    is logged: a view makes none). ``massviz.log_trace`` passes them.

    Returns stats: ``recording_id``, ``frames``, ``detections``, ``chosen``, ``points``, ``rgb`` ("asset",
    "images" or "files"), ``notes`` (warnings also in /log), ``log_seconds`` (wall time of logging, flushing
    included), ``rrd`` (path or None).
    """
    t0 = time.perf_counter()
    _check_match(trace, recording)
    out = Output(rrd=rrd, spawn=spawn, stream=stream)
    try:
        logger = TraceLogger(recording, out.stream, video=video, points=points, step=step, max_points=max_points,
                             clouds=clouds, blueprint=blueprint_for(trace, recording, points=points))
        logger.replay(trace, progress=progress, frames=frames)
        stats = logger.finish(trace, layout=False)
        log_timings(out.stream, {**trace.timings, "log": time.perf_counter() - t0}, stats["frames"])
        out.flush()
    except BaseException as err:
        out.close(err)
        raise
    out.close()
    stats.update(recording_id=out.stream.get_recording_id(), rrd=None if out.rrd is None else str(out.rrd))
    stats["log_seconds"] = time.perf_counter() - t0
    return stats


def log_run(recording, process, *, rrd: str | Path | None = None, spawn: bool = False, progress: bool = False,
            video: str = "auto", points: bool = False, clouds: bool = True, k: int = 5, replay_frames=None,
            measured=None, before_close=None) -> tuple[Trace, dict]:
    """Run the pipeline and log it in one pass (``massviz log``): ``process(on_frame)`` runs the pipeline on
    ``recording`` with ``on_frame`` as its per-frame observer and returns the trace (e.g.
    ``lambda on_frame: pipeline.process(recording, on_frame=on_frame)``; ``on_frame(frame, result, clouds)`` takes
    the measure stage's clouds of the frame, see ``TraceLogger``). Each frame is logged as it is processed, so no frame
    is read twice; a trace that comes from the cache (``on_frame`` never called) is replayed once, its frames and
    clouds from ``replay_frames(trace)`` (``MeasureStage.replay_frames``; default: the recording's frames, no
    clouds). ``measured(trace)``: the trace with the measure stage's measurements (``MeasureStage.finish``), taken
    before what needs the whole trace is logged. Outputs and options as ``log_trace`` (``k``: the selection's K: a
    first layout is sent before the frames, the final one at the end). ``before_close(trace)``: more output
    made from the trace (``log --ply``), run before the .rrd is renamed into place, so that when it fails no .rrd
    is left either. Returns (trace, stats)."""
    t0 = time.perf_counter()
    out = Output(rrd=rrd, spawn=spawn)
    try:
        layout = default_blueprint(k, has_3d=recording.intrinsics is not None, image_size=(recording.width,
                                                                                             recording.height))
        logger = TraceLogger(recording, out.stream, video=video, points=points, clouds=clouds, blueprint=layout)
        trace = process(logger.on_frame)
        if not logger.frames:
            logger.replay(trace, progress=progress, frames=None if replay_frames is None else replay_frames(trace))
        if measured is not None:
            trace = measured(trace)
        stats = logger.finish(trace, points=points)
        log_timings(out.stream, {**trace.timings, "log": logger.seconds}, stats["frames"])
        out.flush()
        if before_close is not None:
            before_close(trace)
    except BaseException as err:
        out.close(err)
        raise
    out.close()
    stats.update(recording_id=out.stream.get_recording_id(), rrd=None if out.rrd is None else str(out.rrd),
                 log_seconds=logger.seconds, seconds=time.perf_counter() - t0)
    return trace, stats


__all__ = ["TraceLogger", "log_trace", "log_run"]
