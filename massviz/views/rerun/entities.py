"""Entity loggers: each kind of data of the Rerun entity tree (``massviz.views.rerun``'s docstring) by one small
``log_*`` function, in the style of Rerun's ``rgbd`` and ``detect_and_track_objects`` examples. They read results
(a ``Trace``, a frame's arrays or bytes, a step's detections) and log them; none runs a stage or measures.
"""
from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import rerun as rr

from massviz.core.patches import model_view
from massviz.core.trace import Trace
from massviz.core.types import Detections, Frame, Intrinsics, class_name
from massviz.errors import MassvizError
from massviz.views.labels import short_reason
from massviz.views.palette import (
    BELOW_THRESHOLD_COLOUR,
    BOX_COLOUR,
    CHOSEN_COLOUR,
    FLAGGED_COLOUR,
    WITHOUT_FLAGGED_COLOUR,
    rgb255,
    track_colour,
)

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


def log_annotation_context(stream: rr.RecordingStream, k: int) -> None:
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
    stream.log("/camera", rr.AnnotationContext(infos), static=True)


# ---------------------------------------------------------------------------------------------------------- camera
def log_pinhole(stream: rr.RecordingStream, intr: Intrinsics, image_plane_distance: float) -> None:
    """The RGB camera (depth is aligned to it), right-down-forward, static."""
    stream.log("/camera", rr.Pinhole(focal_length=[intr.fx, intr.fy], principal_point=[intr.cx, intr.cy],
                                     width=intr.width, height=intr.height, camera_xyz=rr.ViewCoordinates.RDF,
                                     image_plane_distance=image_plane_distance), static=True)
    stream.log("/world", rr.ViewCoordinates.RDF, static=True)


def frustum_depth(depth: np.ndarray) -> float:
    """A frustum depth (m) that reaches about half-way to the scene: half the median valid depth, 0.1..2 m."""
    valid = depth[depth > 0]
    return 0.5 if valid.size == 0 else float(np.clip(0.5 * np.median(valid) / 1000.0, 0.1, 2.0))


# ------------------------------------------------------------------------------------------------------------- rgb
class RgbLogger:
    """Logs ``/camera/rgb``: the recording's video file (``Recording.video_file()``) as one asset + frame references,
    else each frame's own bytes (``Frame.rgb_encoded``, a PNG/JPEG frame file as read), else a JPEG of the decoded
    frame (formats without per-frame files, e.g. RealSense recordings, and a live camera's frames: ``recording``
    None).

    ``video``: ``"auto"`` (asset when Rerun can decode the codec, else JPEG frames), ``"asset"`` (always the asset,
    even if the viewer cannot decode it) or ``"images"`` (always JPEG frames). ``mode`` is what was chosen
    (``"asset"``, ``"files"`` once a frame's own bytes were logged, else ``"images"``); ``warning`` says why a video
    is not logged as an asset (or cannot be shown).
    """

    def __init__(self, recording, video: str = "auto", *, jpeg_quality: int = 90):
        if video not in ("auto", "asset", "images"):
            raise ValueError(f"video must be 'auto', 'asset' or 'images', not {video!r}")
        self.recording, self.warning, self.timestamps_ns = recording, None, None
        self.asset, self.quality = None, int(jpeg_quality)
        video_file = None if recording is None else recording.video_file()
        self.mode = "images" if video_file is None or video == "images" else "asset"
        if self.mode == "images":
            return
        self.asset = rr.AssetVideo(path=video_file)
        try:
            self.timestamps_ns = np.sort(np.asarray(self.asset.read_frame_timestamps_nanos(), dtype=np.int64))
        except Exception as err:  # noqa: BLE001 - Rerun reports unsupported codecs / broken containers as errors
            reason = f"Rerun cannot decode {Path(video_file).name} ({err})"
            if video == "auto":
                self.mode, self.asset = "images", None
                self.warning = f"{reason}: logging the processed frames as JPEG images instead of the video asset"
            else:
                self.warning = f"{reason}: the video asset is logged but the viewer will not show its frames"

    def log_static(self, stream: rr.RecordingStream) -> None:
        if self.asset is not None:
            stream.log("/camera/rgb", self.asset, static=True)

    def video_time_ns(self, index: int) -> int | None:
        """Presentation time of video frame ``index`` (from the container, else index / fps); None without asset."""
        if self.mode != "asset":
            return None
        if self.timestamps_ns is not None and index < len(self.timestamps_ns):
            return int(self.timestamps_ns[index])
        return int(round(index / (self.recording.fps or 30.0) * 1e9))

    def log_frame(self, stream: rr.RecordingStream, frame: Frame) -> None:
        """``/camera/rgb`` of one frame (the stream's time already set to it)."""
        if self.mode == "asset":
            stream.log("/camera/rgb", rr.VideoFrameReference(nanoseconds=self.video_time_ns(frame.index)))
        elif frame.rgb_encoded is not None:
            self.mode = "files"
            stream.log("/camera/rgb", rr.EncodedImage(contents=frame.rgb_encoded, media_type=frame.rgb_media_type))
        else:
            stream.log("/camera/rgb", rr.EncodedImage(
                contents=jpeg_bytes(frame.rgb, self.quality, f"frame {frame.index}",
                                    None if self.recording is None else self.recording.path),
                media_type="image/jpeg"))


