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
from massviz.views.rerun.blueprint import blueprint_for
from massviz.views.rerun.entities import (CLOUD_VOXEL_M, MAX_POINTS, POINT_STEP, RgbLogger, detection_class_ids,
                                          frustum_depth, log_annotation_context, log_depth, log_detections, log_events,
                                          log_flags, log_frame_clouds, log_masks, log_patch, log_pinhole, log_points,
                                          log_predictions, log_running, log_summary, log_timings)
from massviz.views.rerun.output import Output, notebook_stream

def _check_match(trace: Trace, recording) -> None:
    w, h = trace.recording.width, trace.recording.height
    if (w, h) != (recording.width, recording.height):
        raise MassvizError(f"the trace was made on {w}x{h} frames but this recording is "
                           f"{recording.width}x{recording.height}", recording.path)
    if len(trace.frames) and int(np.max(trace.frames)) >= recording.num_frames:
        raise MassvizError(f"the trace has frame {int(np.max(trace.frames))} but the recording has "
                           f"{recording.num_frames} frames", recording.path)


def _log_all(rec: rr.RecordingStream, trace: Trace, recording, *, video: str, step: int,
             max_points: int, progress: bool, clouds: bool, points: bool) -> dict:
    dets, frames = trace.detections, [int(f) for f in trace.frames]
    first = frames[0] if frames else 0
    rank_of = {int(i): r for r, i in enumerate(trace.selection)}
    flag_of = {p.detection: p for p in trace.flags.patches}
    flagged = frozenset(p.detection for p in trace.flags.flagged)
    by_frame: dict[int, list[int]] = defaultdict(list)
    for i, f in enumerate(dets.frame):
        by_frame[int(f)].append(i)
    intr = recording.intrinsics

    rec.send_recording_name(f"massviz {recording.id}")
    log_annotation_context(rec, trace.k)
    log_summary(rec, trace)
    rgb = RgbLogger(recording, video)
    rgb.log_static(rec)
    notes = []
    if intr is None:
        notes.append("no camera intrinsics for this recording: no /camera Pinhole, no 3D view")
    if rgb.warning:
        notes.append(rgb.warning)
    if trace.estimate < 0 and not any(e.kind == "not_estimated" for e in trace.events):
        notes.append("not estimated: no detection with depth was selected")
    rec.set_time("frame", sequence=first)
    for note in notes:
        rec.log("/log", rr.TextLog(note, level=rr.TextLogLevel.WARN))

    cloud_frames = clouds and intr is not None
    n_points, n_clouds, shown = 0, 0, []
    bar = tqdm(recording.frames(indices=frames), total=len(frames), desc=f"{recording.id} → rerun", unit="frame",
               file=sys.stderr, disable=not progress, leave=False)
    for frame in bar:
        rec.set_time("frame", sequence=frame.index)
        ns = rgb.video_time_ns(frame.index)
        if ns is not None:
            rec.set_time("video_time", duration=ns * 1e-9)
        if intr is not None and frame.index == first:
            log_pinhole(rec, intr, frustum_depth(frame.depth))
        rgb.log_frame(rec, frame)
        log_depth(rec, frame.depth, frame.depth_encoded)
        idx = by_frame.get(frame.index, [])
        class_ids = detection_class_ids(dets, idx, rank_of, trace.threshold, flagged)
        log_detections(rec, dets, idx, class_ids, rank_of)
        log_masks(rec, dets, idx, class_ids, frame.depth.shape[:2])
        if points and intr is not None:
            n_points += log_points(rec, frame.depth, frame.rgb, intr, step, max_points)
        for i in idx:
            if i in rank_of:
                patch = dets.patches[i] if dets.patches[i] is not None else crop(frame.rgb, dets.xyxy[i])
                log_patch(rec, rank_of[i], dets, i, patch, flag_of.get(i))
        if cloud_frames:  # in this same pass, so the frames are decoded once
            for path in shown:
                rec.log(path, rr.Clear(recursive=True))
            shown = log_frame_clouds(trace, frame, intr, rec, voxel_m=CLOUD_VOXEL_M)
            n_clouds += len(shown)
    bar.close()
    rec.reset_time()
    log_predictions(rec, trace)
    log_running(rec, trace)
    log_events(rec, trace.events, first)
    log_flags(rec, trace)
    rec.reset_time()
    return {"frames": len(frames), "detections": len(dets), "chosen": len(rank_of), "points": n_points,
            "clouds": n_clouds, "rgb": rgb.mode, "notes": notes}


def log_trace(trace: Trace, recording, *, rrd: str | Path | None = None, spawn: bool = False,
              stream: rr.RecordingStream | None = None, progress: bool = False, max_points: int = MAX_POINTS,
              step: int = POINT_STEP, video: str = "auto", clouds: bool = True, points: bool = False) -> dict:
    """Log ``trace`` (made on ``recording``) to Rerun; the entity tree is in this module's docstring.

    Outputs: ``rrd`` (a file, written atomically: nothing is left at ``rrd`` if logging fails), ``spawn`` (spawn
    or connect to a viewer on the default port), both, or ``stream`` (a caller's ``rr.RecordingStream``, e.g. a
    notebook's inline viewer; its sinks are left as they are and it is not disconnected). Each call logs a new
    recording of application ``massviz`` on its own ``RecordingStream`` (never the global one).

    ``video``: how an mp4 is logged (see ``RgbLogger``). ``points``: also log ``/world/points`` (RGB-coloured
    points; by default Rerun back-projects ``/camera/depth`` itself, which keeps the recording small);
    ``step``/``max_points``: their subsampling.
    ``clouds``: also log each detection's Open3D cloud under ``/world/detections`` (``massviz.core.geometry``).

    Returns stats: ``recording_id``, ``frames``, ``detections``, ``chosen``, ``points``, ``rgb`` ("asset",
    "images" or "files"), ``notes`` (warnings also in /log), ``log_seconds`` (wall time of logging, flushing
    included), ``rrd`` (path or None).
    """
    _check_match(trace, recording)
    t0 = time.perf_counter()
    blueprint = blueprint_for(trace, recording, points=points)

    out = Output(rrd=rrd, spawn=spawn, stream=stream)
    try:
        rec = out.stream
        rec.send_blueprint(blueprint, make_active=True, make_default=True)
        stats = _log_all(rec, trace, recording, video=video, step=step, max_points=max_points, progress=progress,
                         clouds=clouds, points=points)
        log_timings(rec, {**trace.timings, "log": time.perf_counter() - t0}, stats["frames"])
        out.flush()
    except BaseException as err:
        out.close(err)
        raise
    out.close()
    stats.update(recording_id=rec.get_recording_id(), rrd=None if out.rrd is None else str(out.rrd))
    stats["log_seconds"] = time.perf_counter() - t0
    return stats


def show_in_notebook(trace: Trace, recording, *, width: int = 1000, height: int = 640, **options) -> dict:
    """Show ``trace`` in an inline Rerun viewer (``output.notebook_stream``) in the current notebook cell, with
    massviz's default layout, and log it there (``log_trace(..., stream=...)``; ``options`` go to it). Returns
    ``log_trace``'s stats."""
    stream = notebook_stream(recording.id, blueprint_for(trace, recording, points=bool(options.get("points"))),
                             width=width, height=height)
    return log_trace(trace, recording, stream=stream, **options)


__all__ = ["log_trace", "show_in_notebook"]
