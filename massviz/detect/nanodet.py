"""``--detector nanodet``: OpenCV Zoo's NanoDet (COCO, 80 classes) through OpenCV's own DNN module, on a CPU.

A real detector that runs offline and fast (tens of milliseconds a frame on a 2-core CPU, where Mask R-CNN takes
seconds), for live use, CPUs and machines without the Mask R-CNN COCO weights. It is *not* the paper's detector.

**Model.** ``object_detection_nanodet_2022nov.onnx`` of the OpenCV Zoo (Apache-2.0, 3.8 MB): ``--detector-weights
PATH``, else downloaded once from :data:`NANODET_URL_BASE` into the user cache (``massviz.io.weights.cache_dir``),
sha256-pinned (:data:`NANODET_SHA256`). A file that is not that model's layout is refused with one line
(:func:`check_outputs`).

**Pre-processing** (:func:`preprocess`): the RGB frame is letterboxed (aspect kept, centred, padded with black) to
416×416 BGR by ``cv2.dnn.blobFromImagesWithParams`` and normalised ``(pixel − mean) / std`` (mean 103.53, 116.28,
123.675; std 57.375, 57.12, 58.395), NCHW float32.

**Decoding** (:func:`decode`): for each stride (8, 16, 32) a class-score map ``(N, 80)`` (already sigmoid) and a box
map ``(N, 32)``: 4 sides × 8 bins of a distribution, softmax over the bins, expectation over 0..7, times the stride,
giving the distances from the cell centre ``(x·stride + (stride − 1)/2, same for y)`` to the left, top, right and bottom
edges. Every (cell, kept class) pair with score > ``threshold`` (strict, as the paper's ``filter_results`` and
``massviz.detect.maskrcnn``) is a candidate, for the paper's classes only (cup, book, wine glass, bottle — another
class scoring higher in the same cell does not hide a cup, as in torchvision's per-class post-processing); then
class-aware NMS (``cv2.dnn.NMSBoxesBatched``, IoU :data:`NMS_IOU`), at most :data:`MAX_DETECTIONS` boxes, and the
boxes mapped back to the frame (``blobRectsToImageRects``), clipped and truncated to integers (``int(x)``, as the
paper's code does with Mask R-CNN's boxes). Class ids are reported in torchvision's 91-id COCO numbering
(``massviz.core.types.COCO_KEEP``), so a NanoDet cup and a Mask R-CNN cup carry the same id.

**Masks from depth** (:func:`depth_mask`). NanoDet gives boxes only. Inside each box the container is taken to be
the *nearest coherent depth surface*: the box's depth (``min_mm``..``max_mm``) is searched from near to far, in
bins of :data:`BIN_MM` mm, for the first slab ``[z, z + 2·band]`` (band = ``max(band_mm, band_fraction·z)``) that
holds at least ``mode_fraction`` of the box's pixels with depth (a stray near pixel or a thin strip of table edge
does not); the surface's depth is the median of that slab's densest bin, the pixels within ± band of it form the
candidate mask, and its largest 8-connected component is the mask. A box with
too little depth (fewer than ``min_depth_fraction`` of its pixels) gets an empty mask: its d is NaN and the detection
is never chosen (reported as skipped), rather than a guess.

**How d differs from the paper's.** The paper's d is the mean depth over Mask R-CNN's instance mask: the object's
silhouette as the network sees it, including whatever the depth sensor measured through or beside it (the wall
behind a transparent glass, a sliver of background at the rim). Here d is the mean depth of the nearest coherent
surface in the box: background, table and wall pixels inside the box never count, but anything at the container's
depth touching it does (a hand holding it), and a transparent glass whose depth is missing or seen-through yields
the depth of what is nearest behind it within the box (often the hand, or nothing: NaN). On an opaque container d
is the mean of its visible surface, typically a little nearer than the paper's d. a and b (box ratios) depend on
NanoDet's boxes, which are not Mask R-CNN's: the mass CNN was trained on Mask R-CNN crops, so estimates differ from
the paper's even on the same frames (README, "Detectors").
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from massviz.core.types import COCO_KEEP, Detections, Frame
from massviz.errors import WeightsError

#: the OpenCV Zoo file and where it is published (the pinned commit of opencv/opencv_zoo's model folder).
NANODET_NAME = "object_detection_nanodet_2022nov.onnx"
NANODET_URL_BASE = "https://github.com/opencv/opencv_zoo/raw/main/models/object_detection_nanodet/"
NANODET_SHA256 = "4b82da9944b88577175ee23a459dce2e26e6e4be573def65b1055dc2d9720186"

INPUT_SIZE = 416
STRIDES = (8, 16, 32)
REG_MAX = 7
NUM_CLASSES = 80
MEAN = (103.53, 116.28, 123.675)  # BGR
STD = (57.375, 57.12, 58.395)
NMS_IOU = 0.6
MAX_DETECTIONS = 100
#: the paper's classes in NanoDet's 80-class order (0-based) -> torchvision's 91-id COCO numbering (COCO_KEEP).
COCO80_KEEP = {39: COCO_KEEP["bottle"], 40: COCO_KEEP["wine glass"], 41: COCO_KEEP["cup"], 73: COCO_KEEP["book"]}
#: depth histogram bin (mm) of the depth masks.
BIN_MM = 10.0


# ------------------------------------------------------------------------------------------- pre-processing
def _blob_params() -> "cv2.dnn.Image2BlobParams":
    p = cv2.dnn.Image2BlobParams()
    p.scalefactor = tuple(1.0 / s for s in STD) + (0.0,)
    p.size = (INPUT_SIZE, INPUT_SIZE)
    p.mean = MEAN + (0.0,)
    p.swapRB = True  # frames are RGB; the model takes BGR
    p.ddepth = cv2.CV_32F
    p.paddingmode = cv2.dnn.DNN_PMODE_LETTERBOX
    p.borderValue = (0.0, 0.0, 0.0, 0.0)
    return p


def preprocess(rgbs: list[np.ndarray]) -> np.ndarray:
    """The network input for RGB frames (H×W×3 uint8): N×3×416×416 float32, letterboxed (module docstring)."""
    return cv2.dnn.blobFromImagesWithParams([np.ascontiguousarray(r) for r in rgbs], _blob_params())


def input_to_frame(boxes: np.ndarray, width: int, height: int) -> np.ndarray:
    """Boxes (x1, y1, x2, y2, float) in the 416×416 letterboxed input → the W×H frame's coordinates, clipped."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    scale = min(INPUT_SIZE / width, INPUT_SIZE / height)
    rw, rh = int(width * scale), int(height * scale)  # as blobFromImagesWithParams's letterbox
    left, top = (INPUT_SIZE - rw) // 2, (INPUT_SIZE - rh) // 2
    out = np.empty_like(boxes)
    out[:, 0::2] = (boxes[:, 0::2] - left) * (width / rw)
    out[:, 1::2] = (boxes[:, 1::2] - top) * (height / rh)
    out[:, 0::2] = out[:, 0::2].clip(0, width)
    out[:, 1::2] = out[:, 1::2].clip(0, height)
    return out