#: JPEG quality of the patch tiles: they are logged wherever the running selection changes (every rank, often every
#: frame), so they are compressed; the exact pixels the model saw are in the trace (``Detections.patches``).
PATCH_JPEG_QUALITY = 85


def jpeg_bytes(rgb: np.ndarray, quality: int, what: str = "a frame", path=None) -> bytes:
    """``rgb`` (H×W×3 RGB) as JPEG bytes at ``quality``; an encoder failure is one line naming ``what``/``path``."""
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise MassvizError(f"cannot JPEG-encode {what}", path)
    return buf.tobytes()


# ----------------------------------------------------------------------------------------------- depth and points
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def log_depth(stream: rr.RecordingStream, depth: np.ndarray, encoded: bytes | None = None) -> None:
    """``/camera/depth``: the frame's 16-bit PNG as the reader read it (``Frame.depth_encoded``; logged as its own
    bytes, ``EncodedDepthImage``, no re-encode: ``depth`` is those bytes decoded, so they have been checked already),
    else the array as a ``DepthImage``."""
    if encoded is not None and bytes(encoded[:8]) == _PNG_SIGNATURE:
        stream.log("/camera/depth", rr.EncodedDepthImage(encoded, media_type=rr.components.MediaType.PNG,
                                                         meter=1000.0, colormap="turbo"))
    else:
        stream.log("/camera/depth", rr.DepthImage(depth, meter=1000.0, colormap="turbo"))


def scene_depth_m(depth: np.ndarray) -> float:
    """Median valid depth (m) of a frame, 0.1..10 m (1 m without depth): where the 3D view looks at."""
    valid = depth[depth > 0]
    return 1.0 if valid.size == 0 else float(np.clip(np.median(valid) / 1000.0, 0.1, 10.0))


def log_points(stream: rr.RecordingStream, depth: np.ndarray, rgb: np.ndarray, intr: Intrinsics, step: int,
               max_points: int) -> int:
    """``/world/points`` of one frame (at most ``max_points``, evenly subsampled); returns the number logged."""
    from massviz.measure3d.geometry import depth_to_points  # Open3D: imported only with --points

    points, colours = depth_to_points(depth, intr, rgb, step)
    if max_points > 0 and len(points) > max_points:
        keep = np.arange(0, len(points), math.ceil(len(points) / max_points))
        points, colours = points[keep], None if colours is None else colours[keep]
    stream.log("/world/points", rr.Points3D(points, colors=colours, radii=rr.Radius.ui_points(1.5)))
    return len(points)


