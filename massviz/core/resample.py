"""The mass CNN's patch preprocessing on a device: crop, zero-pad to a square and Pillow's bilinear resize to
112×112, for many patches at once, as integer tensor arithmetic that equals Pillow bit for bit.

The reference is ``massviz.core.model.preprocess_patch`` (the paper's transform: Pillow ``Image.resize`` BILINEAR on
the zero-padded square, antialiased when shrinking). Pillow resizes in two passes, horizontal then vertical, each a
sum of 8-bit pixels times fixed-point coefficients (22 fraction bits) rounded back to 8 bits (``Resample.c``:
``precompute_coeffs``, ``normalize_coeffs_8bpc``, ``ImagingResampleHorizontal_8bpc`` / ``Vertical``). Here the
coefficients are computed with numpy in Pillow's own double arithmetic and order (:func:`coefficients`), and the two
passes are int32 sums of gathered pixels on the frames' device (:func:`resize_boxes`): every product and partial sum
is an exact integer, so any device and any summation order give Pillow's bytes (``tests/test_resample.py`` compares
every side from 1 to 400 and large random crops with Pillow).

The pixels of a patch are read straight from its frame (no crop or padded square is materialised): a tap outside the
crop reads 0, the padding. Patches are processed in chunks of similar size (sorted by side) so that padding them to
the chunk's largest side costs little; the tables go to the device in one copy.
"""
from __future__ import annotations

import math

import numpy as np

#: side of the square patch the network sees (``massviz.core.model.PATCH_SIZE``).
PATCH_SIZE = 112
#: Pillow's fixed-point fraction bits for 8-bit images (``PRECISION_BITS = 32 - 8 - 2``).
PRECISION_BITS = 22


def coefficients(side: int, out: int = PATCH_SIZE) -> tuple[np.ndarray, np.ndarray]:
    """Pillow's BILINEAR coefficients for resizing ``side`` pixels to ``out`` (box 0..side): ``first`` (out,) int64,
    the first input pixel of each output pixel, and ``weights`` (out, taps) int32 fixed-point weights (0 past the
    pixel's window). Pillow's ``precompute_coeffs`` + ``normalize_coeffs_8bpc``, operation for operation."""
    if side < 1 or out < 1:
        raise ValueError(f"side and out must be >= 1, got {side}, {out}")
    scale = float(side) / out
    filterscale = max(scale, 1.0)
    support = 1.0 * filterscale  # the bilinear filter's support is 1
    taps = int(math.ceil(support)) * 2 + 1
    xx = np.arange(out, dtype=np.float64)
    center = 0.0 + (xx + 0.5) * scale
    ss = 1.0 / filterscale
    xmin = np.maximum(np.trunc(center - support + 0.5), 0).astype(np.int64)  # C's (int) truncates
    xmax = np.minimum(np.trunc(center + support + 0.5).astype(np.int64), side) - xmin
    x = np.arange(taps)
    used = x[None, :] < xmax[:, None]
    arg = ((x[None, :] + xmin[:, None]) - center[:, None] + 0.5) * ss
    w = np.where(used, np.maximum(1.0 - np.abs(arg), 0.0), 0.0)  # bilinear: 1 - |x| inside (-1, 1)
    ww = np.zeros(out)
    for k in range(taps):  # Pillow sums the weights one by one, in order (not numpy's pairwise sum)
        ww = ww + w[:, k]
    w = np.where(ww[:, None] != 0.0, w / np.where(ww == 0.0, 1.0, ww)[:, None], w)
    scaled = w * float(1 << PRECISION_BITS)
    fixed = np.where(w < 0, np.trunc(-0.5 + scaled), np.trunc(0.5 + scaled)).astype(np.int32)
    return xmin, fixed


_COEFFICIENTS: dict = {}


def _coefficients(side: int) -> tuple[np.ndarray, np.ndarray]:
    got = _COEFFICIENTS.get(side)
    if got is None:
        got = _COEFFICIENTS[side] = coefficients(side)
    return got


_TO_FLOAT: dict = {}


def to_unit_float(u8):
    """uint8 -> float32 / 255 exactly as the CPU computes it (``ToTensor``), on any device: a table of the 256
    quotients made on the CPU. (On CUDA, PyTorch divides by a Python number as a multiplication by its reciprocal,
    which differs from the true quotient in the last bit for some values.)"""
    import torch

    table = _TO_FLOAT.get(u8.device)
    if table is None:
        table = _TO_FLOAT[u8.device] = torch.arange(256, dtype=torch.float32).div(255).to(u8.device)
    return torch.empty_like(u8, dtype=torch.float32).copy_(table[u8.to(torch.int64)])  # u8.float()'s layout


