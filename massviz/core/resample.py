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
the chunk's largest side costs little. The coefficient tables of every side stay on the device (made once per device,
:func:`device_tables`); a batch copies only its boxes there. The passes (:func:`resize_chunk`) have shapes fixed by a
chunk's bucketed side, so on CUDA they run compiled, once per bucket (``massviz.core.streams.compiled``).
"""
from __future__ import annotations

import math
import threading

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
    """uint8 -> float32 / 255 exactly as the CPU computes it (``ToTensor``), on any device, in ``u8.float()``'s
    layout: on the CPU that division itself; elsewhere a table of the 256 quotients made on the CPU (on CUDA, PyTorch
    divides by a Python number as a multiplication by its reciprocal, which differs from the true quotient in the last
    bit for some values)."""
    import torch

    if u8.device.type == "cpu":
        return u8.float().div(255)
    table = _TO_FLOAT.get(u8.device)
    if table is None:
        table = _TO_FLOAT[u8.device] = torch.arange(256, dtype=torch.float32).div(255).to(u8.device)
    return torch.empty_like(u8, dtype=torch.float32).copy_(table[u8.to(torch.int64)])


def _clip8(acc):
    """Pillow's ``clip8``: the rounded fixed-point sum (``acc`` includes the half) back to 0..255."""
    return (acc >> PRECISION_BITS).clamp_(0, 255)


#: sides the device tables grow by (all sides 1..S are kept, S a multiple of this)
TABLE_STEP = 256
_TABLES: dict = {}
_TABLES_LOCK = threading.Lock()


def taps(side: int) -> int:
    """Pillow's taps per output pixel for resizing ``side`` pixels to 112."""
    return int(math.ceil(max(float(side) / PATCH_SIZE, 1.0))) * 2 + 1


def device_tables(device, sides):
    """The coefficient tables on ``device``, kept there per device: ``first`` (S + 1, 112) int64 and ``weights``
    (S + 1, 112, taps(S)) int32, row ``s`` Pillow's coefficients for side s (:func:`coefficients`, zero past its
    taps) for every side in ``sides`` and every side asked for before; rows of sides not asked for yet are zero.
    Only the rows of new sides are copied (a warm run copies none); S grows by ``TABLE_STEP``."""
    import torch

    # ordinary tensors even when a caller runs in inference mode: the tables outlive the call and grow in place, which
    # an inference tensor refuses outside inference mode
    with _TABLES_LOCK, torch.inference_mode(False):
        return _device_tables(torch.device(device), np.unique(np.asarray(sides, dtype=np.int64)))