# ------------------------------------------------------------------------------------------ detections and masks
def detection_class_ids(dets: Detections, idx: list[int], rank_of: dict[int, int], active: np.ndarray,
                        flagged=frozenset()) -> np.ndarray:
    """Annotation class id of each detection in ``idx``: flagged or chosen rank, below the selection's threshold
    (``active``: one bool per detection of ``dets``, True above it: ``Trace.active``, ``FrameResult.active``), or
    its class."""
    out = []
    for i in idx:
        if i in rank_of:
            out.append((FLAGGED_ID if i in flagged else CHOSEN_ID) + rank_of[i])
        elif not active[i]:
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


def log_detections(stream: rr.RecordingStream, dets: Detections, idx: list[int], class_ids: np.ndarray,
                   rank_of: dict[int, int]) -> None:
    """``/camera/detections`` of one frame (an empty frame clears the previous frame's boxes)."""
    if not idx:
        stream.log("/camera/detections", rr.Boxes2D(array=np.zeros((0, 4), np.float32),
                                                    array_format=rr.Box2DFormat.XYXY))
        return
    stream.log("/camera/detections", rr.Boxes2D(
        array=dets.xyxy[idx].astype(np.float32), array_format=rr.Box2DFormat.XYXY, class_ids=class_ids,
        colors=detection_colours(dets, idx, class_ids),
        labels=[detection_label(dets, i, rank_of.get(i), bool(c >= FLAGGED_ID)) for i, c in zip(idx, class_ids)]),
        rr.AnyValues(track=dets.track[idx].astype(np.int64), detection=np.asarray(idx, np.int64)))


def log_masks(stream: rr.RecordingStream, dets: Detections, idx: list[int], class_ids: np.ndarray,
              shape: tuple[int, int]) -> None:
    """``/camera/masks``: one segmentation image of the frame; chosen masks are drawn last (on top)."""
    seg = np.zeros(shape, dtype=np.uint8 if len(idx) == 0 or int(class_ids.max()) < 256 else np.uint16)
    for j in sorted(range(len(idx)), key=lambda j: class_ids[j] >= CHOSEN_ID):
        x1, y1, x2, y2 = (int(v) for v in dets.xyxy[idx[j]])
        seg[y1:y2, x1:x2][dets.mask(idx[j])] = class_ids[j]
    stream.log("/camera/masks", rr.SegmentationImage(seg, opacity=0.5))


# ------------------------------------------------------------------------------------------------------- patches
def log_patch(stream: rr.RecordingStream, rank: int, dets: Detections, i: int, patch: np.ndarray, flag=None,
              static: bool = False) -> None:
    """``/patches/<rank>`` at the stream's time (or ``static``): the model's input image and the numbers that went
    with it, and ``/patches/<rank>/outline`` around it in the chosen colour, or the flagged colour with why (``flag``,
    a ``massviz.core.flags.PatchFlag``)."""
    image = model_view(patch)
    flagged = flag is not None and flag.flagged
    stream.log(f"/patches/{rank}", rr.EncodedImage(contents=jpeg_bytes(image, PATCH_JPEG_QUALITY, f"patch {rank}"),
                                                   media_type="image/jpeg"),
               rr.AnyValues(
        a=float(dets.a[i]), b=float(dets.b[i]), d_mm=float(dets.d[i]), frame=int(dets.frame[i]),
        class_name=class_name(dets.class_id[i]), score=float(dets.score[i]), pred_g=float(dets.pred[i]),
        detection=int(i), track=int(dets.track[i]), flagged=bool(flagged), flag="" if not flagged else flag.reason),
               static=static)
    h, w = image.shape[:2]
    label = f"★{rank} ⚑ flagged: {short_reason(flag)}" if flagged else f"★{rank}"
    stream.log(f"/patches/{rank}/outline", rr.Boxes2D(
        array=[[0.5, 0.5, w - 0.5, h - 0.5]], array_format=rr.Box2DFormat.XYXY, labels=[label],
        colors=[rgb255(FLAGGED_COLOUR if flagged else CHOSEN_COLOUR)], radii=[2.0 if flagged else 1.0]), static=static)


