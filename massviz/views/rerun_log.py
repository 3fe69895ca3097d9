"""Log a ``Trace`` to Rerun: every stage of one estimate, on a ``frame`` timeline, with a default layout.

``log_trace`` reads only the trace and the recording's frames (re-streamed for the processed frames); it never runs
the detector or the model. Each kind of data is logged by a small ``log_*`` function next to it, in the style of
Rerun's ``rgbd`` and ``detect_and_track_objects`` examples, and ``default_blueprint`` lays out the views.

Entity tree (a public contract; the README copies it). Everything temporal is on the ``frame`` timeline (sequence =
frame index in the recording); a video asset's frames are also on ``video_time``.

=============================  ========================================================================================
entity                         what is logged
=============================  ========================================================================================
``/camera``                    ``Pinhole`` (static; RDF camera; only with intrinsics) and the ``AnnotationContext``
                               (static) naming the class ids used by ``/camera/detections`` and ``/camera/masks``
``/camera/rgb``                an mp4 Rerun can decode: the file once as ``AssetVideo`` (static, not re-encoded) and a
                               ``VideoFrameReference`` per processed frame; frame folders: ``EncodedImage`` of each
                               frame file's bytes; an mp4 Rerun cannot decode (e.g. CCM's MPEG-4 Part 2 'mp4v'):
                               JPEG ``EncodedImage`` per processed frame, with a warning in ``/log``
``/camera/depth``              ``EncodedDepthImage``: the recording's 16-bit PNG (mm) as its own bytes (``meter=1000``,
                               turbo colormap); the 3D view back-projects it through the ``Pinhole`` (``DepthImage``
                               of the decoded array when there is no PNG file)
``/camera/detections``         ``Boxes2D`` (XYXY) labelled "class score · d mm · track t", with class ids and
                               ``AnyValues`` track, detection; boxes coloured by object track, chosen patches in the
                               palette's chosen colour (class id ``CHOSEN_ID + rank``, label suffix "★rank"),
                               flagged ones in its flagged colour (class id ``FLAGGED_ID + rank``, "★rank ⚑ flagged")
``/camera/masks``              ``SegmentationImage`` of the same class ids (chosen masks drawn on top)
``/world``                     ``ViewCoordinates.RDF`` (static): the 3D world is the camera frame
``/world/points``              only with ``points=True`` (``massviz log --points``): ``Points3D``, depth back-projected
                               (Open3D) to metres in the camera frame, every ``step``-th pixel, at most ``max_points``,
                               coloured by RGB (only with intrinsics)
``/patches/<rank>``            ``Image`` of chosen patch ``rank`` (0 = nearest) as the model saw it (zero-padded
                               square, 112×112) at its source frame, with ``AnyValues`` a, b, d_mm, frame, class,
                               score, pred_g, detection, track, flagged, flag
``/patches/<rank>/outline``    ``Boxes2D`` around the tile: chosen colour, or flagged colour labelled "⚑ flagged: why"
``/predictions/patch_<rank>``  ``Scalars``: that patch's prediction (g), at its source frame and the last frame
``/predictions/estimate``      ``Scalars``: the estimate (g) at the last processed frame (absent when not estimated)
``/predictions/estimate_without_flagged``  ``Scalars``: the mean prediction of the chosen patches not flagged
                               (``trace.flags``), at the last processed frame (only when some are flagged and
                               some are not)
``/predictions/ground_truth``  ``Scalars``: the container's mass from the recording's meta (``container.mass_g``), at
                               the first and the last processed frame (absent when unknown)
``/world/detections/<id>``     ``Points3D``: detection ``id``'s cleaned Open3D cloud (chosen ones highlighted), with
                               ``/box`` (``Boxes3D``, measured box of a chosen one) and ``/measurement`` (AnyValues);
                               see ``log_frame_clouds`` (clouds from ``massviz.core.geometry``) (only with intrinsics; ``clouds=False`` skips)
``/log``                       ``TextLog`` of the decisions (trace events, missing intrinsics, video fallback) with
                               levels, at their frames; one WARN per flagged patch at its frame and the flags'
                               summary line ("3 of 5 chosen patches look like another object ...") at the last
``/summary``                   ``TextDocument`` (static, markdown): recording, detector, K, estimate, chosen patches
                               with their track and flag
``/timings``                   ``TextDocument`` (static, markdown): seconds per pipeline stage and for logging
``/timings/<stage>``           ``Scalars`` (static): seconds of each stage of ``trace.timings`` and ``log`` (this
                               logging's own cost)
=============================  ========================================================================================

Class ids (``AnnotationContext`` at ``/camera``): 0 background, 1 cup, 2 book, 3 wine glass, 4 bottle, 5 object
(class-agnostic depth detector), 6 other COCO class, 7 below the trace's threshold, ``CHOSEN_ID + rank`` chosen patch,
``FLAGGED_ID + rank`` chosen patch flagged as probably not the container. Colours come from ``massviz.views.palette``
(the same chosen and flagged colours as the notebooks' figures and the Open3D render).
"""
from __future__ import annotations

import math
import os
import sys
import time
import uuid
from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np
import rerun as rr
import rerun.blueprint as rrb
from tqdm.auto import tqdm

