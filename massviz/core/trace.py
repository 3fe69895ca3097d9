"""The trace: everything one pipeline run computed, with each stage's wall time.

Every consumer (Rerun logger, Open3D sink, notebooks, evaluation, training extraction) only *reads* a ``Trace``.
``reselect`` recomputes the selection, the estimate and their events for another K, threshold or set of excluded detections
without running the detector or the model again (every detection already carries its prediction).

A trace saves to a single ``.npz`` (no pickle): JSON header + parallel arrays + packed masks + PNG-encoded patches.

Every trace carries its **tracks** (``detections.track``, ``massviz.core.tracks``) and the **flags** of its selection
(``flags``, ``massviz.core.flags.analyse``: which chosen patches are probably not the container, and the estimate
without them). Both are made when a trace is made (untracked detections are tracked, flags of another selection are
recomputed: ``reselect`` and ``dataclasses.replace`` get fresh flags), saved with it (array ``det_track``, header
``flags``) and, when a file of format 2 written before them lacks them, computed on load.
"""
from __future__ import annotations

import dataclasses
import io
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np

from massviz.io.atomic import atomic_path
from massviz.errors import MassvizError
from massviz.core.flags import Flags, analyse
from massviz.core.selection import NearestOrder, estimate_mass, select_k_nearest
from massviz.core.tracks import assign_tracks
from massviz.core.types import Detections, GroundTruth, PackedMask, RecordingInfo, class_name

TRACE_FORMAT = 2  # 2: typed events, recording info as a dataclass


class Event(NamedTuple):
    """One decision worth reading, at a frame (-1: not tied to a frame).

    ``kind`` is one of ``EVENT_KINDS``: ``chosen`` (a patch was selected), ``estimate`` (the estimate was made),
    ``not_estimated``, ``skipped`` (a detection that cannot be used, e.g. its mask has no depth), ``cache`` (detections
    reused from the trace cache), ``measured`` (the 3D stage's size of a chosen patch), ``warning`` and ``info``.
    ``level`` is ``debug``, ``info`` or ``warn`` (the Rerun ``/log`` level). ``detection`` is the index into the
    trace's detections the event is about (-1: none).
    """

    frame: int
    message: str
    kind: str = "info"
    level: str = "info"
    detection: int = -1

    @property
    def is_selection(self) -> bool:
        """Events that belong to one selection (replaced when the trace is re-selected)."""
        return self.kind in SELECTION_KINDS

    def to_list(self) -> list:
        return [int(self.frame), str(self.message), self.kind, self.level, int(self.detection)]


EVENT_KINDS = ("chosen", "estimate", "not_estimated", "skipped", "cache", "measured", "warning", "info")
SELECTION_KINDS = frozenset({"chosen", "estimate", "not_estimated"})
LEVELS = ("debug", "info", "warn")


