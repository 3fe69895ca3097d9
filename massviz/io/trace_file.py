"""Trace files: a ``massviz.core.trace.Trace`` saved to a single ``.npz`` (no pickle) and read back, checked.

The file holds a JSON header + parallel arrays + packed masks + PNG-encoded patches. Traces carry their tracks (array
``det_track``) and flags (header ``flags``); a file of format 2 written before them lacks them and :func:`load_trace`
computes them (``massviz.core.trace.analyse_trace``, pure computation, only what is missing or stale); the
detections' ground-truth overlaps, when the file lacks them, are read by :func:`load_trace`
(``massviz.io.ground_truth.with_ground_truth``). Events carry their ``reason`` (a sixth element, when there is one);
the rejected objects' events of a file written before reasons get theirs from their message on load. A trace file is untrusted (a replay source, a cache entry):
:func:`load_trace` bounds array sizes before they are allocated and checks every field (:func:`check_trace_arrays`).
"""
from __future__ import annotations

import dataclasses
import io
import json
import re
from pathlib import Path

import cv2
import numpy as np

from massviz.core.flags import Flags
from massviz.core.measurement import Measurement
from massviz.core.selection import REJECTED_PREFIX, Selection
from massviz.core.trace import Event, Trace, analyse_trace
from massviz.core.types import Detections, PackedMask, RecordingInfo
from massviz.errors import MassvizError
from massviz.io.atomic import atomic_path
from massviz.io.ground_truth import with_ground_truth
from massviz.io.untrusted import MAX_INDEX, load_npz_checked, parse_json, png_header_size

TRACE_FORMAT = 2  # 2: typed events, recording info as a dataclass


