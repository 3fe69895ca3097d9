"""The paper's mass CNN (Apicella et al., ICASSP 2022): network and input preprocessing (checkpoint files:
``massviz.io.checkpoint``).

Provenance: a reimplementation of ``Encoder/Models/CNN_encoder_pooling.py`` (network),
``Encoder/Models/DataExtractor.py`` (``SquarePad``) and ``demo/generate_video_inference.py`` (patch transform,
feature normalisation, denormalisation and clamping) of github.com/CORSMAL/Visual, MIT licence,
Copyright (c) 2021 CORSMAL. The layer names match the published state_dicts so those load strictly.

Faithful to the original:

- forward: ``pool(bn(relu(conv)))`` for four 3×3 convs (3→32→64→64→128) → 128×7×7 → flatten (6272) →
  ``bn5(relu(linear1))`` → ``relu(linear2)`` (6) → concat normalised ``[a, b, d]`` (9) → ``linear3`` → one value in
  normalised mass units;
- patch: PIL image → zero-pad to a square (extra pixel right/bottom) → torchvision ``Resize((112, 112), BILINEAR)``
  on the PIL image (antialiased) → ``ToTensor`` ([0, 1]). A different resize (e.g. ``cv2.resize``) changes
  predictions a lot, so only torchvision/PIL is used here;
- features ``(v - min) / (max - min)``; grams ``clamp(y * (maxMass - minMass) + minMass, min=0)``.

Deliberate differences: the model holds no preprocessing (``forward`` takes ready tensors;
``massviz.core.predictor.MassPredictor.predict`` does the rest); the normalisation ranges travel with the checkpoint
(:class:`Ranges`, see ``massviz.io.checkpoint.load_checkpoint``) instead of being constants edited in a script;
``MassPredictor.predict`` returns one prediction per patch (the original averages them per recording, which is the
pipeline's job here).
"""
from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image, ImageOps
from torch import nn

from massviz.errors import WeightsError

#: side of the square patch the network sees.
PATCH_SIZE = 112
#: number of trainable parameters of :class:`MassNet`.
N_PARAMETERS = 532_752
#: the names (and order) of the eight normalisation values, as the original code and golden_public.json spell them.
RANGE_KEYS = ("minAverageDistance", "maxAverageDistance", "minRatioWidth", "maxRatioWidth",
              "minRatioHeight", "maxRatioHeight", "minMass", "maxMass")