class PatchTiles:
    """``/patches/<rank>`` kept equal to the current K nearest: ``update`` with the running selection (trace indices,
    nearest first) logs every rank whose occupant changed (a new detection, or one that moved to another rank) and
    clears ranks left empty, so that each tile shows, at every frame, the patch holding that rank then.

    ``source(i)`` returns (detections, index in them, RGB patch or None, flag or None) of trace detection ``i``; a
    detection without a patch is not shown (its rank is cleared)."""

    def __init__(self, source):
        self.source = source
        self.occupants: list[int] = []

    def update(self, stream: rr.RecordingStream, selection) -> list[int]:
        """Log the ranks that changed at the stream's current time; returns them."""
        new = [int(i) for i in selection]
        changed = []
        for r, i in enumerate(new):
            if r < len(self.occupants) and self.occupants[r] == i:
                continue
            dets, j, patch, flag = self.source(i)
            if patch is None or not patch.size:
                stream.log(f"/patches/{r}", rr.Clear(recursive=True))
            else:
                log_patch(stream, r, dets, j, patch, flag)
            changed.append(r)
        for r in range(len(new), len(self.occupants)):
            stream.log(f"/patches/{r}", rr.Clear(recursive=True))
            changed.append(r)
        self.occupants = new
        return changed


# --------------------------------------------------------------------------------------------------- predictions
def log_predictions(stream: rr.RecordingStream, trace: Trace) -> None:
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
        stream.log(path, rr.SeriesLines(names=name, colors=rgb255(FLAGGED_COLOUR if flagged else CHOSEN_COLOUR)),
                   static=True)
        for t in sorted({int(dets.frame[i]), last}):
            stream.set_time("frame", sequence=t)
            stream.log(path, rr.Scalars(float(dets.pred[i])))
    if trace.estimate >= 0:
        stream.log("/predictions/estimate", rr.SeriesLines(names="estimate", colors=(255, 255, 255), widths=2),
                   rr.SeriesPoints(names="estimate", colors=(255, 255, 255), markers="diamond", marker_sizes=6),
                   static=True)
        stream.set_time("frame", sequence=last)
        stream.log("/predictions/estimate", rr.Scalars(float(trace.estimate)))
    flags = trace.flags
    if flags.flagged and flags.estimate_without >= 0:
        path = "/predictions/estimate_without_flagged"
        colour = rgb255(WITHOUT_FLAGGED_COLOUR)
        stream.log(path, rr.SeriesLines(names="estimate without flagged patches", colors=colour, widths=2),
                   rr.SeriesPoints(names="estimate without flagged patches", colors=colour, markers="diamond",
                                   marker_sizes=6), static=True)
        stream.set_time("frame", sequence=last)
        stream.log(path, rr.Scalars(float(flags.estimate_without)))
    gt = trace.ground_truth_mass
    if gt is not None:
        stream.log("/predictions/ground_truth", rr.SeriesLines(names="ground truth", colors=(0, 200, 0), widths=2),
                   static=True)
        for t in sorted({first, last}):
            stream.set_time("frame", sequence=t)
            stream.log("/predictions/ground_truth", rr.Scalars(gt))


RUNNING_COLOUR = (90, 170, 255)


def log_running(stream: rr.RecordingStream, trace: Trace) -> None:
    """``/predictions/running_estimate``: the estimate after each processed frame (``Trace.running_estimate``, from
    the first frame with a selected patch), and ``/latency/<stage>``: each processed frame's seconds per stage, in
    ms (when the trace has them)."""
    frames = np.asarray(trace.frames, dtype=np.int64)
    if len(frames) == 0:
        return
    running = trace.running_estimate()
    keep = running >= 0
    if keep.any():
        stream.log("/predictions/running_estimate", rr.SeriesLines(names="running estimate (K nearest so far)",
                                                                   colors=RUNNING_COLOUR, widths=2), static=True)
        stream.send_columns("/predictions/running_estimate", indexes=[rr.TimeColumn("frame", sequence=frames[keep])],
                            columns=rr.Scalars.columns(scalars=running[keep]))
    for stage, seconds in trace.frame_timings.items():
        seconds = np.asarray(seconds, dtype=np.float64)
        if len(seconds) == len(frames):
            stream.send_columns(f"/latency/{stage}", indexes=[rr.TimeColumn("frame", sequence=frames)],
                                columns=rr.Scalars.columns(scalars=1000.0 * seconds))