# -- persistence -----------------------------------------------------------------------------------------------
def save_trace(trace: Trace, path: str | Path) -> Path:
    """Write ``trace`` atomically to ``path`` (.npz)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    dets = trace.detections
    header = {
        "format": TRACE_FORMAT, "recording": trace.recording.to_dict(), "detector": trace.detector,
        "detect_threshold": trace.detect_threshold, "threshold": trace.threshold, "k": trace.k,
        "stride": trace.stride, "estimate": trace.estimate, "weights_id": trace.weights_id,
        "timings": trace.timings, "events": [e.to_list() for e in trace.events],
        "measurements": [m.to_dict() for m in trace.measurements],
        "flags": None if trace.flags is None else trace.flags.to_dict(),
        "frame_timing_stages": list(trace.frame_timings),
        "ground_truth_source": trace.ground_truth_source, "compute": trace.compute,
    }
    masks = [m if m is not None else PackedMask(np.zeros((0, 0), bool)) for m in dets.masks]
    patch_idx = [i for i, p in enumerate(dets.patches) if p is not None]
    encoded = [_encode_png(dets.patches[i]) for i in patch_idx]
    arrays = {
        "header": np.frombuffer(json.dumps(header, default=_json_default).encode(), dtype=np.uint8),
        "frames": trace.frames, "selection": trace.selection, "excluded": trace.excluded,
        **{f"det_{name}": getattr(dets, name) for name in Detections._ARRAYS},
        "mask_shapes": np.array([m.shape for m in masks], dtype=np.int32).reshape(-1, 2),
        "mask_sizes": np.array([len(m.bits) for m in masks], dtype=np.int64),
        "mask_bits": np.concatenate([m.bits for m in masks]) if masks else np.zeros(0, np.uint8),
        "patch_index": np.array(patch_idx, dtype=np.int64),
        "patch_sizes": np.array([len(e) for e in encoded], dtype=np.int64),
        "patch_bytes": np.concatenate(encoded) if encoded else np.zeros(0, np.uint8),
        **{f"frame_time_{i}": np.asarray(v, np.float64) for i, v in enumerate(trace.frame_timings.values())},
    }
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, **arrays)
    return path

def load_trace(path: str | Path) -> Trace:
    """Read a trace saved by :func:`save_trace`. The file is untrusted (a replay source, a cache entry): array sizes are
    bounded before they are allocated (``massviz.io.untrusted.load_npz_checked``) and every field is checked
    (:func:`check_trace_arrays`); anything wrong is one ``MassvizError`` naming the file."""
    path = Path(path)
    try:
        data = load_npz_checked(path)
        header = parse_json(data["header"].tobytes(), path, "trace header", MassvizError)
    except Exception as err:  # noqa: BLE001 - any read problem is a corrupt trace file
        raise MassvizError(f"not a massviz trace ({type(err).__name__}: {_first_line(err)})", path) from None
    if not isinstance(header, dict) or header.get("format") != TRACE_FORMAT:
        found = header.get("format") if isinstance(header, dict) else None
        raise MassvizError(f"trace format {found!r} is not supported (expected {TRACE_FORMAT})"[:300], path)
    try:
        check_trace_arrays(header, data)
        trace = _from_arrays(header, data)
    except Exception as err:  # noqa: BLE001 - a field missing, of the wrong type, shape or value
        raise MassvizError(f"not a complete massviz trace ({type(err).__name__}: {_first_line(err)})",
                           path) from None
    # a file from before the overlaps, or made without them: read them now; tracks and flags a file lacks (or flags
    # that do not describe it) are computed
    return analyse_trace(with_ground_truth(trace))


def _event(fields: list) -> Event:
    """An event of the file; a ``skipped`` event of a file written before events had reasons gets the reason its
    message names (the depth detector's "not a container candidate: border-cut object (box ...)")."""
    event = Event(*fields)
    if len(fields) <= 5 and event.kind == "skipped" and event.message.startswith(REJECTED_PREFIX):
        reason = re.sub(r"[,(].*", "", event.message[len(REJECTED_PREFIX):]).strip()
        event = event._replace(reason=reason)
    return event

def _from_arrays(header: dict, data: dict) -> Trace:
    offsets = np.concatenate([[0], np.cumsum(data["mask_sizes"])])
    masks = [PackedMask(shape=tuple(s), bits=data["mask_bits"][offsets[i]:offsets[i + 1]])
             for i, s in enumerate(data["mask_shapes"])]
    patches = [None] * len(masks)
    poff = np.concatenate([[0], np.cumsum(data["patch_sizes"])])
    for j, i in enumerate(data["patch_index"]):
        patches[int(i)] = _decode_png(data["patch_bytes"][poff[j]:poff[j + 1]])
    # det_track and the flags are absent from files written before tracks existed: made by analyse_trace (load_trace)
    dets = Detections(**{name: data[f"det_{name}"] for name in Detections._ARRAYS
                         if name not in Detections._OPTIONAL or f"det_{name}" in data}, masks=masks, patches=patches)
    return Trace(recording=RecordingInfo.from_dict(header["recording"]), detector=header["detector"],
               detect_threshold=header["detect_threshold"], threshold=header["threshold"], k=header["k"],
               stride=header["stride"], frames=data["frames"], detections=dets, selection=data["selection"],
               estimate=header["estimate"], weights_id=header["weights_id"], timings=header["timings"],
               events=[_event(e) for e in header["events"]], excluded=data["excluded"],
               measurements=[Measurement.from_dict(m) for m in header.get("measurements", [])],
               flags=Flags.from_dict(header["flags"]) if isinstance(header.get("flags"), dict) else None,
               frame_timings={name: data[f"frame_time_{i}"]
                              for i, name in enumerate(header.get("frame_timing_stages", []))},
                 ground_truth_source=str(header.get("ground_truth_source", ""))[:10_000],
                 compute=dict(header.get("compute") or {}))


def check_trace_arrays(header: dict, data: dict) -> None:
    """``ValueError`` naming the field when a saved trace's header or arrays are inconsistent or out of range: every
    detection array has one entry per detection, boxes are non-empty integers >= 0, masks and patches have their
    box's size (checked from the stored sizes and PNG headers, before anything is unpacked or decoded), scores are in
    [0, 1], d/a/b/pred finite or NaN, selection and exclusions index detections, thresholds in [0, 1), k and stride
    integers >= 1 (``Selection.check``; the header then holds the values it returns), the estimate finite."""
    import math

    def ints(name, lo=0, hi=MAX_INDEX, ndim=1):
        a = np.asarray(data[name])
        if a.dtype.kind not in "iu" or a.ndim != ndim:
            raise ValueError(f"{name} must be a {ndim}-d integer array, got {a.dtype} {a.shape}")
        if a.size and (int(a.min()) < lo or int(a.max()) > hi):
            raise ValueError(f"{name} values must lie in [{lo}, {hi}]")
        return a.astype(np.int64)

    n = len(ints("det_frame"))
    boxes = ints("det_xyxy", ndim=2)
    # an empty box (x1 == x2 or y1 == y2) is a detection the pipeline keeps and skips: a sub-pixel Mask R-CNN box,
    # cut to integers with int() (detect.maskrcnn.outputs_to_detections), has no pixel, so no depth
    if boxes.shape != (n, 4) or not ((boxes[:, 2] >= boxes[:, 0]) & (boxes[:, 3] >= boxes[:, 1])).all():
        raise ValueError(f"det_xyxy: every box must be 4 integers x1 <= x2, y1 <= y2 (one per detection, {n})")
    ints("det_class_id", lo=-1, hi=10_000)
    if "det_track" in data and len(ints("det_track", hi=MAX_INDEX)) != n:  # absent in files from before tracks
        raise ValueError(f"det_track: one track id >= 0 per detection ({n})")
    for name in ("det_score", "det_d", "det_a", "det_b", "det_pred"):
        a = np.asarray(data[name])
        if a.dtype.kind != "f" or a.shape != (n,):
            raise ValueError(f"{name} must be {n} floats, got {a.dtype} {a.shape}")
        if np.isinf(a).any() or (name == "det_score" and (np.isnan(a).any() or (a < 0).any() or (a > 1).any())):
            raise ValueError(f"{name}: values must be finite{' and in [0, 1]' if name == 'det_score' else ' or NaN'}")
    # the ground-truth overlaps (absent in files from before them): NaN / -1 unknown
    for name in ("det_gt_iou", "det_gt_fraction"):
        if name in data:
            a = np.asarray(data[name])
            if a.dtype.kind != "f" or a.shape != (n,) or (a[np.isfinite(a)] < 0).any() or \
                    (a[np.isfinite(a)] > 1).any() or np.isinf(a).any():
                raise ValueError(f"{name} must be {n} floats in [0, 1] or NaN, got {a.dtype} {a.shape}")
    if "det_gt_instance" in data and len(ints("det_gt_instance", lo=-1, hi=65535)) != n:
        raise ValueError(f"det_gt_instance: one instance id in [-1, 65535] per detection ({n})")
    shapes = ints("mask_shapes", ndim=2)
    sizes = ints("mask_sizes", hi=2**62)
    bits = np.asarray(data["mask_bits"])
    if shapes.shape != (n, 2) or sizes.shape != (n,) or bits.dtype != np.uint8 or int(sizes.sum()) != len(bits):
        raise ValueError("mask_shapes / mask_sizes / mask_bits do not describe one mask per detection")
    box_shape = np.stack([boxes[:, 3] - boxes[:, 1], boxes[:, 2] - boxes[:, 0]], axis=1) if n else shapes
    empty = (shapes == 0).all(axis=1)
    if not ((shapes == box_shape).all(axis=1) | empty).all():
        raise ValueError("mask_shapes: a mask is not the size of its box")
    if not (sizes == (shapes[:, 0] * shapes[:, 1] + 7) // 8).all():
        raise ValueError("mask_sizes: a mask's packed size does not match its shape")
    index, psizes = ints("patch_index", hi=max(n - 1, 0)), ints("patch_sizes", hi=2**40)
    pbytes = np.asarray(data["patch_bytes"])
    if len(index) != len(psizes) or len(set(index.tolist())) != len(index) or int(psizes.sum()) != len(pbytes) \
            or pbytes.dtype != np.uint8 or (len(index) and n == 0):
        raise ValueError("patch_index / patch_sizes / patch_bytes do not describe one PNG per kept patch")
    offsets = np.concatenate([[0], np.cumsum(psizes)]).astype(np.int64)
    for j, i in enumerate(index):
        size = png_header_size(pbytes[offsets[j]:offsets[j] + 24].tobytes())
        if size is None:
            raise ValueError(f"patch of detection {i} is not a PNG")
        w, h = size
        if (h, w) != tuple(box_shape[i]):
            raise ValueError(f"patch of detection {i} is {w}x{h}, not the size of its box")
    for name in ("selection", "excluded"):
        a = ints(name)
        if len(a) and (n == 0 or int(a.max()) >= n):
            raise ValueError(f"{name} indexes a detection that does not exist ({n} detections)")
    ints("frames")
    for name in ("detect_threshold", "threshold", "k", "stride"):
        rule = "threshold" if name.endswith("threshold") else name
        header[name] = Selection.check(rule, header[name], f"header {name}")
    est = header["estimate"]
    if isinstance(est, bool) or not isinstance(est, (int, float)) or not math.isfinite(est):
        raise ValueError(f"header estimate must be a finite number, got {est!r}"[:200])
    if not isinstance(header["events"], list) or not isinstance(header["recording"], dict):
        raise ValueError("header events must be a list and recording an object")
    check_trace_header(header, data)


def check_trace_header(header: dict, data: dict) -> None:
    """``ValueError`` naming the field when a saved trace's header fields have the wrong type or a non-finite value
    (a trace from elsewhere: a list as detector name, text as timings or fps, NaN intrinsics)."""
    import math

    from massviz.core.trace import EVENT_KINDS
    from massviz.errors import DataError
    from massviz.io.untrusted import number, text_id

    def text(value, what, optional=False, limit=10_000):
        if optional and value is None:
            return
        if not isinstance(value, str) or len(value) > limit:
            raise ValueError(f"header {what} must be text (at most {limit} characters), got "
                             f"{type(value).__name__}")

    def num(value, what, **bounds):
        try:
            number(value, f"header {what}", **bounds)
        except DataError as err:
            raise ValueError(str(err)) from None

    det = header["detector"]
    if not isinstance(det, dict) or not all(isinstance(det.get(k, ""), str) and len(det.get(k, "")) <= 200
                                            for k in ("name", "precision")):
        raise ValueError(f"header detector must be an object with a text name, got {type(det).__name__}")
    text(header.get("weights_id"), "weights_id", optional=True, limit=200)
    timings = header["timings"]
    if not isinstance(timings, dict):
        raise ValueError(f"header timings must be an object of seconds, got {type(timings).__name__}")
    for name, seconds in timings.items():
        num(seconds, f"timings.{str(name)[:40]}", lo=0)
    for i, event in enumerate(header["events"]):
        if not (isinstance(event, list) and 2 <= len(event) <= 6):
            raise ValueError(f"header events[{i}] must be [frame, message, kind, level, detection, reason]")
        num(event[0], f"events[{i}] frame", lo=-1, hi=MAX_INDEX, integral=True)
        text(event[1], f"events[{i}] message")
        if len(event) > 2 and event[2] not in EVENT_KINDS:
            raise ValueError(f"header events[{i}] kind must be one of {', '.join(EVENT_KINDS)}")
        if len(event) > 3 and event[3] not in ("debug", "info", "warn"):
            raise ValueError(f"header events[{i}] level must be debug, info or warn")
        if len(event) > 4:
            num(event[4], f"events[{i}] detection", lo=-1, hi=MAX_INDEX, integral=True)
        if len(event) > 5:
            text(event[5], f"events[{i}] reason")
    info = header["recording"]
    try:
        text_id(info.get("id"), "header recording.id", None)
    except DataError as err:
        raise ValueError(str(err)) from None
    for name in ("path", "config_id", "kind", "rgb"):
        if name in info:
            text(info[name] if not isinstance(info[name], int) or isinstance(info[name], bool) else str(info[name]),
                 f"recording.{name}")
    for name in ("width", "height", "num_frames"):
        if name in info:
            num(info[name], f"recording.{name}", lo=0, hi=MAX_INDEX, integral=True)
    if "fps" in info:
        num(info["fps"], "recording.fps", lo=0, hi=1000)
    if "meta" in info and not isinstance(info["meta"], dict):
        raise ValueError("header recording.meta must be an object")
    intr = info.get("intrinsics")
    if intr is not None:
        if not isinstance(intr, dict) or not {"fx", "fy", "cx", "cy", "width", "height"} <= set(intr):
            raise ValueError("header recording.intrinsics must be an object with fx, fy, cx, cy, width, height")
        for name in ("fx", "fy"):
            num(intr[name], f"recording.intrinsics.{name}", lo=0, lo_open=True)
        for name in ("width", "height"):
            num(intr[name], f"recording.intrinsics.{name}", lo=1, hi=MAX_INDEX, integral=True)
        num(intr["cx"], "recording.intrinsics.cx", lo=0, hi=intr["width"])
        num(intr["cy"], "recording.intrinsics.cy", lo=0, hi=intr["height"])
    measurements = header.get("measurements", [])
    fields = [f.name for f in dataclasses.fields(Measurement)]
    if not isinstance(measurements, list) or not all(isinstance(m, dict) and all(f in m for f in fields)
                                                     for m in measurements):
        raise ValueError(f"header measurements must be a list of objects with {', '.join(fields)}")
    for m in measurements:
        for name in ("rank", "detection", "frame", "n_points"):
            num(m[name], f"measurements.{name}", lo=-1, hi=MAX_INDEX, integral=True)
        for name in ("height_mm", "width_mm", "depth_mm"):
            num(m[name], f"measurements.{name}")
        try:
            shapes = [np.asarray(m[k], dtype=np.float64).shape for k in ("center", "extent", "R")]
        except (TypeError, ValueError):
            shapes = []
        if shapes != [(3,), (3,), (3, 3)]:
            raise ValueError("header measurements: center and extent must hold 3 numbers, R 3×3")
    if "flags" in header and header["flags"] is not None and not isinstance(header["flags"], dict):
        raise ValueError("header flags must be an object")
    stages = header.get("frame_timing_stages", [])
    if not isinstance(stages, list) or not all(isinstance(s, str) and len(s) <= 100 for s in stages):
        raise ValueError("header frame_timing_stages must be a list of names")
    for i in range(len(stages)):
        a = np.asarray(data[f"frame_time_{i}"])
        if a.dtype.kind != "f" or not np.isfinite(a).all():
            raise ValueError(f"frame_time_{i} must be finite floats")
    text(header.get("ground_truth_source", ""), "ground_truth_source")
    compute = header.get("compute") or {}
    if not isinstance(compute, dict) or len(compute) > 20 or not all(
            isinstance(k, str) and len(k) <= 40 and (isinstance(v, str) and len(v) <= 200
                                                     or isinstance(v, int) and not isinstance(v, bool))
            for k, v in compute.items()):
        raise ValueError("header compute must be an object of at most 20 short names and texts or integers")
    if not math.isfinite(float(header["estimate"])):
        raise ValueError("header estimate must be a finite number")


def _first_line(err: BaseException) -> str:
    lines = str(err).splitlines()
    return lines[0][:300] if lines else type(err).__name__


def _encode_png(rgb: np.ndarray) -> np.ndarray:
    ok, buf = cv2.imencode(".png", cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR))
    assert ok
    return buf.reshape(-1)


def _decode_png(buf: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(cv2.imdecode(np.asarray(buf, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def _json_default(obj):
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (Path, io.IOBase)):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


__all__ = ["TRACE_FORMAT", "save_trace", "load_trace", "check_trace_arrays"]