from massviz.io.atomic import atomic_path, check_room
from massviz.errors import MassvizError
from massviz.io.recording import Recording
from massviz.core.trace import Trace
from massviz.core.geometry import (Measurement, depth_to_points, detection_cloud, measure_cloud, measurements_of,
                                   skip_reason)
from massviz.core.patches import crop, model_view
from massviz.core.types import Detections, Frame, Intrinsics, class_name
from massviz.views.palette import (BELOW_THRESHOLD_COLOUR, BOX_COLOUR, CHOSEN_COLOUR, FLAGGED_COLOUR,
                                    WITHOUT_FLAGGED_COLOUR, rgb255, track_colour)

APPLICATION_ID = "massviz"
#: every ``POINT_STEP``-th pixel (in x and y) of the depth image becomes a point of ``/world/points``.
POINT_STEP = 4
#: at most this many points per frame in ``/world/points``.
MAX_POINTS = 50_000
#: voxel size (m) of the detection clouds under ``/world/detections`` (the scene itself is the back-projected depth).
CLOUD_VOXEL_M = 0.01

# ---------------------------------------------------------------------------------------------- annotation context
BACKGROUND_ID, OTHER_ID, BELOW_THRESHOLD_ID, CHOSEN_ID, FLAGGED_ID = 0, 6, 7, 10, 200
CLASS_IDS = {"cup": 1, "book": 2, "wine glass": 3, "bottle": 4, "object": 5}
_CLASS_COLOURS = {1: (31, 119, 180), 2: (148, 103, 189), 3: (23, 190, 207), 4: (44, 160, 44), 5: (188, 189, 34),
                  OTHER_ID: (140, 86, 75), BELOW_THRESHOLD_ID: (127, 127, 127)}


def class_id_of(name: str) -> int:
    """Annotation class id of a detection class name (``OTHER_ID`` for classes the paper does not keep)."""
    return CLASS_IDS.get(name, OTHER_ID)


def log_annotation_context(rec: rr.RecordingStream, k: int) -> None:
    """Names and colours of the class ids of ``/camera/detections`` and ``/camera/masks`` (static, at /camera)."""
    infos = [rr.AnnotationInfo(id=BACKGROUND_ID, label="background", color=(0, 0, 0))]
    infos += [rr.AnnotationInfo(id=cid, label=name, color=_CLASS_COLOURS[cid]) for name, cid in CLASS_IDS.items()]
    infos += [rr.AnnotationInfo(id=OTHER_ID, label="other class", color=_CLASS_COLOURS[OTHER_ID]),
              rr.AnnotationInfo(id=BELOW_THRESHOLD_ID, label="below threshold",
                                color=_CLASS_COLOURS[BELOW_THRESHOLD_ID])]
    ranks = range(min(max(k, 1), FLAGGED_ID - CHOSEN_ID))
    infos += [rr.AnnotationInfo(id=CHOSEN_ID + r, label=f"chosen ★{r}", color=rgb255(CHOSEN_COLOUR)) for r in ranks]
    infos += [rr.AnnotationInfo(id=FLAGGED_ID + r, label=f"flagged ★{r}", color=rgb255(FLAGGED_COLOUR))
              for r in ranks]
    rec.log("/camera", rr.AnnotationContext(infos), static=True)


# ---------------------------------------------------------------------------------------------------------- camera
def log_pinhole(rec: rr.RecordingStream, intr: Intrinsics, image_plane_distance: float) -> None:
    """The RGB camera (depth is aligned to it), right-down-forward, static."""
    rec.log("/camera", rr.Pinhole(focal_length=[intr.fx, intr.fy], principal_point=[intr.cx, intr.cy],
                                  width=intr.width, height=intr.height, camera_xyz=rr.ViewCoordinates.RDF,
                                  image_plane_distance=image_plane_distance), static=True)
    rec.log("/world", rr.ViewCoordinates.RDF, static=True)


def frustum_depth(depth: np.ndarray) -> float:
    """A frustum depth (m) that reaches about half-way to the scene: half the median valid depth, 0.1..2 m."""
    valid = depth[depth > 0]
    return 0.5 if valid.size == 0 else float(np.clip(0.5 * np.median(valid) / 1000.0, 0.1, 2.0))


