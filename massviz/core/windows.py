"""Mask R-CNN's masks pasted inside their integer boxes on a device, and what the device path needs of them, in one
function: each box's mask window, its d (the depth under the mask) and the mask's bits in ``np.packbits`` layout.

The paste is torchvision's (``expand_masks``, ``expand_boxes``, a bilinear resize without aligned corners, the 0.5
threshold; ``massviz.detect.maskrcnn.paste_mask_crops`` on the host), written as gathers over many boxes at once, in
float32 as PyTorch's CUDA kernel computes it: ``h0 * (w0 * a + w1 * b) + h1 * (w0 * c + w1 * d)``. A pixel can differ
from ``paste_mask_crops`` only where its probability is within float rounding of 0.5 (tests/test_device_path.py).

Every function here is plain tensor arithmetic with shapes fixed by its integer arguments: the CPU runs them eagerly
(the path CI tests), CUDA runs :func:`window_features` compiled (``massviz.core.streams.compiled``) with the window
sizes and counts bucketed (``massviz.core.streams.bucket``), so it compiles once per bucket. Tests compare the eager
and the compiled function bit for bit.
"""
from __future__ import annotations

import numpy as np


def axis_taps(start, lo, hi, size: int, n_in: int, limit: int):
    """Along one axis, for window positions 0..size-1 of boxes starting at ``start``: the two input cells, their
    weights and whether the canvas holds the position ([lo, hi] of the expanded box, inside the image)."""
    import torch

    pos = start[:, None] + torch.arange(size, device=start.device)[None, :]  # image coordinate
    out_len = (hi - lo + 1).clamp(min=1)  # the resized mask's length
    j = pos - lo[:, None]  # index into the resized mask
    inside = (j >= 0) & (j < out_len[:, None]) & (pos < limit)
    scale = torch.full_like(out_len, n_in, dtype=torch.float32) / out_len.float()
    src = (scale[:, None] * (j.float() + 0.5) - 0.5).clamp(min=0)
    i0 = src.to(torch.int64).clamp(max=n_in - 1)  # src >= 0: truncation is floor
    lam = src - i0.float()
    i1 = torch.where(i0 < n_in - 1, i0 + 1, i0)
    return i0.clamp(min=0), i1.clamp(min=0), 1 - lam, lam, inside


def paste_windows(padded, expanded, box, height: int, width: int, im_h: int, im_w: int, threshold: float):
    """(k, height, width) bool: each mask (``padded`` (k, S, S) probabilities with ``expanded`` (k, 4) int64 boxes,
    ``expand_masks``/``expand_boxes``) pasted in its integer box ``box`` (k, 4) int64 x1, y1, x2, y2, top-left
    aligned, False past the box."""
    import torch

    dev = padded.device
    n_in = padded.shape[-1]
    y0, y1, wy0, wy1, y_in = axis_taps(box[:, 1], expanded[:, 1], expanded[:, 3], height, n_in, im_h)
    x0, x1, wx0, wx1, x_in = axis_taps(box[:, 0], expanded[:, 0], expanded[:, 2], width, n_in, im_w)
    k = torch.arange(len(box), device=dev)[:, None, None]
    rows = torch.arange(n_in, device=dev)[None, :, None]
    cols = torch.arange(width, device=dev)
    # along x for every row of the padded mask, then along y: CUDA's h0 * (w0 * a + w1 * b) + h1 * (...)
    across = wx0[:, None, :] * padded[k, rows, x0[:, None, :]] + wx1[:, None, :] * padded[k, rows, x1[:, None, :]]
    value = wy0[:, :, None] * across[k, y0[:, :, None], cols] + wy1[:, :, None] * across[k, y1[:, :, None], cols]
    in_box = ((torch.arange(height, device=dev)[None, :] < (box[:, 3] - box[:, 1])[:, None])[:, :, None]
              & (cols[None, :] < (box[:, 2] - box[:, 0])[:, None])[:, None, :])
    return (value > threshold) & y_in[:, :, None] & x_in[:, None, :] & in_box


def window_distances(win, depth, geo, hundred):
    """d of each window (float64, NaN without depth): ``mask_distance``'s arithmetic, the sum of the depth under the
    mask over the count of its pixels with depth, rounded to 2 decimals. ``depth``: (F, H, W) int16 (the uint16
    millimetres' bits); ``geo``: (k, 5) int64 frame, x1, y1, x2, y2; ``hundred``: a float64 100 on the device (a
    tensor: a true division on CUDA)."""
    import torch

    dev = win.device
    hh, ww = win.shape[1], win.shape[2]
    ys = (geo[:, 2:3] + torch.arange(hh, device=dev)).clamp(max=depth.shape[1] - 1)
    xs = (geo[:, 1:2] + torch.arange(ww, device=dev)).clamp(max=depth.shape[2] - 1)
    z = depth[geo[:, 0, None, None], ys[:, :, None], xs[:, None, :]].to(torch.int64) & 0xFFFF
    z = torch.where(win, z, 0)
    total, count = z.sum(dim=(1, 2)), (z > 0).sum(dim=(1, 2))
    mean = total.double() / count.double()
    return torch.where(count > 0, torch.round(mean * hundred) / hundred, float("nan"))


def pack_windows(win, geo, nbytes: int):
    """(k, nbytes) uint8: each window's mask inside its box (``geo`` (k, 5): frame, x1, y1, x2, y2), flattened row
    by row and packed 8 pixels a byte, the first pixel in the high bit: ``np.packbits(mask, axis=None)`` of each
    box's (h, w) mask, zero-padded to ``nbytes``."""
    import torch

    dev = win.device
    k, hh, ww = win.shape
    h = (geo[:, 4] - geo[:, 2]).clamp(min=0)
    w = (geo[:, 3] - geo[:, 1]).clamp(min=0)
    p = torch.arange(nbytes * 8, device=dev)[None, :]  # bit positions
    valid = p < (h * w)[:, None]
    wd = w.clamp(min=1)[:, None]
    flat = ((p // wd).clamp(max=hh - 1) * ww + (p % wd).clamp(max=ww - 1))
    bits = win.reshape(k, hh * ww).gather(1, flat) & valid
    weights = torch.tensor([128, 64, 32, 16, 8, 4, 2, 1], dtype=torch.int32, device=dev)
    return (bits.view(k, nbytes, 8).to(torch.int32) * weights).sum(dim=2).to(torch.uint8)


def window_features(padded, expanded, depth, geo, hundred, height: int, width: int, nbytes: int, im_h: int,
                    im_w: int, threshold: float):
    """For k boxes at once: (d (k,) float64, bits (k, nbytes) uint8), :func:`paste_windows`,
    :func:`window_distances` and :func:`pack_windows` in one function (on CUDA, one compiled graph)."""
    win = paste_windows(padded, expanded, geo[:, 1:], height, width, im_h, im_w, threshold)
    return window_distances(win, depth, geo, hundred), pack_windows(win, geo, nbytes)


def packed_bytes(h: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Bytes of ``np.packbits`` of each (h, w) mask."""
    return (np.asarray(h, np.int64) * np.asarray(w, np.int64) + 7) // 8


__all__ = ["axis_taps", "paste_windows", "window_distances", "pack_windows",
           "window_features", "packed_bytes"]
