"""Typed data shared by every stage.

Modelled on roboflow ``supervision``'s ``Detections``: one dataclass of parallel arrays, filtered by boolean or
integer indexing. Masks are stored *cropped to their integer box* (``mask[y1:y2, x1:x2]``), exactly the part of the
mask the paper's code uses for the average distance, which keeps a whole recording's detections small.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import NamedTuple, Sequence

import numpy as np

#: torchvision's COCO category ids (index into ``MaskRCNN_ResNet50_FPN_Weights.meta["categories"]``) of the four
#: classes the paper keeps.
COCO_KEEP = {"bottle": 44, "wine glass": 46, "cup": 47, "book": 84}
#: ``--precision`` choices (Mask R-CNN's arithmetic, the mass CNN's too for bf16); fp32 is the default and the paper's.
PRECISIONS = ("fp32", "bf16", "fp16")
#: class id used by class-agnostic detectors (the depth detector).
OBJECT_CLASS_ID = -1


def class_name(class_id: int) -> str:
    """Human-readable name of a detection class id."""
    for name, cid in COCO_KEEP.items():
        if cid == int(class_id):
            return name
    if int(class_id) == OBJECT_CLASS_ID:
        return "object"
    return f"coco_{int(class_id)}"


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of the RGB camera (pixels). Depth is aligned to RGB, so they serve both."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @property
    def matrix(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1]], dtype=np.float64)

    def to_dict(self) -> dict:
        return {"fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy, "width": self.width, "height": self.height}

    @classmethod
    def from_dict(cls, d: dict) -> "Intrinsics":
        return cls(float(d["fx"]), float(d["fy"]), float(d["cx"]), float(d["cy"]), int(d["width"]), int(d["height"]))


@dataclass
class Frame:
    """One RGB-D frame: ``rgb`` H×W×3 uint8 (RGB order), ``depth`` H×W uint16 millimetres (0 = no depth).

    ``rgb_encoded`` / ``depth_encoded``: the frame's bytes as the format stored them, when the reader read a file of
    this one frame (a PNG/JPEG frame file, a 16-bit depth PNG), so that a sink can log them without reading the file
    again or re-encoding; ``rgb_media_type`` is their MIME type (``image/png``, ``image/jpeg``). None when the format
    has no per-frame file (a video, a RealSense file, a live camera): a sink then encodes the decoded arrays."""

    index: int
    rgb: np.ndarray
    depth: np.ndarray
    rgb_encoded: bytes | None = None
    rgb_media_type: str | None = None
    depth_encoded: bytes | None = None

    @property
    def height(self) -> int:
        return int(self.rgb.shape[0])

    @property
    def width(self) -> int:
        return int(self.rgb.shape[1])


class PackedMask:
    """A boolean mask stored as packed bits (8× smaller than ``bool``); ``.array()`` unpacks it."""

    __slots__ = ("shape", "bits")

    def __init__(self, mask: np.ndarray | None = None, *, shape=None, bits=None):
        if mask is not None:
            mask = np.asarray(mask, dtype=bool)
            shape, bits = mask.shape, np.packbits(mask, axis=None)
        self.shape = tuple(int(s) for s in shape)
        self.bits = np.asarray(bits, dtype=np.uint8)

    def array(self) -> np.ndarray:
        n = int(np.prod(self.shape))
        return np.unpackbits(self.bits, count=n).reshape(self.shape).astype(bool)

    def sum(self) -> int:
        return int(np.unpackbits(self.bits, count=int(np.prod(self.shape))).sum())


class Rejection(NamedTuple):
    """An object a detector saw and did not take as a container candidate: ``reason`` names the kind of object
    (``border-cut object``, ``part of a border-cut object``, ``implausibly sized object``), ``text`` says it in full
    (e.g. "border-cut object (box [0, 10, 80, 200] at 612 mm)")."""

    reason: str
    text: str

    def __str__(self) -> str:
        return self.text


def _empty(dtype, shape=(0,)):
    return np.zeros(shape, dtype=dtype)


@dataclass
class Detections:
    """Parallel arrays, one entry per detection.

    - ``frame``: index of the source frame in the recording.
    - ``xyxy``: integer box ``x1, y1, x2, y2`` (x2/y2 exclusive, the slicing the paper's code uses).
    - ``score``, ``class_id``: detector confidence and class (COCO id, or ``OBJECT_CLASS_ID``).
    - ``masks``: list of boolean masks cropped to the box (shape ``(y2-y1, x2-x1)``), stored as ``PackedMask``
      (pass bool arrays; read them back with ``mask(i)`` or ``full_mask(i, H, W)``).
    - ``d``: mean depth (mm) over the mask pixels with depth (NaN when the mask has no depth).
    - ``a``, ``b``: box width / image width and box height / image height, rounded to 2 decimals.
    - ``pred``: the mass CNN's prediction for this detection's patch (grams; NaN when not predicted).
    - ``patches``: the RGB crop of each box (H×W×3 uint8), or ``None`` entries when not kept.
    - ``track``: the object track of each detection (``massviz.core.tracks``; ids >= 1, 0 = not tracked yet).
    - ``gt_iou``, ``gt_instance``, ``gt_fraction``: how the mask lies on the recording's ground-truth instance masks
      (IoU with the container's, the instance id covering most of it (0 background) and the fraction it covers);
      NaN / -1 when unknown. Filled by ``massviz.io.ground_truth.with_ground_truth``, read by ``massviz.core.flags``.
    """

    frame: np.ndarray = field(default_factory=lambda: _empty(np.int32))
    xyxy: np.ndarray = field(default_factory=lambda: _empty(np.int32, (0, 4)))
    score: np.ndarray = field(default_factory=lambda: _empty(np.float32))
    class_id: np.ndarray = field(default_factory=lambda: _empty(np.int32))
    masks: list = field(default_factory=list)
    d: np.ndarray = field(default_factory=lambda: _empty(np.float64))
    a: np.ndarray = field(default_factory=lambda: _empty(np.float64))
    b: np.ndarray = field(default_factory=lambda: _empty(np.float64))
    pred: np.ndarray = field(default_factory=lambda: _empty(np.float32))
    patches: list = field(default_factory=list)
    track: np.ndarray = field(default_factory=lambda: _empty(np.int64))
    gt_iou: np.ndarray = field(default_factory=lambda: _empty(np.float64))
    gt_instance: np.ndarray = field(default_factory=lambda: _empty(np.int32))
    gt_fraction: np.ndarray = field(default_factory=lambda: _empty(np.float64))

    _ARRAYS = ("frame", "xyxy", "score", "class_id", "d", "a", "b", "pred", "track", "gt_iou", "gt_instance",
               "gt_fraction")
    #: arrays a trace file written before them may lack (made, or unknown, when the trace is read)
    _OPTIONAL = ("track", "gt_iou", "gt_instance", "gt_fraction")
    _LISTS = ("masks", "patches")

    def __post_init__(self) -> None:
        n = len(self.frame)
        self.frame = np.asarray(self.frame, dtype=np.int32).reshape(n)
        self.xyxy = np.asarray(self.xyxy, dtype=np.int32).reshape(n, 4)
        self.score = np.asarray(self.score, dtype=np.float32).reshape(n)
        self.class_id = np.asarray(self.class_id, dtype=np.int32).reshape(n)
        for name in ("d", "a", "b"):
            arr = getattr(self, name)
            setattr(self, name, np.full(n, np.nan) if len(arr) == 0 and n else np.asarray(arr, np.float64).reshape(n))
        self.pred = np.full(n, np.nan, np.float32) if len(self.pred) == 0 and n else np.asarray(self.pred, np.float32).reshape(n)
        self.track = np.zeros(n, np.int64) if len(self.track) == 0 and n else np.asarray(self.track, np.int64).reshape(n)
        for name, dtype, unknown in (("gt_iou", np.float64, np.nan), ("gt_instance", np.int32, -1),
                                     ("gt_fraction", np.float64, np.nan)):
            arr = getattr(self, name)
            setattr(self, name, np.full(n, unknown, dtype) if len(arr) == 0 and n else np.asarray(arr, dtype).reshape(n))
        if not self.masks and n:
            self.masks = [None] * n
        self.masks = [m if m is None or isinstance(m, PackedMask) else PackedMask(m) for m in self.masks]
        if not self.patches and n:
            self.patches = [None] * n
        if len(self.masks) != n or len(self.patches) != n:
            raise ValueError("Detections: masks/patches must have one entry per detection")

    def __len__(self) -> int:
        return len(self.frame)

    def __getitem__(self, index) -> "Detections":
        """Boolean mask, integer array/list or slice; always returns ``Detections``."""
        if isinstance(index, (int, np.integer)):
            index = [int(index)]
        idx = np.arange(len(self))[index]
        kw = {name: getattr(self, name)[idx] for name in self._ARRAYS}
        kw.update({name: [getattr(self, name)[i] for i in idx] for name in self._LISTS})
        return Detections(**kw)

    @classmethod
    def concat(cls, parts: Sequence["Detections"]) -> "Detections":
        parts = [p for p in parts if len(p)]
        if not parts:
            return cls()
        kw = {name: np.concatenate([getattr(p, name) for p in parts]) for name in cls._ARRAYS}
        kw.update({name: [x for p in parts for x in getattr(p, name)] for name in cls._LISTS})
        return cls(**kw)

    def indices_by_frame(self) -> dict[int, np.ndarray]:
        """Frame index -> the indices of its detections (ascending), for the frames that have any, in frame order."""
        order = np.lexsort((np.arange(len(self)), self.frame))  # by frame, then index
        frames, starts = np.unique(self.frame[order], return_index=True)
        return {int(f): order[s:e] for f, s, e in zip(frames, starts, [*starts[1:], len(order)])}

    def class_names(self) -> list[str]:
        return [class_name(c) for c in self.class_id]

    def mask(self, i: int) -> np.ndarray:
        """The i-th mask as a bool array cropped to its box."""
        m = self.masks[i]
        if m is None:
            x1, y1, x2, y2 = (int(v) for v in self.xyxy[i])
            return np.zeros((y2 - y1, x2 - x1), dtype=bool)
        return m.array()

    def full_mask(self, i: int, height: int, width: int) -> np.ndarray:
        """The i-th mask pasted back into an H×W boolean image."""
        out = np.zeros((height, width), dtype=bool)
        x1, y1, x2, y2 = (int(v) for v in self.xyxy[i])
        out[y1:y2, x1:x2] = self.mask(i)
        return out


def _number(value) -> float | None:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


@dataclass(frozen=True)
class GroundTruth:
    """What a recording's ``meta.json`` says about its container, read in one place (``from_meta``).

    ``mass_g`` (empty mass), ``cls`` (cup, glass, box, ...), ``container_id`` (-1 unknown), the annotated size in mm
    (None when unknown), and, for the synthetic samples, ``instance_masks`` (a path pattern relative to the recording,
    e.g. ``gt/{frame:06d}.png``) with ``instances`` ({instance id: name}; the container is named "container").
    A meta.json read from a file is checked first (``massviz.io.meta.check_meta``); ``from_meta`` itself never
    fails: a value it cannot read is unknown (None).
    """

    mass_g: float | None = None
    cls: str | None = None
    container_id: int = -1
    width_top_mm: float | None = None
    width_bottom_mm: float | None = None
    height_mm: float | None = None
    depth_mm: float | None = None
    capacity_ml: float | None = None
    instance_masks: str | None = None
    instances: dict = field(default_factory=dict)

    @classmethod
    def from_meta(cls, meta: dict | None) -> "GroundTruth | None":
        """The ground truth in a ``meta.json`` dict, or None when it has none."""
        meta = meta if isinstance(meta, dict) else {}
        c = meta.get("container") if isinstance(meta.get("container"), dict) else {}
        instances = meta.get("instances") if isinstance(meta.get("instances"), dict) else {}
        if not c and not instances:
            return None
        mass = _number(c.get("mass_g"))
        cid = _number(c.get("id"))
        names = {}
        for k, v in instances.items():
            try:
                names[int(k)] = str(v.get("name") if isinstance(v, dict) else v)
            except (TypeError, ValueError):
                continue
        pattern = meta.get("instance_masks")
        return cls(mass_g=mass if mass is not None and mass > 0 else None,
                   cls=str(c["class"]) if c.get("class") is not None else None,
                   container_id=int(cid) if cid is not None and cid == int(cid) else -1,
                   width_top_mm=_number(c.get("width_top_mm")), width_bottom_mm=_number(c.get("width_bottom_mm")),
                   height_mm=_number(c.get("height_mm")), depth_mm=_number(c.get("depth_mm")),
                   capacity_ml=_number(c.get("capacity_ml")),
                   instance_masks=str(pattern) if isinstance(pattern, str) and pattern else None, instances=names)

    def size(self) -> dict | None:
        """The annotated size (mm): height, top/bottom widths, ``width_mm`` (the larger of the two) and depth (-1
        unknown), or None when height or a width is unknown."""
        if None in (self.width_top_mm, self.width_bottom_mm, self.height_mm):
            return None
        return {"height_mm": self.height_mm, "width_top_mm": self.width_top_mm,
                "width_bottom_mm": self.width_bottom_mm, "width_mm": max(self.width_top_mm, self.width_bottom_mm),
                "depth_mm": -1.0 if self.depth_mm is None or self.depth_mm <= 0 else self.depth_mm}


@dataclass
class RecordingInfo:
    """What a trace remembers of its recording (``Recording.info()``); saved in the trace's header."""

    id: str
    path: str = ""
    config_id: str = ""
    kind: str = "folder"
    width: int = 0
    height: int = 0
    num_frames: int = 0
    fps: float = 0.0
    rgb: str = "frames"
    intrinsics: Intrinsics | None = None
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.id = str(self.id)
        self.config_id = str(self.config_id or self.id)
        if isinstance(self.intrinsics, dict):
            self.intrinsics = Intrinsics.from_dict(self.intrinsics)

    @property
    def ground_truth(self) -> GroundTruth | None:
        return GroundTruth.from_meta(self.meta)

    def to_dict(self) -> dict:
        return {"id": self.id, "config_id": self.config_id, "path": self.path, "kind": self.kind,
                "width": self.width, "height": self.height, "num_frames": self.num_frames, "fps": self.fps,
                "rgb": self.rgb, "intrinsics": self.intrinsics.to_dict() if self.intrinsics else None,
                "meta": self.meta}

    @classmethod
    def from_dict(cls, d: dict) -> "RecordingInfo":
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in names})


__all__ = [
    "COCO_KEEP", "OBJECT_CLASS_ID", "class_name", "Intrinsics", "Frame", "Detections", "PackedMask", "GroundTruth", "RecordingInfo",
    "Rejection"]
