"""A detection's RGB patch as the paper's code crops it, and as the mass CNN sees it.

Views import these to show patches; they never re-run a stage. ``model_view`` loads torch on first use.
"""
from __future__ import annotations

import numpy as np


def crop(rgb: np.ndarray, xyxy) -> np.ndarray:
    """The RGB patch of a box (x2/y2 exclusive), as the paper's code crops it."""
    x1, y1, x2, y2 = (int(v) for v in xyxy)
    return np.ascontiguousarray(rgb[y1:y2, x1:x2])


def model_view(patch: np.ndarray) -> np.ndarray:
    """The patch as the model sees it (``massviz.core.model.preprocess_patch``: zero-padded square, 112×112, [0, 1]),
    as an H×W×3 uint8 image."""
    from massviz.core.model import preprocess_patch

    tensor = preprocess_patch(patch)
    return (tensor.detach().cpu().numpy().transpose(1, 2, 0) * 255.0).round().clip(0, 255).astype(np.uint8)


__all__ = ["crop", "model_view"]