# ----------------------------------------------------------------------------------------------------------- ranges
@dataclass(frozen=True)
class Ranges:
    """Min-max normalisation ranges a checkpoint was trained with (distance in mm, ratios unitless, mass in g)."""

    min_distance: float
    max_distance: float
    min_ratio_width: float
    max_ratio_width: float
    min_ratio_height: float
    max_ratio_height: float
    min_mass: float
    max_mass: float

    def __post_init__(self) -> None:
        values = self.as_tuple()
        if not all(isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isfinite(v) for v in values):
            raise ValueError(f"Ranges: every value must be a finite number, got {values}")
        for f, v in zip(fields(self), values):
            object.__setattr__(self, f.name, float(v))
        values = self.as_tuple()
        for lo, hi in zip(values[0::2], values[1::2]):
            if not hi > lo:
                raise ValueError(f"Ranges: each max must exceed its min, got {values}")
            if not math.isfinite(hi - lo):
                raise ValueError(f"Ranges: each max - min must be a finite number, got {values}")

    def as_tuple(self) -> tuple[float, ...]:
        """The eight values in :data:`RANGE_KEYS` order."""
        return (self.min_distance, self.max_distance, self.min_ratio_width, self.max_ratio_width,
                self.min_ratio_height, self.max_ratio_height, self.min_mass, self.max_mass)

    def to_dict(self) -> dict[str, float]:
        """The original code's names (``minAverageDistance`` ... ``maxMass``), as in golden_public.json."""
        return dict(zip(RANGE_KEYS, (float(v) for v in self.as_tuple())))

    @classmethod
    def from_dict(cls, d: object, path: str | Path | None = None) -> "Ranges":
        """Parse the eight-key dict; anything else raises :class:`WeightsError` naming ``path``."""
        if not isinstance(d, dict) or set(d) != set(RANGE_KEYS):
            got = sorted(d) if isinstance(d, dict) else type(d).__name__
            raise WeightsError(f"ranges must have exactly the keys {', '.join(RANGE_KEYS)}; got {got}", path)
        try:
            return cls(*(d[k] for k in RANGE_KEYS))
        except ValueError as e:
            raise WeightsError(str(e), path) from None

    def normalise_features(self, features) -> np.ndarray:
        """Raw ``[a, b, d_mm]`` rows (N, 3) → float32 (N, 3), each ``(v - min) / (max - min)`` (not clipped)."""
        f = np.asarray(features, dtype=np.float64)
        if f.size == 0:
            f = f.reshape(0, 3)
        if f.ndim != 2 or f.shape[1] != 3:
            raise ValueError(f"features must have shape (N, 3) [a, b, d_mm], got {f.shape}")
        lo = np.array([self.min_ratio_width, self.min_ratio_height, self.min_distance])
        hi = np.array([self.max_ratio_width, self.max_ratio_height, self.max_distance])
        return ((f - lo) / (hi - lo)).astype(np.float32)

    def normalise_features_tensor(self, features: torch.Tensor) -> torch.Tensor:
        """:meth:`normalise_features` on a float64 (N, 3) tensor, on its device: the same float64 arithmetic, then
        float32 (bit-identical to the numpy version)."""
        lo = torch.tensor([self.min_ratio_width, self.min_ratio_height, self.min_distance], dtype=torch.float64,
                          device=features.device)
        hi = torch.tensor([self.max_ratio_width, self.max_ratio_height, self.max_distance], dtype=torch.float64,
                          device=features.device)
        return ((features.double() - lo) / (hi - lo)).float()

    def denormalise_mass(self, y) -> np.ndarray:
        """Network output (normalised) → grams, float32, clamped at 0 as the original does."""
        y = np.asarray(y, dtype=np.float32)
        grams = y * np.float32(self.max_mass - self.min_mass) + np.float32(self.min_mass)
        return np.maximum(grams, np.float32(0.0))


# ---------------------------------------------------------------------------------------------------- preprocessing
# The original's transform is torchvision's ``Compose([SquarePad, Resize((112, 112), BILINEAR), ToTensor()])`` on a PIL
# image; on PIL images those are Pillow's ``ImageOps.expand``, ``Image.resize`` and a uint8 → float /255. They are
# called here on Pillow directly: importing torchvision (its ``ops`` import ``torch._dynamo``) took 2.2 of a
# ``massviz`` command's 4.7 s start-up. ``tests/test_model.py`` holds them bit-equal to torchvision's transforms.
def square_pad(img: Image.Image) -> Image.Image:
    """Zero-pad a PIL image to a square, centred; the odd pixel goes right/bottom (the original's ``SquarePad``)."""
    w, h = img.size
    side = max(w, h)
    left, top = (side - w) // 2, (side - h) // 2
    return ImageOps.expand(img, border=(left, top, side - w - left, side - h - top), fill=0)


def preprocess_patch(rgb: np.ndarray) -> torch.Tensor:
    """H×W×3 uint8 RGB crop → float32 tensor 3×112×112 in [0, 1], exactly as the original transform."""
    rgb = np.asarray(rgb)
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.shape[0] == 0 or rgb.shape[1] == 0:
        raise ValueError(f"patch must be a non-empty H×W×3 uint8 RGB array, got {rgb.dtype} {rgb.shape}")
    img = square_pad(Image.fromarray(np.ascontiguousarray(rgb))).resize((PATCH_SIZE, PATCH_SIZE),
                                                                        Image.Resampling.BILINEAR)
    return torch.from_numpy(np.array(img, np.uint8)).permute(2, 0, 1).contiguous().float().div(255)


def preprocess_patches(patches: Sequence[np.ndarray]) -> torch.Tensor:
    """A list of RGB crops → N×3×112×112 float32 tensor (0×3×112×112 for an empty list)."""
    if len(patches) == 0:
        return torch.empty(0, 3, PATCH_SIZE, PATCH_SIZE)
    return torch.stack([preprocess_patch(p) for p in patches])