# ------------------------------------------------------------------------------------------------------------- rgb
class RgbLogger:
    """Logs ``/camera/rgb``: an mp4 as one video asset + frame references, else compressed images.

    ``video``: ``"auto"`` (asset when Rerun can decode the codec, else JPEG frames), ``"asset"`` (always the asset,
    even if the viewer cannot decode it) or ``"images"`` (always JPEG frames). ``mode`` is what was chosen;
    ``warning`` says why an mp4 is not logged as an asset (or cannot be shown).
    """

    def __init__(self, recording: Recording, video: str = "auto"):
        if video not in ("auto", "asset", "images"):
            raise ValueError(f"video must be 'auto', 'asset' or 'images', not {video!r}")
        self.recording, self.warning, self.timestamps_ns = recording, None, None
        self.asset = None
        if recording.rgb_video is None:
            # frame files are logged as they are; frames without files (RealSense recordings) as JPEG images
            self.mode = "files" if recording.rgb_files is not None else "images"
            return
        self.mode = "images" if video == "images" else "asset"
        if video == "images":
            return
        self.asset = rr.AssetVideo(path=recording.rgb_video)
        try:
            self.timestamps_ns = np.sort(np.asarray(self.asset.read_frame_timestamps_nanos(), dtype=np.int64))
        except Exception as err:  # noqa: BLE001 - Rerun reports unsupported codecs / broken containers as errors
            reason = f"Rerun cannot decode {recording.rgb_video.name} ({err})"
            if video == "auto":
                self.mode, self.asset = "images", None
                self.warning = f"{reason}: logging the processed frames as JPEG images instead of the video asset"
            else:
                self.warning = f"{reason}: the video asset is logged but the viewer will not show its frames"

    def log_static(self, rec: rr.RecordingStream) -> None:
        if self.asset is not None:
            rec.log("/camera/rgb", self.asset, static=True)

    def video_time_ns(self, index: int) -> int | None:
        """Presentation time of video frame ``index`` (from the container, else index / fps); None without asset."""
        if self.mode != "asset":
            return None
        if self.timestamps_ns is not None and index < len(self.timestamps_ns):
            return int(self.timestamps_ns[index])
        return int(round(index / (self.recording.fps or 30.0) * 1e9))

    def log_frame(self, rec: rr.RecordingStream, index: int, rgb: np.ndarray) -> None:
        if self.mode == "asset":
            rec.log("/camera/rgb", rr.VideoFrameReference(nanoseconds=self.video_time_ns(index)))
        elif self.mode == "files":
            rec.log("/camera/rgb", rr.EncodedImage(path=self.recording.rgb_files[index]))
        else:
            rec.log("/camera/rgb", rr.EncodedImage(contents=jpeg_bytes(rgb, 90, f"frame {index}", self.recording.path),
                                                   media_type="image/jpeg"))


def jpeg_bytes(rgb: np.ndarray, quality: int, what: str = "a frame", path=None) -> bytes:
    """``rgb`` (H×W×3 RGB) as JPEG bytes at ``quality``; an encoder failure is one line naming ``what``/``path``."""
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise MassvizError(f"cannot JPEG-encode {what}", path)
    return buf.tobytes()


# ----------------------------------------------------------------------------------------------- depth and points
def log_depth(rec: rr.RecordingStream, depth: np.ndarray, png: Path | None = None) -> None:
    """``/camera/depth``: the frame's 16-bit PNG file as its own bytes (``EncodedDepthImage``, no decode/re-encode;
    ``depth`` is that file decoded, so it has been checked already), else the array as a ``DepthImage``."""
    if png is not None and png.suffix.lower() == ".png":
        rec.log("/camera/depth", rr.EncodedDepthImage(png.read_bytes(), media_type=rr.components.MediaType.PNG,
                                                      meter=1000.0, colormap="turbo"))
    else:
        rec.log("/camera/depth", rr.DepthImage(depth, meter=1000.0, colormap="turbo"))


def scene_depth_m(depth: np.ndarray) -> float:
    """Median valid depth (m) of a frame, 0.1..10 m (1 m without depth): where the 3D view looks at."""
    valid = depth[depth > 0]
    return 1.0 if valid.size == 0 else float(np.clip(np.median(valid) / 1000.0, 0.1, 10.0))


def log_points(rec: rr.RecordingStream, depth: np.ndarray, rgb: np.ndarray, intr: Intrinsics, step: int,
               max_points: int) -> int:
    """``/world/points`` of one frame (at most ``max_points``, evenly subsampled); returns the number logged."""
    points, colours = depth_to_points(depth, intr, rgb, step)
    if max_points > 0 and len(points) > max_points:
        keep = np.arange(0, len(points), math.ceil(len(points) / max_points))
        points, colours = points[keep], None if colours is None else colours[keep]
    rec.log("/world/points", rr.Points3D(points, colors=colours, radii=rr.Radius.ui_points(1.5)))
    return len(points)


# ------------------------------------------------------------------------------------------ detections and masks
def detection_class_ids(dets: Detections, idx: list[int], rank_of: dict[int, int], threshold: float,
                        flagged=frozenset()) -> np.ndarray:
    """Annotation class id of each detection in ``idx``: flagged or chosen rank, below threshold, or its class."""
    out = []
    for i in idx:
        if i in rank_of:
            out.append((FLAGGED_ID if i in flagged else CHOSEN_ID) + rank_of[i])
        elif dets.score[i] <= threshold:
            out.append(BELOW_THRESHOLD_ID)
        else:
            out.append(class_id_of(class_name(dets.class_id[i])))
    return np.asarray(out, dtype=np.uint16)


def detection_label(dets: Detections, i: int, rank: int | None, flagged: bool = False) -> str:
    d = "no depth" if not np.isfinite(dets.d[i]) else f"{dets.d[i]:.0f} mm"
    star = "" if rank is None else f" ★{rank}" + (" ⚑ flagged" if flagged else "")
    return f"{class_name(dets.class_id[i])} {dets.score[i]:.2f} · {d} · track {int(dets.track[i])}{star}"