# ----------------------------------------------------------------------------------------------------- text, log
def text_log(text: str, level: str = "info") -> rr.TextLog:
    """A ``/log`` entry at an ``Event`` level (``debug``, ``info``, ``warn``; anything else: info), as Rerun's
    ``TextLogLevel``."""
    return rr.TextLog(str(text), level=getattr(rr.TextLogLevel, str(level).upper(), rr.TextLogLevel.INFO))


def log_events(stream: rr.RecordingStream, events, first_frame: int) -> None:
    """``/log``: the trace's typed events at their frames (frame -1, e.g. cache reuse: at the first frame), at
    their level."""
    for e in events:
        frame = int(e.frame)
        stream.set_time("frame", sequence=frame if frame >= 0 else first_frame)
        stream.log("/log", text_log(e.message, e.level))


def log_flags(stream: rr.RecordingStream, trace: Trace) -> None:
    """``/log`` WARN entries of ``trace.flags``: each flagged patch at its frame, the summary line at the last frame."""
    flags = trace.flags
    if not flags.flagged:
        return
    for p in flags.flagged:
        stream.set_time("frame", sequence=p.frame)
        stream.log("/log", rr.TextLog(f"flagged patch ★{p.rank} (frame {p.frame}, track {p.track}, severity "
                                      f"{p.severity}): probably not the container: {p.reason}",
                                      level=rr.TextLogLevel.WARN))
    last = int(trace.frames[-1]) if len(trace.frames) else max(p.frame for p in flags.patches)
    stream.set_time("frame", sequence=last)
    stream.log("/log", rr.TextLog(flags.warning(), level=rr.TextLogLevel.WARN))


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
                  + (f"⚑ {short_reason(flag_of[int(i)])} |" if int(i) in flag_of and flag_of[int(i)].flagged
                     else "|") for r, i in enumerate(trace.selection)]
    return "\n".join(lines) + "\n"


def log_summary(stream: rr.RecordingStream, trace: Trace) -> None:
    stream.log("/summary", rr.TextDocument(summary_markdown(trace), media_type=rr.MediaType.MARKDOWN), static=True)


def log_timings(stream: rr.RecordingStream, timings: dict, n_frames: int) -> None:
    """``/timings``: seconds per stage (the pipeline's and ``log``, this logging's cost), static."""
    rows = ["| stage | seconds | ms / frame |", "|---|---:|---:|"]
    for stage, seconds in timings.items():
        per = f"{1000 * seconds / n_frames:.1f}" if n_frames else "–"
        rows.append(f"| {stage} | {seconds:.3f} | {per} |")
        stream.log(f"/timings/{stage}", rr.Scalars(float(seconds)), static=True)
    stream.log("/timings", rr.TextDocument("\n".join(rows) + "\n", media_type=rr.MediaType.MARKDOWN), static=True)



# ------------------------------------------------------------------------------------------------ 3D clouds
class _RowsOf:
    """A Rerun component column given for some rows of a chunk only, null in the others (``present``): what lets one
    ``send_columns`` carry rows of different components, e.g. a cloud at its frame and its ``Clear`` at the next."""

    def __init__(self, column, present):
        self.column, self.present = column, np.asarray(present, bool)
        self.component_descriptor = column.component_descriptor

    def as_arrow_array(self):
        import pyarrow as pa

        dense = self.column.as_arrow_array()
        lengths = np.zeros(len(self.present), np.int64)
        lengths[self.present] = np.diff(dense.offsets.to_numpy(zero_copy_only=False))
        offsets = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int32)
        return pa.ListArray.from_arrays(pa.array(offsets), dense.values, mask=pa.array(~self.present))