@dataclass
class Trace:
    """Output of ``massviz.core.pipeline.run`` for one recording.

    - ``recording``: ``RecordingInfo`` (id, path, size, frame count, intrinsics, meta; ``.ground_truth``).
    - ``detector``: the detector's name and settings; ``detect_threshold`` the score threshold it ran at.
    - ``threshold``, ``k``, ``stride``: the selection settings this trace's ``selection``/``estimate`` use.
    - ``frames``: indices of the processed frames.
    - ``detections``: every detection (score > detect_threshold) with d, a, b, the model's ``pred`` and, for the
      ``keep_patches`` nearest ones, the RGB patch.
    - ``selection``: indices into ``detections`` of the chosen patches, nearest first.
    - ``estimate``: mean of the chosen predictions in grams; -1 when nothing was selected (not estimated).
    - ``excluded``: detection indices the user excluded (never selected).
    - ``timings``: wall time per stage in seconds; ``events``: typed ``Event`` decisions worth reading.
    - ``measurements``: the 3D stage's measured size of each chosen detection (``massviz.core.geometry.Measurement``
      as dicts, read them with ``geometry3d.measurements_of``); empty when not measured. ``reselect`` drops them
      (they belong to the old selection).
    - ``frame_timings``: seconds per stage for each processed frame (stage -> array aligned with ``frames``; empty
      for traces made before massviz recorded them).
    - ``flags``: ``massviz.core.flags.Flags`` of the selection (made when the trace is; see the module docstring).
    """

    recording: RecordingInfo
    detector: dict
    detect_threshold: float
    threshold: float
    k: int
    stride: int
    frames: np.ndarray
    detections: Detections
    selection: np.ndarray
    estimate: float
    weights_id: str = ""
    timings: dict = field(default_factory=dict)
    events: list = field(default_factory=list)
    excluded: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    measurements: list = field(default_factory=list)
    frame_timings: dict = field(default_factory=dict)
    flags: Flags | None = None

    def __post_init__(self) -> None:
        if isinstance(self.recording, dict):
            self.recording = RecordingInfo.from_dict(self.recording)
        self.events = [e if isinstance(e, Event) else Event(*e) for e in self.events]
        dets = self.detections
        if len(dets) and (dets.track <= 0).any():
            dets.track = assign_tracks(dets, self.recording.fps)
        if isinstance(self.flags, dict):
            self.flags = Flags.from_dict(self.flags)
        if self.flags is None or not self.flags.describes(self):
            self.flags = analyse(self)

    # -- views -----------------------------------------------------------------------------------------------------
    @property
    def selected(self) -> Detections:
        return self.detections[self.selection]

    @property
    def ground_truth(self) -> GroundTruth | None:
        """The recording's ground truth (``meta.json``), None when it has none."""
        return self.recording.ground_truth

    @property
    def ground_truth_mass(self) -> float | None:
        gt = self.ground_truth
        return None if gt is None else gt.mass_g

    def active(self) -> np.ndarray:
        """Boolean mask of detections above the current threshold."""
        return self.detections.score > self.threshold

    def table(self):
        """One row per detection (pandas DataFrame): frame, class, score, box, d, a, b, pred, selected rank."""
        import pandas as pd

        dets = self.detections
        rank = np.full(len(dets), -1)
        rank[self.selection] = np.arange(len(self.selection))
        return pd.DataFrame({
            "frame": dets.frame, "class": dets.class_names(), "score": dets.score,
            "x1": dets.xyxy[:, 0], "y1": dets.xyxy[:, 1], "x2": dets.xyxy[:, 2], "y2": dets.xyxy[:, 3],
            "d_mm": dets.d, "a": dets.a, "b": dets.b, "pred_g": dets.pred,
            "active": self.active(), "rank": rank,
        })

    def running_estimate(self) -> np.ndarray:
        """The estimate as it stood after each processed frame (aligned with ``frames``): the mean prediction of the
        K nearest detections among those of the frames processed so far, with this trace's K, threshold and
        exclusions (what ``massviz live`` shows as ``/predictions/running_estimate``); -1 while none is selected.
        Its last value is ``estimate``."""
        dets = self.detections
        nearest = NearestOrder(dets.d, dets.score, self.excluded)  # finite d, not excluded, sorted by d (ties: first)
        order = nearest.order[nearest.score > self.threshold]
        position = {int(f): j for j, f in enumerate(self.frames)}
        processed_at = np.array([position.get(int(f), len(self.frames)) for f in dets.frame[order]], dtype=np.int64)
        out = np.full(len(self.frames), -1.0)
        for j in range(len(self.frames)):
            out[j] = estimate_mass(dets.pred, order[processed_at <= j][: self.k])
        return out

    def settled_after(self, tolerance: float = 0.10) -> int | None:
        """How many processed frames it took the running estimate to settle: from then on it stays within
        ``tolerance`` (relative) of the final estimate. None when not estimated."""
        if self.estimate < 0 or len(self.frames) == 0:
            return None
        running = self.running_estimate()
        outside = np.flatnonzero((running < 0) | (np.abs(running - self.estimate) > tolerance * abs(self.estimate)))
        return int(outside[-1]) + 2 if len(outside) else 1

    # -- reselection -----------------------------------------------------------------------------------------------
    def reselect(self, k: int | None = None, threshold: float | None = None, exclude=None) -> "Trace":
        """A new trace with the selection and estimate recomputed for another ``k``/``threshold``/exclusion.

        ``threshold`` must be >= the threshold the detector ran at (lower-scored boxes were never kept).
        ``exclude``: detection indices (or a bool mask) never to select; ``None`` keeps the current exclusions.
        """
        k = self.k if k is None else int(k)
        threshold = self.threshold if threshold is None else float(threshold)
        if threshold < self.detect_threshold - 1e-9:
            raise MassvizError(f"threshold {threshold} is below the detection threshold {self.detect_threshold} "
                               "this trace was made with; run the detector again with --threshold "
                               f"{threshold} (detections at threshold t serve any threshold >= t)")
        if exclude is None:
            excluded = self.excluded
        else:
            ex = np.asarray(exclude)
            excluded = np.flatnonzero(ex) if ex.dtype == bool else ex.astype(np.int64).reshape(-1)
        selection = select_k_nearest(self.detections.d, self.detections.score, k, threshold, excluded)
        estimate = estimate_mass(self.detections.pred, selection)
        events = [e for e in self.events if not e.is_selection]
        events.extend(describe_selection(self.detections, selection, estimate, k))
        return dataclasses.replace(self, k=k, threshold=threshold, selection=selection, estimate=estimate,
                                   excluded=excluded, events=events, measurements=[])

    # -- persistence -----------------------------------------------------------------------------------------------
    def save(self, path: str | Path) -> Path:
        """Write the trace atomically to ``path`` (.npz)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        dets = self.detections
        header = {
            "format": TRACE_FORMAT, "recording": self.recording.to_dict(), "detector": self.detector,
            "detect_threshold": self.detect_threshold, "threshold": self.threshold, "k": self.k,
            "stride": self.stride, "estimate": self.estimate, "weights_id": self.weights_id,
            "timings": self.timings, "events": [e.to_list() for e in self.events],
            "measurements": list(self.measurements), "flags": self.flags.to_dict(),
            "frame_timing_stages": list(self.frame_timings),
        }
        masks = [m if m is not None else PackedMask(np.zeros((0, 0), bool)) for m in dets.masks]
        patch_idx = [i for i, p in enumerate(dets.patches) if p is not None]
        encoded = [_encode_png(dets.patches[i]) for i in patch_idx]
        arrays = {
            "header": np.frombuffer(json.dumps(header, default=_json_default).encode(), dtype=np.uint8),
            "frames": self.frames, "selection": self.selection, "excluded": self.excluded,
            **{f"det_{name}": getattr(dets, name) for name in Detections._ARRAYS},
            "mask_shapes": np.array([m.shape for m in masks], dtype=np.int32).reshape(-1, 2),
            "mask_sizes": np.array([len(m.bits) for m in masks], dtype=np.int64),
            "mask_bits": np.concatenate([m.bits for m in masks]) if masks else np.zeros(0, np.uint8),
            "patch_index": np.array(patch_idx, dtype=np.int64),
            "patch_sizes": np.array([len(e) for e in encoded], dtype=np.int64),
            "patch_bytes": np.concatenate(encoded) if encoded else np.zeros(0, np.uint8),
            **{f"frame_time_{i}": np.asarray(v, np.float64) for i, v in enumerate(self.frame_timings.values())},
        }
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            np.savez_compressed(fh, **arrays)
        return path

    @classmethod
    def load(cls, path: str | Path) -> "Trace":
        """Read a trace saved by :meth:`save`. The file is untrusted (a replay source, a cache entry): array sizes are
        bounded before they are allocated (``massviz.io.untrusted.load_npz_checked``) and every field is checked
        (:func:`check_trace_arrays`); anything wrong is one ``MassvizError`` naming the file."""
        from massviz.io.untrusted import load_npz_checked

        path = Path(path)
        try:
            data = load_npz_checked(path)
            header = json.loads(data["header"].tobytes().decode())
        except Exception as err:  # noqa: BLE001 - any read problem is a corrupt trace file
            raise MassvizError(f"not a massviz trace ({type(err).__name__}: {_first_line(err)})", path) from None
        if not isinstance(header, dict) or header.get("format") != TRACE_FORMAT:
            found = header.get("format") if isinstance(header, dict) else None
            raise MassvizError(f"trace format {found!r} is not supported (expected {TRACE_FORMAT})"[:300], path)
        try:
            check_trace_arrays(header, data)
            return cls._from_arrays(header, data)
        except Exception as err:  # noqa: BLE001 - a field missing, of the wrong type, shape or value
            raise MassvizError(f"not a complete massviz trace ({type(err).__name__}: {_first_line(err)})",
                               path) from None

    @classmethod
    def _from_arrays(cls, header: dict, data: dict) -> "Trace":
        offsets = np.concatenate([[0], np.cumsum(data["mask_sizes"])])
        masks = [PackedMask(shape=tuple(s), bits=data["mask_bits"][offsets[i]:offsets[i + 1]])
                 for i, s in enumerate(data["mask_shapes"])]
        patches = [None] * len(masks)
        poff = np.concatenate([[0], np.cumsum(data["patch_sizes"])])
        for j, i in enumerate(data["patch_index"]):
            patches[int(i)] = _decode_png(data["patch_bytes"][poff[j]:poff[j + 1]])
        # det_track and the flags are absent from files written before tracks existed: made by __post_init__
        dets = Detections(**{name: data[f"det_{name}"] for name in Detections._ARRAYS
                             if name != "track" or "det_track" in data}, masks=masks, patches=patches)
        return cls(recording=RecordingInfo.from_dict(header["recording"]), detector=header["detector"],
                   detect_threshold=header["detect_threshold"], threshold=header["threshold"], k=header["k"],
                   stride=header["stride"], frames=data["frames"], detections=dets, selection=data["selection"],
                   estimate=header["estimate"], weights_id=header["weights_id"], timings=header["timings"],
                   events=[Event(*e) for e in header["events"]], excluded=data["excluded"],
                   measurements=header.get("measurements", []),
                   flags=Flags.from_dict(header["flags"]) if isinstance(header.get("flags"), dict) else None,
                   frame_timings={name: data[f"frame_time_{i}"]
                                  for i, name in enumerate(header.get("frame_timing_stages", []))})


#: largest frame index or pixel coordinate a trace may hold.
_MAX_INDEX = 2**31 - 1


def check_trace_arrays(header: dict, data: dict) -> None:
    """``ValueError`` naming the field when a saved trace's header or arrays are inconsistent or out of range: every
    detection array has one entry per detection, boxes are non-empty integers >= 0, masks and patches have their
    box's size (checked from the stored sizes and PNG headers, before anything is unpacked or decoded), scores are in
    [0, 1], d/a/b/pred finite or NaN, selection and exclusions index detections, thresholds in [0, 1), k and stride
    integers >= 1, the estimate finite."""
    import math
    import struct

    def ints(name, lo=0, hi=_MAX_INDEX, ndim=1):
        a = np.asarray(data[name])
        if a.dtype.kind not in "iu" or a.ndim != ndim:
            raise ValueError(f"{name} must be a {ndim}-d integer array, got {a.dtype} {a.shape}")
        if a.size and (int(a.min()) < lo or int(a.max()) > hi):
            raise ValueError(f"{name} values must lie in [{lo}, {hi}]")
        return a.astype(np.int64)

    n = len(ints("det_frame"))
    boxes = ints("det_xyxy", ndim=2)
    if boxes.shape != (n, 4) or not ((boxes[:, 2] > boxes[:, 0]) & (boxes[:, 3] > boxes[:, 1])).all():
        raise ValueError(f"det_xyxy: every box must be 4 integers x1 < x2, y1 < y2 (one per detection, {n})")
    ints("det_class_id", lo=-1, hi=10_000)
    if "det_track" in data and len(ints("det_track", hi=_MAX_INDEX)) != n:  # absent in files from before tracks
        raise ValueError(f"det_track: one track id >= 0 per detection ({n})")
    for name in ("det_score", "det_d", "det_a", "det_b", "det_pred"):
        a = np.asarray(data[name])
        if a.dtype.kind != "f" or a.shape != (n,):
            raise ValueError(f"{name} must be {n} floats, got {a.dtype} {a.shape}")
        if np.isinf(a).any() or (name == "det_score" and (np.isnan(a).any() or (a < 0).any() or (a > 1).any())):
            raise ValueError(f"{name}: values must be finite{' and in [0, 1]' if name == 'det_score' else ' or NaN'}")
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
        head = pbytes[offsets[j]:offsets[j] + 24].tobytes()
        if head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
            raise ValueError(f"patch of detection {i} is not a PNG")
        w, h = struct.unpack(">II", head[16:24])
        if (h, w) != tuple(box_shape[i]):
            raise ValueError(f"patch of detection {i} is {w}x{h}, not the size of its box")
    for name in ("selection", "excluded"):
        a = ints(name)
        if len(a) and (n == 0 or int(a.max()) >= n):
            raise ValueError(f"{name} indexes a detection that does not exist ({n} detections)")
    ints("frames")
    for name in ("detect_threshold", "threshold"):
        v = header[name]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 <= v < 1:
            raise ValueError(f"header {name} must be a number in [0, 1), got {v!r}"[:200])
    for name in ("k", "stride"):
        v = header[name]
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise ValueError(f"header {name} must be an integer >= 1, got {v!r}"[:200])
    est = header["estimate"]
    if isinstance(est, bool) or not isinstance(est, (int, float)) or not math.isfinite(est):
        raise ValueError(f"header estimate must be a finite number, got {est!r}"[:200])
    if not isinstance(header["events"], list) or not isinstance(header["recording"], dict):
        raise ValueError("header events must be a list and recording an object")


def _first_line(err: BaseException) -> str:
    lines = str(err).splitlines()
    return lines[0][:300] if lines else type(err).__name__


def describe_detection(dets: Detections, i: int) -> str:
    """One detection in a line: class, score, box, d and prediction."""
    return (f"{class_name(dets.class_id[i])} {dets.score[i]:.2f} box {dets.xyxy[i].tolist()} "
            f"d={dets.d[i]:.0f}mm pred={dets.pred[i]:.1f}g")


def describe_selection(dets: Detections, selection: np.ndarray, estimate: float, k: int) -> list[Event]:
    """The selection stage's decisions: one ``chosen`` event per patch, then ``estimate`` or ``not_estimated``."""
    out = [Event(int(dets.frame[i]), f"chose patch {r} (of K={k}): {describe_detection(dets, i)}", "chosen",
                 "info", int(i)) for r, i in enumerate(selection)]
    last = int(dets.frame.max()) if len(dets) else 0
    if len(selection):
        out.append(Event(last, f"estimate {estimate:.1f} g = mean of {len(selection)} patch predictions", "estimate"))
    else:
        out.append(Event(last, "no detection with depth: mass not estimated (-1)", "not_estimated", "warn"))
    return out


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