# ------------------------------------------------------------------------------------------- post-processing
def cell_centres(stride: int, size: int = INPUT_SIZE) -> np.ndarray:
    """(N, 2) centres (x, y) of a stride's cells in the input, row-major (the maps' order)."""
    n = int(np.ceil(size / stride))
    ys, xs = np.mgrid[0:n, 0:n]
    return np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64) * stride + 0.5 * (stride - 1)


def distribution_distances(box_map: np.ndarray, stride: int) -> np.ndarray:
    """(N, 32) distribution logits → (N, 4) distances (left, top, right, bottom) in input pixels."""
    logits = np.asarray(box_map, dtype=np.float64).reshape(-1, 4, REG_MAX + 1)
    logits = logits - logits.max(axis=2, keepdims=True)
    p = np.exp(logits)
    p /= p.sum(axis=2, keepdims=True)
    return (p @ np.arange(REG_MAX + 1, dtype=np.float64)) * stride


def decode(score_maps: list[np.ndarray], box_maps: list[np.ndarray], threshold: float,
           keep=tuple(COCO80_KEEP), nms_iou: float = NMS_IOU, max_detections: int = MAX_DETECTIONS):
    """One image's outputs (per stride: scores (N, 80), box logits (N, 32)) → boxes (M, 4) in input pixels
    (x1, y1, x2, y2), scores (M,), 80-class ids (M,), best first (module docstring: candidates with score >
    ``threshold`` among the ``keep`` classes, class-aware NMS)."""
    keep = np.asarray(sorted(keep), dtype=np.int64)
    boxes, scores, classes = [], [], []
    for stride, s_map, b_map in zip(STRIDES, score_maps, box_maps):
        s = np.asarray(s_map, dtype=np.float32).reshape(-1, NUM_CLASSES)[:, keep]
        cell, col = np.nonzero(s > threshold)
        if len(cell) == 0:
            continue
        uniq, inv = np.unique(cell, return_inverse=True)
        dist = distribution_distances(np.asarray(b_map).reshape(-1, 4 * (REG_MAX + 1))[uniq], stride)
        c = cell_centres(stride)[uniq]
        b = np.concatenate([c - dist[:, :2], c + dist[:, 2:]], 1).clip(0, INPUT_SIZE)
        boxes.append(b[inv])
        scores.append(s[cell, col])
        classes.append(keep[col])
    if not boxes:
        return np.zeros((0, 4)), np.zeros(0, np.float32), np.zeros(0, np.int64)
    boxes, scores, classes = np.concatenate(boxes), np.concatenate(scores), np.concatenate(classes)
    xywh = np.concatenate([boxes[:, :2], boxes[:, 2:] - boxes[:, :2]], 1)
    idx = cv2.dnn.NMSBoxesBatched(xywh.tolist(), scores.astype(float).tolist(), classes.tolist(), float(threshold),
                                  float(nms_iou))
    idx = np.asarray(idx, dtype=np.int64).reshape(-1)
    idx = idx[np.lexsort((-scores[idx],))][:max_detections]  # by score, ties in order (stable)
    return boxes[idx], scores[idx], classes[idx]


