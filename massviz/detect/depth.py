"""A detector without weights: the nearest objects in the depth map.

The paper assumes that the manipulated container is the object nearest to the fixed frontal camera. This detector
takes that assumption literally and segments the nearest things in the depth map, class-agnostically:

1. **Working range.** Depth outside ``[min_mm, max_mm]`` is ignored (the wall, the room).
2. **Support planes.** Up to ``max_planes`` large planes (the table top) are found by RANSAC and removed, so that an
   object standing on the table is not joined to it. Planes are fitted in ``(u, v, 1/z)``: a 3D plane is exactly a
   plane there (``1/z = a·u + b·v + c``), so no intrinsics are needed, and a stereo camera's depth noise, which grows
   with z², is about constant in 1/z, so one tolerance fits near and far. A plane counts as support only when it is
   large (``plane_min_area`` of the image) and wide (its inliers span ``plane_min_span`` of the image width), which a
   handed-over box face never is.
3. **Nearest layer, nearest blob.** The nearest remaining depth ``z0`` (a low order statistic, robust to stray
   pixels) opens a layer ``[z0, z0 + slab_mm]`` as deep as a container (once its nearest blob is known, the layer
   restarts at that blob's own front, so a stray near pixel cannot cut the blob short). The layer's mask is closed morphologically
   (kernel ``close_size`` × image width), adding only pixels without depth: this bridges random dropouts and the
   sparse returns of a transparent glass (its rim, its silhouette, its base). The blob is the connected component of
   that mask with the nearest depth, grown over its convex hull: the layer's components mostly inside the hull join
   it (pieces of a glass outline that its depth-less inside keeps apart) and so do the depth-less pixels inside the
   hull (the inside of a glass). A pixel that measured something farther is never added (a handle stays open).
4. The blob is removed and the search repeats, up to ``max_objects`` blobs, nearest first. A pitcher nearer than the
   container is returned together with the container; the K-nearest selection downstream decides.
5. **Not container candidates** (removed like the others, but never returned; the search goes on behind them):
   a blob **cut by the image border** (pixels within ``border_px`` of it: the table's front corner, a robot gripper
   entering the view, a sliver at the image edge; what is cut cannot be measured whole), a blob **attached to a
   border-cut one** (within ``attach_px`` of it and within ``slab_mm`` of its depth: the visible top of that gripper),
   and a blob of **implausible size** for a hand-held container (wider or taller than ``max_size_mm``, e.g. a cup
   merged with the arms and the table edge behind it). Metric size needs a focal length the detector is not given; it
   assumes fx = fy = ``fx_fraction`` × image width (0.72: the CCM cameras, 923 px at 1280, and the RealSense D4xx
   colour camera's ~69° field of view), which is exact enough for a 450 mm bound. Each rejected blob is noted per
   frame (``notes``; the pipeline puts them in the trace's events, and when nothing else is left the recording is
   *not estimated* with them as the reason).

A hand holding the container is at the container's depth and touches it: it becomes part of the container's blob
(the slab cuts the arm off a few centimetres behind it). Depth alone cannot tell them apart.

**Score** (the confidence ``threshold`` is compared with): the fraction of the blob's outline where the depth jumps
away behind it (by more than ``jump_mm`` + 2 %) or is missing, i.e. how freely the blob stands in front of the rest.
The blobs themselves do not depend on the threshold, which only filters them.
An object held in the air scores about 1; one standing on a table, a little less (its base touches the table); a
patch of a larger surface or something partly hidden by a nearer object scores low. The default threshold 0.4 keeps
blobs that are free along at least 40 % of their outline (measured: every cut from 0.2 to 0.5 chooses the same
patches on CCM 618, view1 and the samples; docs/detectors.md, "Default score cuts").
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import cv2
import numpy as np

from massviz.core.detector import DEFAULT_THRESHOLDS
from massviz.core.types import OBJECT_CLASS_ID, Detections, Frame, Rejection


@dataclass
class DepthDetector:
    """Class-agnostic nearest-object detector on the depth map (see the module docstring for the method).

    Lengths are millimetres; ``close_size`` and ``min_area`` are fractions of the image width and of its pixel count,
    so the same settings serve 480×270 samples and 1280×720 recordings.
    """

    threshold: float = DEFAULT_THRESHOLDS["depth"]
    max_objects: int = 2
    min_mm: float = 200.0
    max_mm: float = 2000.0
    slab_mm: float = 80.0
    jump_mm: float = 20.0
    close_size: float = 0.02
    min_area: float = 0.001
    max_planes: int = 2
    plane_tol: float = 0.006  # 1/m: inlier tolerance of the support planes in inverse depth
    plane_min_area: float = 0.08
    plane_min_span: float = 0.5
    ransac_iterations: int = 300
    seed: int = 0
    border_px: int = 2
    attach_px: int = 3
    max_size_mm: float = 450.0
    fx_fraction: float = 0.72
    name: str = "depth"

    @property
    def default_threshold(self) -> float:
        return DEFAULT_THRESHOLDS["depth"]

    def __post_init__(self) -> None:
        #: frame index -> why blobs of that frame were not candidates (``pop_notes``); not a setting.
        self._notes: dict[int, list[Rejection]] = {}

    def settings(self) -> dict:
        """Every setting that changes the output except ``threshold`` (it keys the detection cache)."""
        out = asdict(self)
        del out["threshold"]
        out.pop("_notes", None)
        return out

    def pop_notes(self, index: int) -> list[Rejection]:
        """Why blobs of frame ``index`` were not container candidates (``Rejection``: the reason and a line), once."""
        return self._notes.pop(int(index), [])

    def detect(self, frame: Frame) -> Detections:
        """Of the ``max_objects`` nearest blobs of ``frame.depth``, those with score > ``threshold``, nearest first."""
        depth = np.asarray(frame.depth)
        h, w = depth.shape
        z = depth.astype(np.float32)
        valid = (z >= self.min_mm) & (z <= self.max_mm)
        remaining = valid & ~support_planes(z, valid, self)
        min_px = max(1, int(self.min_area * h * w))
        k = 2 * int(round(self.close_size * w / 2)) + 1  # odd: a closing with an even kernel shifts the mask
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
        found, cut, notes = [], np.zeros((h, w), dtype=bool), []
        edge = np.zeros((h, w), dtype=bool)
        b = max(1, int(self.border_px))
        edge[:b], edge[-b:], edge[:, :b], edge[:, -b:] = True, True, True, True
        near_kernel = np.ones((2 * self.attach_px + 1, 2 * self.attach_px + 1), np.uint8)
        fx = self.fx_fraction * w
        for _ in range(6 * self.max_objects + 6):  # each round takes a blob, rejects one or discards fragments
            if len(found) == self.max_objects or remaining.sum() < min_px:
                break
            blob, fragments = nearest_blob(z, depth == 0, remaining, kernel, min_px, self.slab_mm)
            remaining &= ~fragments
            if blob is None:  # only fragments in this layer: look farther
                continue
            remaining &= ~blob
            zb = float(np.median(z[blob & ~(depth == 0)])) if (blob & ~(depth == 0)).any() else 0.0
            ys, xs = np.nonzero(blob)
            where = f"box {[int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1]} at {zb:.0f} mm"
            size = (np.ptp(xs) + 1) * zb / fx, (np.ptp(ys) + 1) * zb / fx
            if (blob & edge).any():
                cut |= blob
                notes.append(Rejection("border-cut object", f"border-cut object ({where})"))
                continue
            touching = cv2.dilate(blob.astype(np.uint8), near_kernel) > 0
            attached = touching & cut
            if attached.any() and abs(float(np.median(z[attached & (depth > 0)])) - zb) <= self.slab_mm \
                    if (attached & (depth > 0)).any() else False:
                cut |= blob
                notes.append(Rejection("part of a border-cut object", f"part of a border-cut object ({where})"))
                continue
            if max(size) > self.max_size_mm:
                notes.append(Rejection("implausibly sized object",
                                       f"implausibly sized object, {size[0]:.0f}×{size[1]:.0f} mm ({where})"))
                continue
            found.append((blob, separation(blob, z, depth == 0, self.jump_mm)))
        if notes:
            if len(self._notes) > 256:  # nobody collects them: keep the newest frames only
                self._notes.pop(next(iter(self._notes)))
            self._notes[int(frame.index)] = notes
        # The threshold only filters (it is not part of the cache key): the blobs do not depend on it.
        return _detections(frame.index, [(blob, score) for blob, score in found if score > self.threshold])


def support_planes(z: np.ndarray, valid: np.ndarray, det: DepthDetector) -> np.ndarray:
    """Mask of the pixels on large, wide planes (table tops, walls), fitted by RANSAC in ``(u, v, 1/z)``."""
    h, w = z.shape
    rng = np.random.default_rng(det.seed)
    inv = np.where(valid, 1000.0 / np.maximum(z, 1.0), 0.0)  # 1/m
    planes = np.zeros((h, w), dtype=bool)
    free = valid.copy()
    for _ in range(det.max_planes):
        idx = np.flatnonzero(free)
        if len(idx) < max(3, det.plane_min_area * h * w):
            break
        sample = rng.choice(idx, size=min(len(idx), 4000), replace=False)
        pts, target = _uv1(sample, w), inv.flat[sample]
        tri = rng.integers(0, len(sample), size=(det.ransac_iterations, 3))
        a, b = pts[tri], target[tri]
        ok = np.abs(np.linalg.det(a)) > 1e-6
        coef = np.linalg.solve(a[ok], b[ok][..., None])[..., 0]  # planes × 3
        residual = pts @ coef.T  # sample × planes; in place from here (the same arithmetic, a third of the time)
        residual -= target[:, None]
        np.abs(residual, out=residual)
        support = np.count_nonzero(residual < det.plane_tol, axis=0)
        best = coef[int(np.argmax(support))]
        full, target = _uv1(idx, w), inv.flat[idx]
        for _refine in range(2):  # least squares on all inliers, twice
            inl = np.abs(full @ best - target) < det.plane_tol
            best = np.linalg.lstsq(full[inl], target[inl], rcond=None)[0]
        inliers = idx[np.abs(full @ best - target) < det.plane_tol]
        cols = inliers % w
        if len(inliers) < det.plane_min_area * h * w or np.ptp(cols) < det.plane_min_span * w:
            break
        planes.flat[inliers] = True
        free.flat[inliers] = False
    return planes


def _uv1(flat: np.ndarray, w: int) -> np.ndarray:
    """``(u, v, 1)`` rows (float64) of the pixels at flat indices ``flat`` of an image ``w`` wide."""
    out = np.empty((len(flat), 3))
    out[:, 1], out[:, 0] = np.divmod(flat, w)
    out[:, 2] = 1.0
    return out


def close_near(mask: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """``cv2.morphologyEx(mask, MORPH_CLOSE, kernel) > 0``, computed on ``mask``'s bounding box grown by the kernel's
    size only: the same pixels (outside that box the dilation is empty and the erosion keeps it so; a pixel whose
    erosion would look past the box is itself farther than the kernel's reach from the mask, hence empty), at a
    fraction of the cost when the mask covers little of a large image."""
    m = mask.astype(np.uint8)
    x, y, bw, bh = cv2.boundingRect(m)
    out = np.zeros(mask.shape, dtype=bool)
    if bw == 0:
        return out
    kh, kw = kernel.shape
    y0, y1 = max(0, y - kh), min(mask.shape[0], y + bh + kh)
    x0, x1 = max(0, x - kw), min(mask.shape[1], x + bw + kw)
    out[y0:y1, x0:x1] = cv2.morphologyEx(m[y0:y1, x0:x1], cv2.MORPH_CLOSE, kernel) > 0
    return out


def depth_layer(z: np.ndarray, hole: np.ndarray, remaining: np.ndarray, kernel: np.ndarray, far_mm: float):
    """The ``remaining`` pixels up to ``far_mm``, closed with ``kernel`` (adding only depth-less pixels), labelled.

    Returns the layer mask, the closed mask and ``cv2.connectedComponentsWithStats`` of the closed mask.
    """
    layer = remaining & (z <= far_mm)
    closed = close_near(layer, kernel)
    closed &= layer | hole
    return layer, closed, cv2.connectedComponentsWithStats(closed.astype(np.uint8), connectivity=8)


def nearest_blob(z: np.ndarray, hole: np.ndarray, remaining: np.ndarray, kernel: np.ndarray, min_px: int,
                 slab_mm: float) -> tuple[np.ndarray | None, np.ndarray]:
    """The nearest blob of the nearest depth layer and the layer's fragments.

    Fragments are the layer's components smaller than ``min_px`` or with less than a quarter of that measured
    (stray pixels, slivers): they are never objects. The blob is ``None`` when the layer holds only fragments.
    """
    near = z[remaining]
    kth = min(len(near) - 1, max(0, min_px // 10))
    z0 = float(np.partition(near, kth)[kth])
    layer, closed, (n, labels, stats, _) = depth_layer(z, hole, remaining, kernel, z0 + slab_mm)
    best, front = None, np.inf
    measured_px = np.bincount(labels[layer], minlength=n)
    small = (stats[:, cv2.CC_STAT_AREA] < min_px) | (measured_px < min_px // 4)
    small[0] = False
    fragments = (layer & ~closed) | (small[labels] & layer)
    for i in np.flatnonzero(~small[1:]) + 1:
        comp = labels == i
        comp_front = float(np.percentile(z[comp & layer], 5))
        if comp_front < front:
            best, front = comp, comp_front
    if best is None:
        return None, fragments
    # The layer started at the nearest stray pixel; restart it at the blob's own front so it holds all of the blob.
    _, closed, (_, labels, _, _) = depth_layer(z, hole, remaining & ~fragments, kernel, front + slab_mm)
    label = np.bincount(labels[best & closed]).argmax()
    return absorb(labels, label, hole), fragments


def convex_hull(mask: np.ndarray) -> np.ndarray:
    """The filled convex hull of ``mask``."""
    points = cv2.findNonZero(mask.astype(np.uint8))
    out = np.zeros(mask.shape, dtype=np.uint8)
    cv2.fillConvexPoly(out, cv2.convexHull(points), 1)
    return out > 0


def absorb(labels: np.ndarray, label: int, hole: np.ndarray) -> np.ndarray:
    """The component ``label`` grown over what lies inside its convex hull.

    Components of the same layer mostly inside the hull join it (the pieces of a glass's outline that its empty
    inside keeps apart), then the depth-less pixels inside the hull are added (the inside of a glass, dropouts).
    Pixels that measured something else are never added: a handle through which the wall is seen stays open.
    """
    hull = convex_hull(labels == label)
    inside = np.bincount(labels[hull], minlength=labels.max() + 1)
    area = np.bincount(labels.ravel(), minlength=labels.max() + 1)
    join = inside >= 0.5 * area
    join[0] = False
    blob = join[labels]
    return blob | (convex_hull(blob) & hole)


def separation(blob: np.ndarray, z: np.ndarray, hole: np.ndarray, jump_mm: float) -> float:
    """Fraction of the pixels just outside ``blob`` that have no depth or are farther than the blob beside them.

    "Farther" means by more than ``jump_mm`` (plus 2 % of the depth, the sensor's noise) than the farthest blob
    pixel within 2 pixels: a depth discontinuity, the blob stands in front of what is behind it there.
    """
    ring = cv2.dilate(blob.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    ring &= ~blob
    if not ring.any():  # the blob fills the image
        return 0.0
    beside = cv2.dilate(np.where(blob & ~hole, z, 0).astype(np.float32), np.ones((5, 5), np.uint8))
    farther = (beside > 0) & (z > beside * 1.02 + jump_mm)
    return float((hole[ring] | farther[ring]).mean())


def _detections(index: int, found: list[tuple[np.ndarray, float]]) -> Detections:
    boxes, masks = [], []
    for blob, _ in found:
        ys, xs = np.nonzero(blob)
        x1, y1, x2, y2 = int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1
        boxes.append((x1, y1, x2, y2))
        masks.append(blob[y1:y2, x1:x2].copy())
    n = len(found)
    return Detections(frame=np.full(n, index), xyxy=np.array(boxes, dtype=np.int32).reshape(n, 4),
                      score=np.array([s for _, s in found], dtype=np.float32),
                      class_id=np.full(n, OBJECT_CLASS_ID), masks=masks)


__all__ = ["DepthDetector"]
