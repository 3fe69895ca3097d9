"""Per-detection features, as the paper's published code computes them.

For a detection with integer box (x1, y1, x2, y2) and mask M (cropped to the box) on a W×H frame with depth D:

* d = sum(D[box][M]) / count_nonzero(D[box][M]) rounded to 2 decimals (numpy rounding, as the original);
* a = round((x2 - x1) / W, 2) and b = round((y2 - y1) / H, 2) (Python rounding, as the original).

Deliberate differences from the original code (CORSMAL/Visual, demo/generate_video_inference.py):

* A mask without any depth made the original divide by zero (d = NaN, which then sorts unpredictably). massviz
  leaves d = NaN; the selection (``massviz.core.selection``) never selects such a detection, and reports it.
* With exactly one Mask R-CNN detection in a frame, the original's ``masks.squeeze()`` dropped the instance axis and
  it then used the first image *row* as the mask; massviz keeps the instance axis (see ``detect/maskrcnn.py``).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from massviz.core.types import Detections


def box_ratios(xyxy: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """a = box width / image width, b = box height / image height, each rounded to 2 decimals."""
    xyxy = np.asarray(xyxy).reshape(-1, 4)
    a = [round(int(x2 - x1) / width, 2) for x1, _, x2, _ in xyxy]
    b = [round(int(y2 - y1) / height, 2) for _, y1, _, y2 in xyxy]
    return np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)


def mask_distance(depth: np.ndarray, xyxy, mask: np.ndarray) -> float:
    """Mean depth (mm) over the mask pixels that have depth; NaN when none has."""
    x1, y1, x2, y2 = (int(v) for v in xyxy)
    box = depth[y1:y2, x1:x2]
    if mask.shape != box.shape:
        raise ValueError(f"mask of shape {mask.shape} does not fit box {[x1, y1, x2, y2]} ({box.shape} in frame)")
    values = box[mask]
    valid = np.count_nonzero(values)
    if valid == 0:
        return float("nan")
    return float(np.round(np.sum(values) / valid, 2))


def compute_features(dets: Detections, depth: np.ndarray) -> Detections:
    """The detections made on one frame with their ``d``, ``a`` and ``b``: a new ``Detections`` (``dets`` is left as
    it was)."""
    height, width = depth.shape[:2]
    a, b = box_ratios(dets.xyxy, width, height)
    d = np.array([mask_distance(depth, dets.xyxy[i], dets.mask(i)) for i in range(len(dets))], np.float64)
    return dataclasses.replace(dets, d=d, a=a, b=b, masks=list(dets.masks), patches=list(dets.patches))