def check_outputs(outputs, batch: int, path) -> tuple[list, list]:
    """Split the network's outputs into per-stride score and box maps, or ``WeightsError`` naming ``path`` when they
    are not NanoDet's layout (three ``(B, N, 80)`` score maps and three ``(B, N, 32)`` box maps for N = 52², 26², 13²)."""
    want = [int(np.ceil(INPUT_SIZE / s)) ** 2 for s in STRIDES]
    shapes = [tuple(np.shape(o)) for o in outputs]
    by_shape = {s: o for s, o in zip(shapes, outputs)}
    expected = [(batch, n, NUM_CLASSES) for n in want] + [(batch, n, 4 * (REG_MAX + 1)) for n in want]
    if len(outputs) != 6 or sorted(shapes) != sorted(expected):
        raise WeightsError(f"not OpenCV Zoo's NanoDet: its outputs are {shapes}, expected three (B, N, 80) class maps "
                           f"and three (B, N, 32) box maps for N = {', '.join(map(str, want))}", path)
    return ([by_shape[(batch, n, NUM_CLASSES)] for n in want],
            [by_shape[(batch, n, 4 * (REG_MAX + 1))] for n in want])


# ------------------------------------------------------------------------------------------- masks from depth
def depth_mask(depth_box: np.ndarray, *, min_mm: float = 200.0, max_mm: float = 4000.0, band_mm: float = 40.0,
               band_fraction: float = 0.05, mode_fraction: float = 0.15,
               min_depth_fraction: float = 0.05) -> np.ndarray:
    """The nearest coherent depth surface inside one box (``depth_box``: the box's depth, mm, 0 = none) as a bool
    mask of the box's shape (module docstring); all False when the box has too little depth."""
    z = np.asarray(depth_box, dtype=np.float64)
    valid = (z >= min_mm) & (z <= max_mm)
    n_valid = int(valid.sum())
    out = np.zeros(z.shape, dtype=bool)
    if z.size == 0 or n_valid < max(10, min_depth_fraction * z.size):
        return out
    values = np.sort(z[valid])
    edges = np.arange(values[0], values[-1] + 2 * BIN_MM, BIN_MM)
    hist = np.histogram(values, bins=edges)[0]
    need = mode_fraction * n_valid
    mode = None
    for i in np.flatnonzero(hist):  # near to far: the first slab [edge, edge + 2·half] holding enough of the box
        start = edges[i]
        half = max(band_mm, band_fraction * start)
        inside = np.searchsorted(values, start + 2 * half, side="right") - np.searchsorted(values, start)
        if inside >= need:
            j = np.searchsorted(edges, start + 2 * half, side="right")
            dense = i + int(np.argmax(hist[i:j]))  # its densest bin
            lo, hi = np.searchsorted(values, edges[dense]), np.searchsorted(values, edges[dense + 1])
            mode = float(np.median(values[lo:hi]))
            break
    if mode is None:  # no slab holds enough: the densest bin of the box
        dense = int(np.argmax(hist))
        mode = float(np.median(values[(values >= edges[dense]) & (values < edges[dense + 1])]))
    half = max(band_mm, band_fraction * mode)
    band = valid & (np.abs(z - mode) <= half)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(band.astype(np.uint8), connectivity=8)
    if n <= 1:
        return out
    best = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    return labels == best


# ------------------------------------------------------------------------------------------- the detector
def load_net(path: str | Path):
    """``cv2.dnn`` network of the ONNX file at ``path``; ``WeightsError`` naming it when it is missing or does not
    load, or when its outputs are not NanoDet's layout (one probe forward)."""
    path = Path(path)
    if not path.is_file():
        raise WeightsError("NanoDet model file not found", path)
    try:
        net = cv2.dnn.readNet(str(path))
        names = list(net.getUnconnectedOutLayersNames())
        net.setInput(np.zeros((1, 3, INPUT_SIZE, INPUT_SIZE), np.float32))
        outputs = net.forward(names)
    except cv2.error as err:
        first = next((ln.strip() for ln in str(err).splitlines() if "error:" in ln), "cannot load it")
        raise WeightsError(f"not a NanoDet ONNX model OpenCV can run ({first[:160]})", path) from None
    check_outputs(outputs, 1, path)
    return net, names