# ---------------------------------------------------------------------------------------------------------- network
class MassNet(nn.Module):
    """The paper's mass CNN, layers and forward only: ``forward(images N×3×112×112, features N×3 normalised) → N×1
    normalised mass``. Predictions from patches and raw features (normalisation ranges, batching, device, threads,
    precision) are ``massviz.core.predictor.MassPredictor``'s; ``massviz.io.checkpoint.load_checkpoint`` returns one
    holding this network."""

    def __init__(self):
        super().__init__()
        self.conv1 = nn.Conv2d(3, 32, kernel_size=3, padding=1, stride=1)
        self.bn1 = nn.BatchNorm2d(32)
        self.conv2 = nn.Conv2d(32, 64, kernel_size=3, padding=1, stride=1)
        self.bn2 = nn.BatchNorm2d(64)
        self.conv3 = nn.Conv2d(64, 64, kernel_size=3, padding=1, stride=1)
        self.bn3 = nn.BatchNorm2d(64)
        self.conv4 = nn.Conv2d(64, 128, kernel_size=3, padding=1, stride=1)
        self.bn4 = nn.BatchNorm2d(128)
        self.linear1 = nn.Linear(128 * 7 * 7, 64)
        self.bn5 = nn.BatchNorm1d(64)
        self.linear2 = nn.Linear(64, 6)
        self.linear3 = nn.Linear(6 + 3, 1)
        self.pool = nn.MaxPool2d((2, 2))

    def _blocks(self):
        return ((self.conv1, self.bn1), (self.conv2, self.bn2), (self.conv3, self.bn3), (self.conv4, self.bn4))

    def forward(self, images: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        x = images
        for conv, bn in self._blocks():
            x = self.pool(bn(F.relu(conv(x))))
        return self.head(x, features)

    def head(self, x: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        """The linear layers on the pooled maps ``x`` (N×128×7×7) and the normalised features (N×3)."""
        x = self.bn5(F.relu(self.linear1(x.flatten(1))))
        x = F.relu(self.linear2(x))
        return self.linear3(torch.cat((x, features), dim=1))

    def forward_eval(self, images: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        """``forward`` in eval mode, bit for bit, with ReLU and BatchNorm on the pooled maps (a quarter of the data).

        In eval mode a block's ``bn(relu(v))`` is, per channel, a monotone function of v: non-decreasing where the
        norm's weight is >= 0, non-increasing where it is < 0 (floating-point rounding is monotone too). So the 2x2
        max of it is that function of the max of v, or of the min of v. The min comes from the max of the
        convolution with that channel's weights and bias negated (exact: negation commutes with rounding), so
        ``pool(bn(relu(conv(x))))`` = ``bn(relu(s * pool(conv_s(x))))`` with s = ±1 per channel: the same numbers.
        Only valid with the norms' running statistics (not in training mode, where they come from the batch).
        """
        return self.head(self.trunk_eval(images), features)

    def trunk_eval(self, images: torch.Tensor) -> torch.Tensor:
        """The convolution blocks of ``forward_eval``: the pooled maps (N×128×7×7) :meth:`head` reads."""
        if self.training:
            raise RuntimeError("MassNet.forward_eval needs eval mode (BatchNorm running statistics)")
        x = images
        for conv, bn in self._blocks():
            s = torch.where(bn.weight < 0, -1.0, 1.0).to(conv.weight.dtype)
            w = conv.weight * s.view(-1, 1, 1, 1)
            if conv.weight.is_contiguous(memory_format=torch.channels_last):
                w = w.contiguous(memory_format=torch.channels_last)
            v = self.pool(F.conv2d(x, w, conv.bias * s, conv.stride, conv.padding))
            x = bn(F.relu_(v.mul_(s.view(1, -1, 1, 1).to(v.dtype))))  # ±1: exact in any dtype
        return x


__all__ = ["PATCH_SIZE", "N_PARAMETERS", "RANGE_KEYS", "Ranges", "square_pad", "preprocess_patch",
           "preprocess_patches", "MassNet"]