def detection_colours(dets: Detections, idx: list[int], class_ids: np.ndarray) -> np.ndarray:
    """RGB of each box: flagged / chosen colour, grey below the threshold, else its track's colour (palette)."""
    out = []
    for i, cid in zip(idx, class_ids):
        if cid >= FLAGGED_ID:
            out.append(rgb255(FLAGGED_COLOUR))
        elif cid >= CHOSEN_ID:
            out.append(rgb255(CHOSEN_COLOUR))
        elif cid == BELOW_THRESHOLD_ID:
            out.append(rgb255(BELOW_THRESHOLD_COLOUR))
        else:
            out.append(rgb255(track_colour(int(dets.track[i]))))
    return np.asarray(out, dtype=np.uint8).reshape(-1, 3)


def log_detections(rec: rr.RecordingStream, dets: Detections, idx: list[int], class_ids: np.ndarray,
                   rank_of: dict[int, int]) -> None:
    """``/camera/detections`` of one frame (an empty frame clears the previous frame's boxes)."""
    if not idx:
        rec.log("/camera/detections", rr.Boxes2D(array=np.zeros((0, 4), np.float32),
                                                 array_format=rr.Box2DFormat.XYXY))
        return
    rec.log("/camera/detections", rr.Boxes2D(
        array=dets.xyxy[idx].astype(np.float32), array_format=rr.Box2DFormat.XYXY, class_ids=class_ids,
        colors=detection_colours(dets, idx, class_ids),
        labels=[detection_label(dets, i, rank_of.get(i), bool(c >= FLAGGED_ID)) for i, c in zip(idx, class_ids)]),
        rr.AnyValues(track=dets.track[idx].astype(np.int64), detection=np.asarray(idx, np.int64)))


def log_masks(rec: rr.RecordingStream, dets: Detections, idx: list[int], class_ids: np.ndarray,
              shape: tuple[int, int]) -> None:
    """``/camera/masks``: one segmentation image of the frame; chosen masks are drawn last (on top)."""
    seg = np.zeros(shape, dtype=np.uint8 if len(idx) == 0 or int(class_ids.max()) < 256 else np.uint16)
    for j in sorted(range(len(idx)), key=lambda j: class_ids[j] >= CHOSEN_ID):
        x1, y1, x2, y2 = (int(v) for v in dets.xyxy[idx[j]])
        seg[y1:y2, x1:x2][dets.mask(idx[j])] = class_ids[j]
    rec.log("/camera/masks", rr.SegmentationImage(seg, opacity=0.5))


# ------------------------------------------------------------------------------------------------------- patches
def log_patch(rec: rr.RecordingStream, rank: int, dets: Detections, i: int, patch: np.ndarray, flag=None) -> None:
    """``/patches/<rank>`` at its source frame: the model's input image and the numbers that went with it, and
    ``/patches/<rank>/outline`` around it in the chosen colour, or the flagged colour with why (``flag``, a
    ``massviz.core.flags.PatchFlag``)."""
    image = model_view(patch)
    flagged = flag is not None and flag.flagged
    rec.log(f"/patches/{rank}", rr.Image(image), rr.AnyValues(
        a=float(dets.a[i]), b=float(dets.b[i]), d_mm=float(dets.d[i]), frame=int(dets.frame[i]),
        class_name=class_name(dets.class_id[i]), score=float(dets.score[i]), pred_g=float(dets.pred[i]),
        detection=int(i), track=int(dets.track[i]), flagged=bool(flagged), flag="" if not flagged else flag.reason))
    h, w = image.shape[:2]
    label = f"★{rank} ⚑ flagged: {_short_reason(flag)}" if flagged else f"★{rank}"
    rec.log(f"/patches/{rank}/outline", rr.Boxes2D(
        array=[[0.5, 0.5, w - 0.5, h - 0.5]], array_format=rr.Box2DFormat.XYXY, labels=[label],
        colors=[rgb255(FLAGGED_COLOUR if flagged else CHOSEN_COLOUR)], radii=[2.0 if flagged else 1.0]))


def _short_reason(flag) -> str:
    """What a flagged patch is, in a few words (tile labels, series names)."""
    if flag.ground_truth is not None:
        return f"the {flag.ground_truth}" + (" (a part of it)" if flag.ground_truth == "container" else "")
    return ", ".join(k.replace("_", " ") for k in flag.cue_kinds)