def resolve_model(path: str | Path | None, *, progress: bool = True) -> Path:
    """The model file: ``path`` (must exist), else the sha256-checked copy in the weights cache, downloaded once."""
    from massviz.io import weights

    if path is not None:
        p = Path(path).expanduser()
        if not p.is_file():
            raise WeightsError("NanoDet model file not found", p)
        return p
    cached = weights.cache_dir() / NANODET_NAME
    if cached.is_file() and weights.sha256_file(cached) == NANODET_SHA256:
        return cached
    return weights.download(NANODET_URL_BASE + NANODET_NAME, cached, NANODET_SHA256, progress=progress)


def cached_model() -> Path | None:
    """The cached OpenCV Zoo model when it was downloaded before (checked by size only: cheap; ``resolve_model``
    checks its sha256)."""
    from massviz.io import weights

    cached = weights.cache_dir() / NANODET_NAME
    return cached if cached.is_file() and cached.stat().st_size == 3_800_954 else None


class NanoDetDetector:
    """``--detector nanodet`` (module docstring). The network is loaded on the first frame, or at once with
    ``load()`` (the CLI does, so that a bad file is reported before anything is written)."""

    name = "nanodet"
    default_batch = 1

    def __init__(self, threshold: float = 0.4, weights: str | Path | None = None, *, nms_iou: float = NMS_IOU,
                 band_mm: float = 40.0, band_fraction: float = 0.05, mode_fraction: float = 0.15,
                 progress: bool = True):
        self.threshold = float(threshold)
        self.weights = None if weights is None else Path(weights)
        self.nms_iou = float(nms_iou)
        self.mask = {"band_mm": float(band_mm), "band_fraction": float(band_fraction),
                     "mode_fraction": float(mode_fraction)}
        self.progress = progress
        self._net = None
        self._names = None
        self._path = None
        self._digest = None

    def load(self) -> "NanoDetDetector":
        if self._net is None:
            self._path = resolve_model(self.weights, progress=self.progress)
            self._net, self._names = load_net(self._path)
        return self

    def settings(self) -> dict:
        """Every setting that changes the output except ``threshold``: the model by content, NMS and mask settings."""
        from massviz.io.filehash import file_digest

        if self._digest is None:  # the model by content (the file is resolved, and checked, first)
            self._digest = file_digest(self.load()._path)
        return {"weights": f"nanodet:{self._digest}", "classes": sorted(COCO80_KEEP.values()),
                "nms_iou": self.nms_iou, "input": INPUT_SIZE, "mask": dict(self.mask), "version": 1}

    def detect(self, frame: Frame) -> Detections:
        return self.detect_batch([frame])[0]

    def detect_batch(self, frames: list[Frame]) -> list[Detections]:
        """Detections of each frame (equal to ``detect`` frame by frame). The Zoo's graph is fixed to batch 1
        (its heads reshape to one image), so the frames are letterboxed in one call and run one forward each."""
        if not frames:
            return []
        self.load()
        blob = preprocess([f.rgb for f in frames])
        out = []
        for i, f in enumerate(frames):
            self._net.setInput(blob[i:i + 1])
            score_maps, box_maps = check_outputs(self._net.forward(self._names), 1, self._path)
            out.append(self._detections(f, [s[0] for s in score_maps], [b[0] for b in box_maps]))
        return out

    def _detections(self, frame: Frame, score_maps, box_maps) -> Detections:
        boxes, scores, classes = decode(score_maps, box_maps, self.threshold, nms_iou=self.nms_iou)
        h, w = frame.rgb.shape[:2]
        fb = input_to_frame(boxes, w, h)
        xyxy = np.array([[int(v) for v in b] for b in fb], dtype=np.int32).reshape(-1, 4)
        ok = (xyxy[:, 2] > xyxy[:, 0]) & (xyxy[:, 3] > xyxy[:, 1])
        xyxy, scores, classes = xyxy[ok], scores[ok], classes[ok]
        depth = np.asarray(frame.depth)
        masks = [depth_mask(depth[y1:y2, x1:x2], **self.mask) for x1, y1, x2, y2 in xyxy]
        return Detections(frame=np.full(len(xyxy), frame.index), xyxy=xyxy, score=scores.astype(np.float32),
                          class_id=np.array([COCO80_KEEP[int(c)] for c in classes], dtype=np.int64), masks=masks)


__all__ = ["NanoDetDetector", "preprocess", "decode", "input_to_frame", "check_outputs", "depth_mask", "load_net",
           "resolve_model", "cached_model", "NANODET_NAME", "NANODET_URL_BASE", "NANODET_SHA256", "COCO80_KEEP"]
