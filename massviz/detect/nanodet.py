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

**Masks from depth** (:func:`depth_mask`). NanoDet gives boxes only; the mask must follow the object inside its
box, not whatever is nearest in it (the table in front of a cup seen from above is nearer than the cup):

1. **Support plane.** A plane is fitted by RANSAC in ``(u, v, 1/z)`` (:func:`support_plane`) to the depth around the
   lower part of the box (the strip below it and beside its lower third); when it holds half of that region's depth
   pixels it is the table the object stands on, and the box's pixels on it are left out.
2. **Seed layer at the box's centre.** In the box's central region (``centre`` of its width and height), from near
   to far, the first slab ``[z, z + 2·band]`` (band = ``max(band_mm, band_fraction·z)``) holding ``mode_fraction``
   of the region's depth pixels; its median is the object's depth, and the central pixels within ± band of it are
   the seeds (a stray near pixel, a strip of table at the box's bottom or the wall seen beside the object is not).
3. **Grown over the surface.** From the seeds, a flood fill of ``log z`` through 8-neighbours whose depth differs by
   at most ``max(step_fraction·z, step_mm)``: the mask follows a surface however deep it is (a mug seen from above
   spans 100 mm and more of depth) and stops where the depth jumps (the background behind its outline) or where the
   support plane was removed (its base). The largest 8-connected component is the mask.

A box with too little depth (fewer than ``min_depth_fraction`` of its pixels) gets an empty mask: its d is NaN and
the detection is never chosen (reported as skipped), rather than a guess. Measured on CCM 618 and on ray-cast mugs
and boxes seen from 20-65° above (docs/detectors.md).

**How d differs from the paper's.** The paper's d is the mean depth over Mask R-CNN's instance mask: the object's
silhouette as the network sees it, including whatever the depth sensor measured through or beside it (the wall
behind a transparent glass, a sliver of background at the rim). Here d is the mean depth of the object's surface
grown from the box's centre: background, table and wall pixels inside the box never count, but anything continuous
with it does (a hand holding it, a cup's rim and the inside seen over it), and a transparent glass whose depth is
missing or seen-through yields the depth of what is behind it at the box's centre (often the hand, or nothing: NaN). On an opaque container d
is the mean of its visible surface, typically a little nearer than the paper's d. a and b (box ratios) depend on
NanoDet's boxes, which are not Mask R-CNN's: the mass CNN was trained on Mask R-CNN crops, so estimates differ from
the paper's even on the same frames (docs/detectors.md).
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from massviz.core.detector import DEFAULT_THRESHOLDS
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
#: RANSAC of the support plane: iterations, points sampled, inlier tolerance in 1/z (1/m; 0.01 is 5.6 mm at 0.75 m).
PLANE_ITERATIONS = 100
PLANE_POINTS = 1500
PLANE_TOL = 0.01


def _uv1(us: np.ndarray, vs: np.ndarray) -> np.ndarray:
    return np.stack([us, vs, np.ones(len(us))], 1).astype(np.float64)


def support_plane(depth: np.ndarray, box, *, min_mm: float = 200.0, max_mm: float = 4000.0, tol: float = PLANE_TOL,
                  min_share: float = 0.5, seed: int = 0) -> np.ndarray | None:
    """The box's pixels on the plane the object stands on (bool, the box's shape), or None when there is none.

    The plane is fitted by RANSAC in ``(u, v, 1000/z)`` (a 3D plane is a plane there, and a stereo camera's noise
    is about constant in 1/z) on what lies *around the lower part of the box*: the strip below it and its lower
    third's sides, each a quarter of the box wide. It is a support only when it holds ``min_share`` of that
    region's depth pixels: a table top continues beyond the box, the face of a box held or standing in it does not."""
    h, w = depth.shape
    x1, y1, x2, y2 = (int(v) for v in box)
    bw, bh = x2 - x1, y2 - y1
    mx, my = max(4, bw // 4), max(4, bh // 4)
    rx1, rx2, ry1, ry2 = max(0, x1 - mx), min(w, x2 + mx), y1 + (2 * bh) // 3, min(h, y2 + my)
    z = depth[ry1:ry2, rx1:rx2].astype(np.float64)
    around = (z >= min_mm) & (z <= max_mm)
    around[:y2 - ry1, x1 - rx1:x2 - rx1] = False  # the box itself is not the surroundings
    vs, us = np.nonzero(around)
    if len(us) < 50:
        return None
    rng = np.random.default_rng(seed)
    if len(us) > PLANE_POINTS:
        pick = rng.choice(len(us), PLANE_POINTS, replace=False)
        us, vs = us[pick], vs[pick]
    pts, inv = _uv1(us + rx1, vs + ry1), 1000.0 / z[vs, us]
    tri = rng.integers(0, len(pts), size=(PLANE_ITERATIONS, 3))
    a, b = pts[tri], inv[tri]
    ok = np.abs(np.linalg.det(a)) > 1e-6
    if not ok.any():
        return None
    coef = np.linalg.solve(a[ok], b[ok][..., None])[..., 0]
    best = coef[int(np.argmax(np.count_nonzero(np.abs(pts @ coef.T - inv[:, None]) < tol, axis=0)))]
    for _refine in range(2):  # least squares on its inliers
        inl = np.abs(pts @ best - inv) < tol
        best = np.linalg.lstsq(pts[inl], inv[inl], rcond=None)[0]
    if np.mean(np.abs(pts @ best - inv) < tol) < min_share:
        return None
    zb = depth[y1:y2, x1:x2].astype(np.float64)
    vv, uu = np.mgrid[y1:y2, x1:x2]
    return (zb > 0) & (np.abs(1000.0 / np.maximum(zb, 1.0) - (best[0] * uu + best[1] * vv + best[2])) < tol)


def depth_mask(depth: np.ndarray, box, *, min_mm: float = 200.0, max_mm: float = 4000.0, centre: float = 0.5,
               mode_fraction: float = 0.25, band_mm: float = 40.0, band_fraction: float = 0.05,
               step_fraction: float = 0.015, step_mm: float = 6.0, min_depth_fraction: float = 0.05) -> np.ndarray:
    """The object in one box as a bool mask of the box's shape (module docstring): ``depth`` is the whole frame's
    depth (mm, 0 = none), ``box`` (x1, y1, x2, y2) integers. All False when the box has too little depth."""
    x1, y1, x2, y2 = (int(v) for v in box)
    z = np.asarray(depth[y1:y2, x1:x2], dtype=np.float64)
    valid = (z >= min_mm) & (z <= max_mm)
    out = np.zeros(z.shape, dtype=bool)
    if z.size == 0 or int(valid.sum()) < max(10, min_depth_fraction * z.size):
        return out
    plane = support_plane(depth, (x1, y1, x2, y2), min_mm=min_mm, max_mm=max_mm)
    if plane is not None:
        valid &= ~plane
    h, w = z.shape
    core = np.zeros_like(valid)
    core[int(h * (1 - centre) / 2):int(np.ceil(h * (1 + centre) / 2)),
         int(w * (1 - centre) / 2):int(np.ceil(w * (1 + centre) / 2))] = True
    values = np.sort(z[valid & core])
    if values.size < 10:  # the centre has (almost) no depth: the whole box
        core, values = valid, np.sort(z[valid])
        if values.size == 0:
            return out
    # the seed layer: from near to far, the first slab [v, v + 2·band] holding mode_fraction of the centre's depth
    ends = np.searchsorted(values, values + 2 * np.maximum(band_mm, band_fraction * values), side="right")
    enough = np.flatnonzero(ends - np.arange(values.size) >= mode_fraction * values.size)
    i = int(enough[0]) if enough.size else 0
    mode = float(np.median(values[i:ends[i]]))
    seeds = valid & core & (np.abs(z - mode) <= max(band_mm, band_fraction * mode))
    # grown from the seeds over neighbours whose depth differs by at most step (relative: a flood fill of log z)
    logz = np.where(valid, np.log(np.maximum(z, 1.0)), 1e3).astype(np.float32)
    step = float(np.log1p(max(step_fraction, step_mm / mode)))
    grown = np.zeros((h + 2, w + 2), np.uint8)
    flags = 8 | cv2.FLOODFILL_MASK_ONLY | (1 << 8)
    ys, xs = np.nonzero(seeds)
    centred = (ys - h / 2) ** 2 + (xs - w / 2) ** 2
    while ys.size:  # from the seed nearest the box's centre, then any seed the fills have not reached
        k = int(np.argmin(centred))
        cv2.floodFill(logz, grown, (int(xs[k]), int(ys[k])), 0, step, step, flags)
        left = grown[ys + 1, xs + 1] == 0
        ys, xs, centred = ys[left], xs[left], centred[left]
    n, labels, stats, _ = cv2.connectedComponentsWithStats(grown[1:-1, 1:-1] & valid.astype(np.uint8), connectivity=8)
    if n <= 1:
        return out
    return labels == 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))


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
    default_threshold = DEFAULT_THRESHOLDS["nanodet"]

    def __init__(self, threshold: float = DEFAULT_THRESHOLDS["nanodet"], weights: str | Path | None = None, *,
                 nms_iou: float = NMS_IOU,
                 band_mm: float = 40.0, band_fraction: float = 0.05, mode_fraction: float = 0.25,
                 step_fraction: float = 0.015, progress: bool = True):
        self.threshold = float(threshold)
        self.weights = None if weights is None else Path(weights)
        self.nms_iou = float(nms_iou)
        self.mask = {"band_mm": float(band_mm), "band_fraction": float(band_fraction),
                     "mode_fraction": float(mode_fraction), "step_fraction": float(step_fraction)}
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
                "nms_iou": self.nms_iou, "input": INPUT_SIZE, "mask": dict(self.mask), "version": 2}

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
        masks = [depth_mask(depth, b, **self.mask) for b in xyxy]
        return Detections(frame=np.full(len(xyxy), frame.index), xyxy=xyxy, score=scores.astype(np.float32),
                          class_id=np.array([COCO80_KEEP[int(c)] for c in classes], dtype=np.int64), masks=masks)


__all__ = ["NanoDetDetector", "preprocess", "decode", "input_to_frame", "check_outputs", "depth_mask", "support_plane", "load_net",
           "resolve_model", "cached_model", "NANODET_NAME", "NANODET_URL_BASE", "NANODET_SHA256", "COCO80_KEEP"]