def _clip8(acc):
    """Pillow's ``clip8``: the rounded fixed-point sum (``acc`` includes the half) back to 0..255."""
    return (acc >> PRECISION_BITS).clamp_(0, 255)


def resize_boxes(frames, frame_of, boxes, chunk: int = 64):
    """The mass CNN's input for each box: (n, 3, 112, 112) float32 in [0, 1] on ``frames``' device, equal to
    ``preprocess_patch(crop(frames[f], box))`` bit for bit.

    ``frames``: (F, H, W, 3) uint8 tensor (any device); ``frame_of``: (n,) which frame each box is on; ``boxes``:
    (n, 4) integer ``x1, y1, x2, y2`` (x2/y2 exclusive, non-empty, inside the frame), host arrays."""
    import torch

    boxes = np.asarray(boxes, dtype=np.int64).reshape(-1, 4)
    frame_of = np.asarray(frame_of, dtype=np.int64).reshape(-1)
    n = len(boxes)
    out = torch.empty((n, 3, PATCH_SIZE, PATCH_SIZE), dtype=torch.float32, device=frames.device)
    if n == 0:
        return out
    w, h = boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]
    if (w < 1).any() or (h < 1).any():
        raise ValueError("resize_boxes: every box must be at least one pixel wide and high")
    side = np.maximum(w, h)
    left, top = (side - w) // 2, (side - h) // 2
    order = np.argsort(side, kind="stable")
    # every table in one copy to the device (a copy from pageable memory waits for the device's queue)
    tables = [_coefficients(int(s)) for s in side]
    taps = np.array([t[1].shape[1] for t in tables])
    first = np.stack([t[0] for t in tables])
    weights = np.zeros((n, PATCH_SIZE, int(taps.max())), np.int32)
    for i, (_, wt) in enumerate(tables):
        weights[i, :, :wt.shape[1]] = wt
    geo = np.stack([frame_of, boxes[:, 0] - left, boxes[:, 1] - top, boxes[:, 0], boxes[:, 2], boxes[:, 1],
                    boxes[:, 3]], axis=1)
    dev = frames.device
    first_d, weights_d = torch.from_numpy(first).to(dev), torch.from_numpy(weights).to(dev)
    geo_d, order_d = torch.from_numpy(geo).to(dev), torch.from_numpy(order).to(dev)
    for start in range(0, n, chunk):
        idx = order_d[start:start + chunk]
        s_max = int(side[order[start:start + chunk]].max())
        k_max = int(taps[order[start:start + chunk]].max())
        f, x0, y0, x_lo, x_hi, y_lo, y_hi = geo_d[idx].unbind(1)
        cf, cw = first_d[idx], weights_d[idx]
        # rows of the padded square (0..s_max) -> frame rows; those outside the crop read 0
        y = y0[:, None] + torch.arange(s_max, device=dev)[None, :]  # (m, s_max)
        y_ok = (y >= y_lo[:, None]) & (y < y_hi[:, None])
        y = torch.where(y_ok, y, y_lo[:, None])
        # horizontal pass: (m, s_max rows, 112, 3)
        acc = torch.full((len(idx), s_max, PATCH_SIZE, 3), 1 << (PRECISION_BITS - 1), dtype=torch.int32, device=dev)
        for k in range(k_max):
            x = x0[:, None] + cf + k  # (m, 112) frame columns of tap k
            x_ok = (x >= x_lo[:, None]) & (x < x_hi[:, None])
            x = torch.where(x_ok, x, x_lo[:, None])
            px = frames[f[:, None, None], y[:, :, None], x[:, None, :]].to(torch.int32)  # (m, s_max, 112, 3)
            wk = torch.where(x_ok, cw[:, :, k], 0)  # (m, 112)
            acc += px * (wk[:, None, :, None] * y_ok[:, :, None, None])
        rows = _clip8(acc)  # (m, s_max, 112, 3): Pillow's intermediate image, rows of the padded square
        # vertical pass: (m, 112, 112, 3)
        acc = torch.full((len(idx), PATCH_SIZE, PATCH_SIZE, 3), 1 << (PRECISION_BITS - 1), dtype=torch.int32,
                         device=dev)
        m = torch.arange(len(idx), device=dev)
        for k in range(k_max):
            yk = (cf + k).clamp_(max=s_max - 1)  # a tap past the square has weight 0
            acc += rows[m[:, None], yk] * cw[:, :, k][:, :, None, None]
        out[idx] = to_unit_float(_clip8(acc).permute(0, 3, 1, 2))
    return out


__all__ = ["PATCH_SIZE", "PRECISION_BITS", "coefficients", "resize_boxes", "to_unit_float"]