def _device_tables(device, sides):
    import torch

    key = str(device)
    got = _TABLES.get(key)
    need = int(sides.max()) if len(sides) else 1
    if got is None or got[0].shape[0] <= need:
        size = -(-need // TABLE_STEP) * TABLE_STEP
        first = torch.zeros((size + 1, PATCH_SIZE), dtype=torch.int64, device=device)
        weights = torch.zeros((size + 1, PATCH_SIZE, taps(size)), dtype=torch.int32, device=device)
        have = set()
        if got is not None:  # the rows made before
            first[:got[0].shape[0]] = got[0]
            weights[:got[1].shape[0], :, :got[1].shape[2]] = got[1]
            have = got[2]
        got = _TABLES[key] = (first, weights, have)
    first, weights, have = got
    new = [int(s) for s in sides if int(s) not in have]
    if new:
        rows_f = np.stack([_coefficients(s)[0] for s in new])
        rows_w = np.zeros((len(new), PATCH_SIZE, weights.shape[2]), np.int32)
        for i, s in enumerate(new):
            wt = _coefficients(s)[1]
            rows_w[i, :, :wt.shape[1]] = wt
        idx = torch.tensor(new, dtype=torch.int64, device=device)
        first[idx] = torch.from_numpy(rows_f).to(device)
        weights[idx] = torch.from_numpy(rows_w).to(device)
        have.update(new)
    return first, weights


def resize_chunk(frames, geo, first, weights, s_max: int, k_max: int):
    """(m, 3, 112, 112) float32 for m boxes: Pillow's two passes (horizontal into the rows of each padded square,
    then vertical) as int32 sums. ``geo`` (m, 7) int64: frame, x0, y0 (the padded square's corner), x_lo, x_hi,
    y_lo, y_hi (the crop); ``first`` (m, 112), ``weights`` (m, 112, >= k_max) each box's tables; ``s_max``: at least
    the largest side, ``k_max``: at least the most taps. Larger ``s_max``/``k_max`` give the same bytes (a tap
    past a box's own reads weight 0), so callers bucket them."""
    import torch

    dev = frames.device
    m = geo.shape[0]
    f, x0, y0, x_lo, x_hi, y_lo, y_hi = geo.unbind(1)
    # rows of the padded square (0..s_max) -> frame rows; those outside the crop read 0
    y = y0[:, None] + torch.arange(s_max, device=dev)[None, :]  # (m, s_max)
    y_ok = (y >= y_lo[:, None]) & (y < y_hi[:, None])
    y = torch.where(y_ok, y, y_lo[:, None])
    # horizontal pass: (m, s_max rows, 112, 3)
    acc = torch.full((m, s_max, PATCH_SIZE, 3), 1 << (PRECISION_BITS - 1), dtype=torch.int32, device=dev)
    for k in range(k_max):
        x = x0[:, None] + first + k  # (m, 112) frame columns of tap k
        x_ok = (x >= x_lo[:, None]) & (x < x_hi[:, None])
        x = torch.where(x_ok, x, x_lo[:, None])
        px = frames[f[:, None, None], y[:, :, None], x[:, None, :]].to(torch.int32)  # (m, s_max, 112, 3)
        wk = torch.where(x_ok, weights[:, :, k], 0)  # (m, 112)
        acc += px * (wk[:, None, :, None] * y_ok[:, :, None, None])
    rows = _clip8(acc)  # (m, s_max, 112, 3): Pillow's intermediate image, rows of the padded square
    # vertical pass: (m, 112, 112, 3)
    acc = torch.full((m, PATCH_SIZE, PATCH_SIZE, 3), 1 << (PRECISION_BITS - 1), dtype=torch.int32, device=dev)
    mi = torch.arange(m, device=dev)
    for k in range(k_max):
        yk = (first + k).clamp_(max=s_max - 1)  # a tap past the square has weight 0
        acc += rows[mi[:, None], yk] * weights[:, :, k][:, :, None, None]
    return _clip8(acc).permute(0, 3, 1, 2).to(torch.uint8)


def resize_boxes(frames, frame_of, boxes, chunk: int = 64):
    """The mass CNN's input for each box: (n, 3, 112, 112) float32 in [0, 1] on ``frames``' device, equal to
    ``preprocess_patch(crop(frames[f], box))`` bit for bit.

    ``frames``: (F, H, W, 3) uint8 tensor (any device); ``frame_of``: (n,) which frame each box is on; ``boxes``:
    (n, 4) integer ``x1, y1, x2, y2`` (x2/y2 exclusive, non-empty, inside the frame), host arrays. Chunks of
    ``chunk`` boxes of similar side (the last one padded), their largest side rounded up by
    ``massviz.core.streams.bucket``: on CUDA the passes (:func:`resize_chunk`) run compiled, once per bucket."""
    import torch

    from massviz.core.streams import bucket, compiled

    boxes = np.asarray(boxes, dtype=np.int64).reshape(-1, 4)
    frame_of = np.asarray(frame_of, dtype=np.int64).reshape(-1)
    n = len(boxes)
    dev = frames.device
    out = torch.empty((n, 3, PATCH_SIZE, PATCH_SIZE), dtype=torch.float32, device=dev)
    if n == 0:
        return out
    w, h = boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]
    if (w < 1).any() or (h < 1).any():
        raise ValueError("resize_boxes: every box must be at least one pixel wide and high")
    side = np.maximum(w, h)
    left, top = (side - w) // 2, (side - h) // 2
    order = np.argsort(side, kind="stable")
    first_t, weights_t = device_tables(dev, side)
    # the boxes in one copy to the device: geometry, then the side (the tables' row)
    geo = np.stack([frame_of, boxes[:, 0] - left, boxes[:, 1] - top, boxes[:, 0], boxes[:, 2], boxes[:, 1],
                    boxes[:, 3], side], axis=1)[order]
    pad = (-n) % chunk
    geo = np.concatenate([geo, np.repeat(geo[-1:], pad, axis=0)])  # the last chunk padded with its last box
    src = torch.from_numpy(geo)
    geo_d = (src.pin_memory() if dev.type == "cuda" else src).to(dev, non_blocking=True)
    order_d = torch.from_numpy(order).to(dev, non_blocking=dev.type == "cuda")
    run = compiled(resize_chunk, dev)
    for start in range(0, n, chunk):
        g = geo_d[start:start + chunk]
        s_max = min(bucket(int(side[order[min(start + chunk, n) - 1]]), least=32), first_t.shape[0] - 1)
        u8 = run(frames, g[:, :7], first_t[g[:, 7]], weights_t[g[:, 7]], s_max, min(taps(s_max), weights_t.shape[2]))
        m = min(chunk, n - start)
        out[order_d[start:start + m]] = to_unit_float(u8[:m])
    return out


__all__ = ["PATCH_SIZE", "PRECISION_BITS", "TABLE_STEP", "coefficients", "device_tables",
           "resize_boxes", "resize_chunk", "taps", "to_unit_float"]
