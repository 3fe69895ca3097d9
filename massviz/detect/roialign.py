"""RoIAlign on channels_last features as one weighted gather: torchvision's ``roi_align`` up to float rounding, ~10x
faster on a CPU.

torchvision's CPU ``roi_align`` walks an NCHW feature map channel plane by channel plane (one core; and it first
copies channels_last features to NCHW). Each output bin of RoIAlign (``aligned=False``, a fixed sampling grid) is a
weighted sum of 4 x grid x grid feature vectors: grid x grid bilinear samples, 4 neighbours each. With channels_last
features a feature vector is one contiguous row of C values, so the whole pooling is one
``torch.nn.functional.embedding_bag(mode="sum", per_sample_weights=...)`` over the (H*W, C) rows: vectorised over
channels and multi-threaded.

Same arithmetic as torchvision's kernel (``roi_align_common.h``): the sample positions, the clamping at the border,
the "outside [-1, size]" rule and the bilinear weights are computed in the features' dtype in the same order, so
they are bit-identical; the weights are divided by the sample count (a power of two here: exact) instead of the sum.
Only the order of the weighted additions differs (float rounding, ~1e-6 relative).

``ChannelsLastMultiScaleRoIAlign`` reuses private helpers of ``torchvision.ops.poolers`` (:data:`TORCHVISION_PRIVATES`)
and ``MultiScaleRoIAlign``'s attributes, checked against the pinned torchvision (:data:`TESTED_TORCHVISION`) by
tests/test_copies.py, which fails on another version until they are checked again.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

#: the torchvision version the private helpers below were checked against (constraints.txt pins it).
TESTED_TORCHVISION = "0.29.1"
#: the private names of ``torchvision.ops.poolers`` this module calls.
TORCHVISION_PRIVATES = ("_convert_to_roi_format", "_filter_input", "_setup_scales")


def _axis(start: torch.Tensor, bin_size: torch.Tensor, bins: int, grid: int, length: int):
    """Per roi, bin and sample along one axis: (low, high) neighbour indices and their weights, (R, bins, grid, 2)."""
    dtype = start.dtype
    p = torch.arange(bins, dtype=dtype).view(1, bins, 1)
    i = torch.arange(grid, dtype=dtype).view(1, 1, grid)
    b = bin_size.view(-1, 1, 1)
    pos = start.view(-1, 1, 1) + p * b + (i + 0.5) * b / grid
    inside = ((pos >= -1.0) & (pos <= length)).to(dtype)
    pos = pos.clamp(min=0)
    low = pos.long()
    top = low >= length - 1
    low = torch.where(top, torch.full_like(low, length - 1), low)
    high = torch.where(top, low, low + 1)
    pos = torch.where(top, low.to(dtype), pos)
    frac = pos - low
    return torch.stack([low, high], -1), torch.stack([(1 - frac) * inside, frac * inside], -1)


def roi_align_channels_last(features: torch.Tensor, rois: torch.Tensor, output_size: tuple[int, int],
                            spatial_scale: float, sampling_ratio: int) -> torch.Tensor:
    """``torchvision.ops.roi_align(features, rois, output_size, spatial_scale, sampling_ratio, aligned=False)``.

    ``features`` (N, C, H, W), best channels_last; ``rois`` (R, 5) ``[image index, x1, y1, x2, y2]``;
    ``sampling_ratio`` > 0 (torchvision's adaptive grid, ``<= 0``, is not handled here). Returns (R, C, *output_size).
    """
    if sampling_ratio <= 0:
        raise ValueError("roi_align_channels_last needs a fixed sampling_ratio > 0")
    n, c, height, width = features.shape
    ph, pw = output_size
    g = int(sampling_ratio)
    r = len(rois)
    if r == 0:
        return features.new_zeros((0, c, ph, pw))
    rois = rois.to(features.dtype)
    x1, y1, x2, y2 = (rois[:, j] * spatial_scale for j in range(1, 5))
    roi_w = torch.clamp(x2 - x1, min=1.0)
    roi_h = torch.clamp(y2 - y1, min=1.0)
    yi, wy = _axis(y1, roi_h / ph, ph, g, height)  # (R, ph, g, 2)
    xi, wx = _axis(x1, roi_w / pw, pw, g, width)  # (R, pw, g, 2)
    image = rois[:, 0].long().view(r, 1, 1, 1, 1, 1, 1)
    # one bag per output bin (R, ph, pw), its 4 * g * g entries in torchvision's order: sample (iy, ix), then the
    # neighbours (y_low, x_low), (y_low, x_high), (y_high, x_low), (y_high, x_high)
    index = (image * (height * width) + yi.view(r, ph, 1, g, 1, 2, 1) * width + xi.view(r, 1, pw, 1, g, 1, 2))
    weight = wy.view(r, ph, 1, g, 1, 2, 1) * wx.view(r, 1, pw, 1, g, 1, 2) / (g * g)
    rows = features.permute(0, 2, 3, 1).reshape(n * height * width, c)  # a view for channels_last features
    out = F.embedding_bag(index.reshape(r * ph * pw, -1), rows, per_sample_weights=weight.reshape(r * ph * pw, -1),
                          mode="sum")
    return out.view(r, ph, pw, c).permute(0, 3, 1, 2)


class ChannelsLastMultiScaleRoIAlign(nn.Module):
    """torchvision's ``MultiScaleRoIAlign`` (``inner``: its level mapping and scales) with
    ``roi_align_channels_last`` for the pooling; falls back to ``inner`` off the CPU or with an adaptive grid."""

    def __init__(self, inner: nn.Module):
        super().__init__()
        self.inner = inner

    def forward(self, x: dict, boxes: list, image_shapes: list) -> torch.Tensor:
        from torchvision.ops.poolers import _convert_to_roi_format, _filter_input, _setup_scales

        inner = self.inner
        x_filtered = _filter_input(x, inner.featmap_names)
        if inner.sampling_ratio <= 0 or any(v.device.type != "cpu" for v in x_filtered):
            return inner(x, boxes, image_shapes)
        if inner.scales is None or inner.map_levels is None:
            inner.scales, inner.map_levels = _setup_scales(x_filtered, image_shapes, inner.canonical_scale,
                                                           inner.canonical_level)
        rois = _convert_to_roi_format(boxes)
        size = tuple(inner.output_size)
        if len(x_filtered) == 1:
            return roi_align_channels_last(x_filtered[0], rois, size, inner.scales[0], inner.sampling_ratio)
        levels = inner.map_levels(boxes)
        result = torch.zeros((len(rois), x_filtered[0].shape[1], *size), dtype=x_filtered[0].dtype)
        for level, (feature, scale) in enumerate(zip(x_filtered, inner.scales)):
            idx = torch.where(levels == level)[0]
            if len(idx):
                result[idx] = roi_align_channels_last(feature, rois[idx], size, scale,
                                                      inner.sampling_ratio).to(result.dtype)
        return result


__all__ = ["roi_align_channels_last", "ChannelsLastMultiScaleRoIAlign", "TESTED_TORCHVISION", "TORCHVISION_PRIVATES"]