# --------------------------------------------------------------------------------------------------- predictions
def log_predictions(rec: rr.RecordingStream, trace: Trace) -> None:
    """``/predictions/*``: each chosen prediction from its source frame to the last frame, the estimate at the last
    frame (when estimated), the ground truth over the whole run (when known)."""
    if len(trace.frames) == 0:
        return
    first, last = int(trace.frames[0]), int(trace.frames[-1])
    dets = trace.detections
    for rank, i in enumerate(trace.selection):
        path = f"/predictions/patch_{rank}"
        flag = trace.flags.of(int(i))
        flagged = flag is not None and flag.flagged
        name = f"patch ★{rank} ({class_name(dets.class_id[i])}, {dets.d[i]:.0f} mm)" + (" ⚑ flagged" if flagged else "")
        rec.log(path, rr.SeriesLines(names=name, colors=rgb255(FLAGGED_COLOUR if flagged else CHOSEN_COLOUR)),
                static=True)
        for t in sorted({int(dets.frame[i]), last}):
            rec.set_time("frame", sequence=t)
            rec.log(path, rr.Scalars(float(dets.pred[i])))
    if trace.estimate >= 0:
        rec.log("/predictions/estimate", rr.SeriesLines(names="estimate", colors=(255, 255, 255), widths=2),
                rr.SeriesPoints(names="estimate", colors=(255, 255, 255), markers="diamond", marker_sizes=6),
                static=True)
        rec.set_time("frame", sequence=last)
        rec.log("/predictions/estimate", rr.Scalars(float(trace.estimate)))
    flags = trace.flags
    if flags.flagged and flags.estimate_without >= 0:
        path = "/predictions/estimate_without_flagged"
        colour = rgb255(WITHOUT_FLAGGED_COLOUR)
        rec.log(path, rr.SeriesLines(names="estimate without flagged patches", colors=colour, widths=2),
                rr.SeriesPoints(names="estimate without flagged patches", colors=colour, markers="diamond",
                                marker_sizes=6), static=True)
        rec.set_time("frame", sequence=last)
        rec.log(path, rr.Scalars(float(flags.estimate_without)))
    gt = trace.ground_truth_mass
    if gt is not None:
        rec.log("/predictions/ground_truth", rr.SeriesLines(names="ground truth", colors=(0, 200, 0), widths=2),
                static=True)
        for t in sorted({first, last}):
            rec.set_time("frame", sequence=t)
            rec.log("/predictions/ground_truth", rr.Scalars(gt))


RUNNING_COLOUR = (90, 170, 255)


def log_running(rec: rr.RecordingStream, trace: Trace) -> None:
    """``/predictions/running_estimate``: the estimate after each processed frame (``Trace.running_estimate``, from
    the first frame with a selected patch), and ``/latency/<stage>``: each processed frame's seconds per stage, in
    ms (when the trace has them)."""
    frames = np.asarray(trace.frames, dtype=np.int64)
    if len(frames) == 0:
        return
    running = trace.running_estimate()
    keep = running >= 0
    if keep.any():
        rec.log("/predictions/running_estimate", rr.SeriesLines(names="running estimate (K nearest so far)",
                                                                colors=RUNNING_COLOUR, widths=2), static=True)
        rec.send_columns("/predictions/running_estimate", indexes=[rr.TimeColumn("frame", sequence=frames[keep])],
                         columns=rr.Scalars.columns(scalars=running[keep]))
    for stage, seconds in trace.frame_timings.items():
        seconds = np.asarray(seconds, dtype=np.float64)
        if len(seconds) == len(frames):
            rec.send_columns(f"/latency/{stage}", indexes=[rr.TimeColumn("frame", sequence=frames)],
                             columns=rr.Scalars.columns(scalars=1000.0 * seconds))


# ----------------------------------------------------------------------------------------------------- text, log
_LEVELS = {"debug": rr.TextLogLevel.DEBUG, "info": rr.TextLogLevel.INFO, "warn": rr.TextLogLevel.WARN}


def log_events(rec: rr.RecordingStream, events, first_frame: int) -> None:
    """``/log``: the trace's typed events at their frames (frame -1, e.g. cache reuse: at the first frame), at
    their level."""
    for e in events:
        frame = int(e.frame)
        rec.set_time("frame", sequence=frame if frame >= 0 else first_frame)
        rec.log("/log", rr.TextLog(str(e.message), level=_LEVELS.get(e.level, rr.TextLogLevel.INFO)))


def log_flags(rec: rr.RecordingStream, trace: Trace) -> None:
    """``/log`` WARN entries of ``trace.flags``: each flagged patch at its frame, the summary line at the last frame."""
    flags = trace.flags
    if not flags.flagged:
        return
    for p in flags.flagged:
        rec.set_time("frame", sequence=p.frame)
        rec.log("/log", rr.TextLog(f"flagged patch ★{p.rank} (frame {p.frame}, track {p.track}, severity "
                                   f"{p.severity}): probably not the container: {p.reason}",
                                   level=rr.TextLogLevel.WARN))
    last = int(trace.frames[-1]) if len(trace.frames) else max(p.frame for p in flags.patches)
    rec.set_time("frame", sequence=last)
    rec.log("/log", rr.TextLog(flags.warning(), level=rr.TextLogLevel.WARN))