def log_detection_clouds(stream, clouds: dict, *, root: str = "world/detections", voxel_m: float = CLOUD_VOXEL_M,
                         frame: int | None = None, cleared_at: int | None = None,
                         timeline: str = "frame") -> dict[int, str]:
    """Log the clouds of one frame's detections (``clouds``: {detection index in the trace: cleaned Open3D cloud},
    as the measure stage made them, ``massviz.measure3d.stage.MeasureStage``) as ``/<root>/<id>`` (Points3D in their
    RGB colours): at the stream's time, or with ``frame`` at that time of ``timeline``, and with ``cleared_at`` a
    recursive ``Clear`` at that later time, sent in the same chunk as the cloud (a chunk carries its own schema, so
    one chunk a cloud instead of two keeps an .rrd smaller). ``voxel_m`` thins the clouds (0: every point).
    Returns {id: entity path} of the clouds logged (empty clouds are not). ``log_cloud_overlays`` adds what the
    selection says (colours of the chosen ones, their measured boxes)."""
    paths = {}
    for i, pcd in clouds.items():
        if len(pcd.points) == 0:
            continue
        shown = pcd.voxel_down_sample(voxel_m) if voxel_m > 0 else pcd
        path = f"{root}/{int(i)}"
        points = np.asarray(shown.points, np.float32)
        colours = (np.asarray(shown.colors) * 255).astype(np.uint8)
        if frame is None:
            stream.log(path, rr.Points3D(points, colors=colours, radii=0.002))
        else:
            times = [int(frame)] if cleared_at is None else [int(frame), int(cleared_at)]
            cloud = [True] if cleared_at is None else [True, False]
            columns = [_RowsOf(c, cloud) for c in (*rr.Points3D.columns(positions=points, colors=colours)
                                                   .partition([len(points)]),
                                                   *rr.Points3D.columns(radii=[0.002]).partition([1]))]
            if cleared_at is not None:
                columns += [_RowsOf(c, [False, True]) for c in rr.Clear.columns(is_recursive=[True]).partition([1])]
            stream.send_columns(path, indexes=[rr.TimeColumn(timeline, sequence=times)], columns=columns)
        paths[int(i)] = path
    return paths


def log_cloud_overlays(stream, trace: Trace, paths: dict[int, str], *, timeline: str = "frame") -> None:
    """For each chosen detection whose cloud is at ``paths`` ({id: entity path}, ``log_detection_clouds``), at its
    frame: the cloud recoloured (``CHOSEN_COLOUR``, flagged ones ``FLAGGED_COLOUR``) and its measured box as
    ``<path>/box`` (Boxes3D labelled with the size) and ``<path>/measurement`` (AnyValues), from
    ``Trace.measurements`` (what the measure stage measured; none when the trace has no measurement: a view never
    measures)."""
    dets = trace.detections
    stored = {m.detection: m for m in trace.measurements}
    for i in (int(i) for i in trace.selection):
        path = paths.get(i)
        if path is None:
            continue
        stream.set_time(timeline, sequence=int(dets.frame[i]))
        flag = trace.flags.of(i)
        colour = FLAGGED_COLOUR if flag is not None and flag.flagged else CHOSEN_COLOUR
        # one colour for all points (Rerun repeats it), logged after the RGB colours at the same time: it wins
        stream.log(path, rr.Points3D.from_fields(colors=np.array([rgb255(colour)], np.uint8)))
        m = stored.get(i)
        if m is not None:
            label = f"★{m.rank} h {m.height_mm:.0f} w {m.width_mm:.0f} d {m.depth_mm:.0f} mm"
            stream.log(f"{path}/box", rr.Transform3D(translation=m.center, mat3x3=np.asarray(m.R)),
                       rr.Boxes3D(half_sizes=[np.asarray(m.extent) / 2], colors=[rgb255(BOX_COLOUR)], labels=[label]))
            stream.log(f"{path}/measurement", rr.AnyValues(
                rank=m.rank, height_mm=m.height_mm, width_mm=m.width_mm, depth_mm=m.depth_mm, n_points=m.n_points))