def summary_markdown(trace: Trace) -> str:
    info, dets = trace.recording, trace.detections
    est = "**not estimated** (no detection with depth)" if trace.estimate < 0 else f"**{trace.estimate:.1f} g**"
    gt = trace.ground_truth_mass
    lines = [f"# {info.id}", "",
             f"- recording: `{info.path}` ({info.width}×{info.height}, "
             f"{info.num_frames} frames; {len(trace.frames)} processed, stride {trace.stride})",
             f"- detector: {trace.detector.get('name', '?')}"
             + (f" ({trace.detector['precision']})" if "precision" in trace.detector else "")
             + f", threshold {trace.threshold:g}; "
             f"{len(dets)} detections",
             f"- model weights: `{trace.weights_id or '?'}`; K = {trace.k}",
             f"- estimate: {est}" + ("" if gt is None else f"; ground truth {gt:.1f} g"
                                      + ("" if trace.estimate < 0 else f" (error {trace.estimate - gt:+.1f} g)")),
             ""]
    warning = trace.flags.warning()
    if warning:
        lines[-1:-1] = [f"- **⚑ {warning}**"]
    if len(trace.selection):
        flag_of = {p.detection: p for p in trace.flags.patches}
        lines += ["| rank | frame | track | class | score | d (mm) | a | b | prediction (g) | flag |",
                  "|---:|---:|---:|---|---:|---:|---:|---:|---:|---|"]
        lines += [f"| ★{r} | {dets.frame[i]} | {dets.track[i]} | {class_name(dets.class_id[i])} | {dets.score[i]:.2f} | "
                  f"{dets.d[i]:.0f} | {dets.a[i]:.2f} | {dets.b[i]:.2f} | {dets.pred[i]:.1f} | "
                  + (f"⚑ {_short_reason(flag_of[int(i)])} |" if int(i) in flag_of and flag_of[int(i)].flagged
                     else "|") for r, i in enumerate(trace.selection)]
    return "\n".join(lines) + "\n"


def log_summary(rec: rr.RecordingStream, trace: Trace) -> None:
    rec.log("/summary", rr.TextDocument(summary_markdown(trace), media_type=rr.MediaType.MARKDOWN), static=True)


def log_timings(rec: rr.RecordingStream, timings: dict, n_frames: int) -> None:
    """``/timings``: seconds per stage (the pipeline's and ``log``, this logging's cost), static."""
    rows = ["| stage | seconds | ms / frame |", "|---|---:|---:|"]
    for stage, seconds in timings.items():
        per = f"{1000 * seconds / n_frames:.1f}" if n_frames else "–"
        rows.append(f"| {stage} | {seconds:.3f} | {per} |")
        rec.log(f"/timings/{stage}", rr.Scalars(float(seconds)), static=True)
    rec.log("/timings", rr.TextDocument("\n".join(rows) + "\n", media_type=rr.MediaType.MARKDOWN), static=True)


# ------------------------------------------------------------------------------------------------------ blueprint
def default_blueprint(n_patches: int, *, has_3d: bool = True, flagged=(), look_at_m: float = 1.0,
                      points: bool = False) -> rrb.Blueprint:
    """RGB + detections + masks, depth and 3D on the left; the chosen patches, predictions and text on the right.

    The 3D view starts at the camera (the origin of ``/world``, the camera frame) looking along its optical axis at
    ``look_at_m`` metres (orbiting around that point), image up. It shows the camera frustum, the detection clouds
    and the depth back-projected by Rerun through the ``Pinhole`` (or ``/world/points`` instead when ``points``).
    The RGB image is not in it: seen from the camera it would cover the whole view. ``flagged``: ranks of flagged
    patches (their tiles are named "patch ★r ⚑ flagged")."""
    flagged = {int(r) for r in flagged}
    camera = rrb.Spatial2DView(name="RGB · detections · masks", origin="/camera",
                               contents=["/camera/rgb", "/camera/detections", "/camera/masks"])
    depth = rrb.Spatial2DView(name="Depth", origin="/camera", contents=["/camera/depth"])
    lower = [depth]
    if has_3d:
        eye = rrb.EyeControls3D(position=[0.0, 0.0, 0.0], look_target=[0.0, 0.0, float(look_at_m)],
                                eye_up=[0.0, -1.0, 0.0])
        lower.append(rrb.Spatial3DView(name="3D (camera frame, m)", origin="/", eye_controls=eye,
                                       contents=["/world/**", "/camera"] + ([] if points else ["/camera/depth"])))
    if n_patches:
        patches = rrb.Grid(*[rrb.Spatial2DView(name=f"patch ★{r}" + (" ⚑ flagged" if r in flagged else ""),
                                               origin=f"/patches/{r}") for r in range(n_patches)],
                           name="Chosen patches (model input)")
    else:
        patches = rrb.TextDocumentView(name="Summary", origin="/summary")
    text = rrb.Tabs(rrb.TextLogView(name="Decisions", origin="/log"),
                    rrb.TextDocumentView(name="Summary", origin="/summary"),
                    rrb.TextDocumentView(name="Timings", origin="/timings"),
                    rrb.TimeSeriesView(name="Latency per frame (ms)", origin="/latency"))
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(camera, rrb.Horizontal(*lower), row_shares=[3, 2]),
            rrb.Vertical(patches, rrb.TimeSeriesView(name="Predictions (g)", origin="/predictions"), text,
                         row_shares=[2, 2, 2]),
            column_shares=[3, 2]),
        rrb.TimePanel(timeline="frame"),
        collapse_panels=False,
    )


# ------------------------------------------------------------------------------------------------ 3D clouds
def log_frame_clouds(trace, frame: Frame, intr: Intrinsics, stream, *, root: str = "world/detections",
                     voxel_m: float = 0.004) -> list[str]:
    """Log each detection of ``frame`` (above the trace's threshold) as ``/<root>/<id>`` (Points3D, its colours;
    chosen ones in ``CHOSEN_COLOUR``, flagged ones in ``FLAGGED_COLOUR``, with their box as ``<id>/box`` Boxes3D
    labelled with the measured size).
    Call it with the stream's time already set to the frame. ``voxel_m`` thins the clouds (0: every point).
    Returns the entity paths logged."""
    dets = trace.detections
    rank_of = {int(i): r for r, i in enumerate(trace.selection)}
    stored = {m.detection: m for m in measurements_of(trace)}
    idx = [int(i) for i in np.flatnonzero((dets.frame == frame.index) & trace.active())]
    paths = []
    for i in idx:
        pcd = detection_cloud(frame, dets, i, intr)
        if len(pcd.points) == 0:
            continue
        m = stored.get(i)
        size = None
        if i in rank_of and m is None:
            size = measure_cloud(pcd)
            m = Measurement.from_size(rank_of[i], i, frame.index, size) if size is not None else None
        shown = pcd.voxel_down_sample(voxel_m) if voxel_m > 0 else pcd
        pts = np.asarray(shown.points, np.float32)
        path = f"{root}/{i}"
        if i in rank_of:
            flag = trace.flags.of(i)
            colour = FLAGGED_COLOUR if flag is not None and flag.flagged else CHOSEN_COLOUR
            colours = np.array([rgb255(colour)], np.uint8)  # one colour for all: Rerun repeats it
        else:
            colours = (np.asarray(shown.colors) * 255).astype(np.uint8)
        stream.log(path, rr.Points3D(pts, colors=colours, radii=0.002))
        if m is not None:
            label = f"★{m.rank} h {m.height_mm:.0f} w {m.width_mm:.0f} d {m.depth_mm:.0f} mm"
            stream.log(f"{path}/box", rr.Transform3D(translation=m.center, mat3x3=np.asarray(m.R)),
                       rr.Boxes3D(half_sizes=[np.asarray(m.extent) / 2], colors=[rgb255(BOX_COLOUR)], labels=[label]))
            stream.log(f"{path}/measurement", rr.AnyValues(
                rank=m.rank, height_mm=m.height_mm, width_mm=m.width_mm, depth_mm=m.depth_mm, n_points=m.n_points))
        paths.append(path)
    return paths


def log_clouds(trace, recording, stream, *, timeline: str = "frame", root: str = "world/detections",
               voxel_m: float = 0.004) -> int:
    """Log every processed frame's detection clouds (``log_frame_clouds``) on ``timeline`` (sequence = frame index),
    clearing each frame's detection entities at the next processed frame so that none lingers. Returns the number of
    clouds logged; 0 (and nothing logged) for a recording without intrinsics."""
    if skip_reason(recording):
        return 0
    dets = trace.detections
    with_dets = sorted({int(f) for f in dets.frame[trace.active()]})
    processed = [int(f) for f in trace.frames]
    n = 0
    shown: list[str] = []
    for frame in recording.frames(indices=sorted(set(with_dets) | set(processed))):
        stream.set_time(timeline, sequence=frame.index)
        for p in shown:
            stream.log(p, rr.Clear(recursive=True))
        shown = log_frame_clouds(trace, frame, recording.intrinsics, stream, root=root, voxel_m=voxel_m) \
            if frame.index in with_dets else []
        n += len(shown)
    return n


# ---------------------------------------------------------------------------------------------------------- main
def _check_match(trace: Trace, recording: Recording) -> None:
    w, h = trace.recording.width, trace.recording.height
    if (w, h) != (recording.width, recording.height):
        raise MassvizError(f"the trace was made on {w}x{h} frames but this recording is "
                           f"{recording.width}x{recording.height}", recording.path)
    if len(trace.frames) and int(np.max(trace.frames)) >= recording.num_frames:
        raise MassvizError(f"the trace has frame {int(np.max(trace.frames))} but the recording has "
                           f"{recording.num_frames} frames", recording.path)


def _log_all(rec: rr.RecordingStream, trace: Trace, recording: Recording, *, video: str, step: int,
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
        rgb.log_frame(rec, frame.index, frame.rgb)
        log_depth(rec, frame.depth, _depth_file(recording, frame.index))
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


def _depth_file(recording: Recording, index: int) -> Path | None:
    files = getattr(recording, "depth_files", None) or []
    return Path(files[index]) if index < len(files) else None


def _look_at_m(recording: Recording, trace: Trace) -> float:
    """Where the 3D view looks: the median depth of the first processed frame."""
    if recording.intrinsics is None or len(trace.frames) == 0:
        return 1.0
    return scene_depth_m(recording.read_depth(int(trace.frames[0])))


def blueprint_for(trace: Trace, recording: Recording, *, points: bool = False) -> rrb.Blueprint:
    """``default_blueprint`` for this trace: its K patches, a 3D view (with intrinsics) looking at its scene."""
    return default_blueprint(len(trace.selection), has_3d=recording.intrinsics is not None,
                             flagged=[p.rank for p in trace.flags.flagged], look_at_m=_look_at_m(recording, trace),
                             points=points)


def log_trace(trace: Trace, recording: Recording, *, rrd: str | Path | None = None, spawn: bool = False,
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
    if stream is not None and (rrd is not None or spawn):
        raise ValueError("give either stream or rrd/spawn: a caller's stream keeps its own sinks")
    if stream is None and rrd is None and not spawn:
        raise ValueError("nothing to log to: give rrd, spawn=True or stream")
    _check_match(trace, recording)
    t0 = time.perf_counter()
    blueprint = blueprint_for(trace, recording, points=points)

    def log_into(rec: rr.RecordingStream) -> dict:
        rec.send_blueprint(blueprint, make_active=True, make_default=True)
        stats = _log_all(rec, trace, recording, video=video, step=step, max_points=max_points, progress=progress,
                         clouds=clouds, points=points)
        log_timings(rec, {**trace.timings, "log": time.perf_counter() - t0}, stats["frames"])
        try:
            rec.flush()
        except RuntimeError as err:  # the gRPC sink reports an unreachable viewer here
            if rrd is not None and not spawn:  # the file sink: a full disk or a failing write
                raise MassvizError(f"cannot write the recording ({err}; is the disk full?)", rrd) from None
            where = "the spawned Rerun viewer" if spawn else "Rerun"
            raise MassvizError(f"could not deliver the recording to {where} ({err}); without a display, "
                               "log to a file (rrd) and open it elsewhere with 'rerun FILE.rrd'") from None
        return stats

    if stream is not None:
        stats = log_into(stream)
        stats.update(recording_id=stream.get_recording_id(), rrd=None)
    else:
        rec = rr.RecordingStream(APPLICATION_ID, recording_id=str(uuid.uuid4()))
        if rrd is not None:
            rrd = Path(rrd)
            with atomic_path(rrd) as tmp:
                try:
                    _connect(rec, tmp, spawn)
                    stats = log_into(rec)
                finally:
                    rec.disconnect()
                if not tmp.is_file() or tmp.stat().st_size == 0:
                    raise MassvizError("Rerun wrote nothing (is logging disabled with RERUN=off?)", rrd)
        else:
            _connect(rec, None, spawn)
            try:
                stats = log_into(rec)
            finally:
                rec.disconnect()
        stats.update(recording_id=rec.get_recording_id(), rrd=None if rrd is None else str(rrd))
    stats["log_seconds"] = time.perf_counter() - t0
    return stats


# ------------------------------------------------------------------------------------------------------ notebook
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


def show_in_notebook(trace: Trace, recording: Recording, *, width: int = 1000, height: int = 640,
                     **options) -> dict:
    """Show ``trace`` in an inline Rerun viewer (rerun-notebook) in the current notebook cell, with massviz's default
    layout, and log it there (``log_trace(..., stream=...)``; ``options`` go to it). The viewer's code is served
    locally (``use_local_notebook_assets``), so no network is needed. Returns ``log_trace``'s stats."""
    use_local_notebook_assets()
    stream = rr.RecordingStream(APPLICATION_ID, recording_id=f"notebook-{recording.id}-{uuid.uuid4().hex[:8]}")
    stream.notebook_show(width=width, height=height,
                         blueprint=blueprint_for(trace, recording, points=bool(options.get("points"))))
    return log_trace(trace, recording, stream=stream, **options)


def _connect(rec: rr.RecordingStream, path: Path | None, spawn: bool) -> None:
    """Point ``rec`` at a file, a (spawned) viewer, or both."""
    if path is not None:
        check_room(path)  # Rerun's file sink hangs when its first write fails (a full disk): fail here instead
    if spawn:
        rr.spawn(connect=False)
    if path is not None and spawn:
        rec.set_sinks(rr.FileSink(os.fspath(path)), rr.GrpcSink())
    elif path is not None:
        rec.save(path)
    else:
        rec.connect_grpc()


# ------------------------------------------------------------------------------------------------- reading .rrd
def rrd_contents(path: str | Path) -> dict[str, set[str]]:
    """Entity path → its components (e.g. ``"AssetVideo:blob"``) in the first recording of an .rrd file
    (recording properties ``/__properties`` left out)."""
    from rerun.chunk import RrdReader

    path = Path(path)
    if not path.is_file():
        raise MassvizError("no such .rrd file", path)
    try:
        reader = RrdReader(path)
        try:
            schema = reader.store().schema()
        except Exception:  # noqa: BLE001 - files without a footer: read every chunk instead
            schema = reader.stream().collect().schema()
    except Exception as err:  # noqa: BLE001 - any read problem is a corrupt file
        raise MassvizError(f"not a readable Rerun .rrd file ({type(err).__name__}: {err})", path) from None
    out: dict[str, set[str]] = defaultdict(set)
    for col in schema.component_columns():
        if not col.is_property:
            out[col.entity_path].add(col.component)
    return dict(out)


def rrd_entities(path: str | Path) -> set[str]:
    """Entity paths logged in the first recording of an .rrd file."""
    return set(rrd_contents(path))


__all__ = ["log_trace", "log_flags", "default_blueprint", "log_clouds", "log_frame_clouds", "rrd_entities",
           "rrd_contents", "RgbLogger", "CLASS_IDS", "CHOSEN_ID", "FLAGGED_ID", "POINT_STEP", "MAX_POINTS",
           "blueprint_for", "show_in_notebook", "use_local_notebook_assets"]
