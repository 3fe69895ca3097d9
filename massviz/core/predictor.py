"""Mass predictions from the paper's CNN: the network (``massviz.core.model.MassNet``, layers only) with what turns
patches and raw features into grams: the checkpoint's normalisation ranges, the calls (batching), the device, the
torch threads and the precision.

``massviz.io.checkpoint.load_checkpoint`` returns a :class:`MassPredictor`; the pipeline's stage calls it
(``predict_groups`` on the CPU, ``predict_normalised`` on the device path).
"""
from __future__ import annotations

import os
from typing import Sequence

import numpy as np
import torch

from massviz.core.model import MassNet, Ranges, preprocess_patches
from massviz.core.types import PRECISIONS
from massviz.errors import WeightsError

#: rows of every mass CNN call of :meth:`MassPredictor.predict_normalised` (the device path), the last call padded:
#: a patch's prediction then never depends on how many patches share its call.
DEVICE_CALL_ROWS = 128

#: torch intra-op threads for :meth:`MassPredictor.predict` (0: leave torch's setting). One thread: a call of 6-16
#: patches is too small to share between threads, and a second thread competes with the detector and the reader for
#: the cores (``benchmarks/model_threads.py`` compares 1 and 2 on a machine); predictions move by < 2e-5 g.
#: Environment ``MASSVIZ_MODEL_THREADS`` overrides it.
MODEL_THREADS = 1


def model_threads() -> int:
    """The intra-op threads a prediction runs with: ``MASSVIZ_MODEL_THREADS`` when set, else :data:`MODEL_THREADS`."""
    value = os.environ.get("MASSVIZ_MODEL_THREADS", "")
    return int(value) if value.isdigit() else MODEL_THREADS


class MassPredictor:
    """The mass CNN's predictions: ``net`` (a :class:`MassNet`) and the policy around it.

    ``ranges``: the checkpoint's normalisation ranges (:class:`Ranges`; needed to predict); ``weights_id``: the
    first 12 hex characters of the checkpoint file's sha256 (a cache key; ``+bf16`` appended in bf16, so such
    predictions never pass for fp32 ones in the trace cache); ``precision``: ``"fp32"`` or ``"bf16"``
    (:meth:`set_precision`); ``threads``: torch intra-op threads of :meth:`predict` (None: :func:`model_threads`
    at each call; 0: leave torch's setting); ``checkpoint_path``: the file, named by errors. The device is the
    network's (:meth:`to`). Predictions run in eval mode; the network's training flag is restored after each.
    """

    def __init__(self, net: MassNet, ranges: Ranges | None = None, weights_id: str | None = None, *,
                 precision: str = "fp32", threads: int | None = None, checkpoint_path: str | None = None):
        self.net, self.ranges, self.threads, self.checkpoint_path = net, ranges, threads, checkpoint_path
        self._weights_id = None if weights_id is None else weights_id.split("+")[0]
        self.precision = "fp32"
        self.set_precision(precision)

    def __repr__(self) -> str:
        return (f"MassPredictor(weights_id={self.weights_id!r}, precision={self.precision!r}, "
                f"device={str(self.device)!r})")

    @property
    def weights_id(self) -> str | None:
        """The checkpoint's id, ``+bf16`` appended in bf16 (None for a network that came from no file)."""
        if self._weights_id is None:
            return None
        return self._weights_id + ("+bf16" if self.precision == "bf16" else "")

    @property
    def device(self) -> torch.device:
        """Where the network's parameters are."""
        return next(self.net.parameters()).device

    def to(self, device) -> "MassPredictor":
        """The network moved to ``device``; returns ``self``."""
        self.net.to(device)
        return self

    def set_precision(self, precision: str) -> "MassPredictor":
        """``"fp32"`` (default) or ``"bf16"`` (bf16 autocast: CPUs with bfloat16 support or CUDA; the caller
        checks, as ``massviz.detect.maskrcnn.check_precision`` does). ``"fp16"`` keeps the mass CNN in fp32: it runs
        on the CPU, where fp16 is not a fast format. Returns ``self``."""
        if precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {', '.join(PRECISIONS)}, got {precision!r}")
        self.precision = "bf16" if precision == "bf16" else "fp32"
        return self

    def _autocast(self, device: torch.device):
        return torch.autocast(device.type, dtype=torch.bfloat16, enabled=self.precision == "bf16")

    @torch.no_grad()
    def pooled_features(self, patches: Sequence[np.ndarray], rows: int = 64) -> np.ndarray:
        """The pooled maps the head reads (128×7×7, flattened: float32, shape (N, 6272)) of N RGB crops, in eval
        mode: the network's own description of what a patch looks like (the patch map's embedding). Calls of
        ``rows`` patches."""
        net = self.net
        was_training = net.training
        net.eval()
        device = self.device
        out = []
        try:
            for start in range(0, len(patches), rows):
                x = preprocess_patches(patches[start:start + rows]).to(device)
                out.append(net.trunk_eval(x).flatten(1).float().cpu().numpy())
        finally:
            net.train(was_training)
        return np.concatenate(out) if out else np.zeros((0, 128 * 7 * 7), np.float32)

    @torch.no_grad()
    def predict_normalised(self, images: torch.Tensor, features: torch.Tensor,
                           rows: int = DEVICE_CALL_ROWS) -> torch.Tensor:
        """The network's outputs (normalised mass, float32, shape (N,), on the network's device) for inputs already
        there: ``images`` (N, 3, 112, 112) float32 in [0, 1] (``massviz.core.resample.resize_boxes``), ``features``
        (N, 3) normalised (``Ranges.normalise_features_tensor``). Every call has exactly ``rows`` rows, the last one
        padded with zeros, so a patch's output does not depend on how many patches share its call (on a GPU the
        kernels are chosen by the call's shape). Nothing is copied to the host: ``Ranges.denormalise_mass`` of the
        result gives grams."""
        net = self.net
        n = len(images)
        device = self.device
        out = torch.empty(n, dtype=torch.float32, device=device)
        if n == 0:
            return out
        was_training = net.training
        net.eval()
        net.to(memory_format=torch.channels_last)
        try:
            for start in range(0, n, rows):
                x = images[start:start + rows]
                f = features[start:start + rows]
                if len(x) < rows:  # pad to the fixed call size
                    x = torch.cat([x, x.new_zeros((rows - len(x), *x.shape[1:]))])
                    f = torch.cat([f, f.new_zeros((rows - len(f), f.shape[1]))])
                x = x.to(device).contiguous(memory_format=torch.channels_last)
                with self._autocast(device):
                    y = net.head(net.trunk_eval(x), f.to(device))
                out[start:start + rows] = y[:min(rows, n - start), 0].float()
        finally:
            net.train(was_training)
        return out

    @torch.no_grad()
    def predict_boxes(self, rgb: np.ndarray, xyxy: np.ndarray, features) -> np.ndarray:
        """Grams (float32, shape (N,)) for N non-empty boxes of one H×W×3 uint8 frame and their raw
        ``[a, b, d_mm]`` features, computed as the stage's device kernels compute them: the frame copied to the
        network's device, each patch cut and resized there (``massviz.core.resample.resize_boxes``, Pillow's bytes
        exactly), the network in calls of :data:`DEVICE_CALL_ROWS` (:meth:`predict_normalised`)."""
        from massviz.core.device import upload
        from massviz.core.resample import resize_boxes

        self._check_ranges()
        xyxy = np.asarray(xyxy).reshape(-1, 4)
        feats = np.asarray(features, dtype=np.float64).reshape(-1, 3)
        if len(xyxy) != len(feats):
            raise ValueError(f"{len(xyxy)} boxes but {len(feats)} feature rows")
        if len(xyxy) == 0:
            return np.zeros(0, dtype=np.float32)
        device = self.device
        images = resize_boxes(upload([rgb], device), np.zeros(len(xyxy), np.int64), xyxy)
        y = self.predict_normalised(images, self.ranges.normalise_features_tensor(torch.from_numpy(feats).to(device)))
        return self.ranges.denormalise_mass(y.cpu().numpy())

    @torch.no_grad()
    def predict(self, patches: Sequence[np.ndarray], features, batch_size: int = 16) -> np.ndarray:
        """Grams (float32, shape (N,)) for N RGB crops (H×W×3 uint8) and their raw ``[a, b, d_mm]`` features."""
        return self.predict_groups([(patches, features)], batch_size)[0]

    def _check_ranges(self) -> None:
        if self.ranges is None:
            raise WeightsError("MassPredictor needs normalisation ranges to predict (load with "
                               "massviz.io.checkpoint.load_checkpoint)", self.checkpoint_path)

    @torch.no_grad()
    def predict_groups(self, groups: Sequence[tuple[Sequence[np.ndarray], np.ndarray]],
                       batch_size: int = 16) -> list[np.ndarray]:
        """``[predict(patches, features) for patches, features in groups]`` (e.g. one group per frame), bit for bit,
        with the convolutions of every group's patches run together, ``batch_size`` rows a call.

        Bit for bit because a row of the convolution blocks does not depend on the other rows of its call as long as
        the call has two rows or more (oneDNN's CPU kernels, fp32 and bf16, 1 and 2 threads: rows computed with
        2 ... 96 others are equal; a call of ONE row takes another kernel and differs by ~2e-6). So a
        patch ``predict`` would send alone (a group's last call of one row) is sent alone here too; the others go in
        calls of ``batch_size`` (never leaving one row alone); the head (linear layers, whose rows do depend on the
        call's size) then runs on each group's own calls of ``batch_size``, exactly as ``predict`` calls it."""
        self._check_ranges()
        feats, spans = [], []
        for patches, features in groups:
            f = self.ranges.normalise_features(features)
            if len(patches) != len(f):
                raise ValueError(f"{len(patches)} patches but {len(f)} feature rows")
            feats.append(f)
            # predict's calls: rows [i, i + batch_size) of this group
            spans.append([(i, min(i + batch_size, len(f))) for i in range(0, len(f), batch_size)])
        if not any(len(f) for f in feats):
            return [np.zeros(0, dtype=np.float32) for _ in groups]
        net = self.net
        was_training = net.training
        net.eval()
        device = self.device
        # channels_last: the same arithmetic in another order, ~1.5x faster on a CPU (max-pooling most of all);
        # trunk_eval: the same numbers as forward with ReLU/BatchNorm on a quarter of the data; batches of 16
        # stay in the caches (~1.6x faster than 64 on a 2-core CPU; the batch size moves predictions by ~1e-4 g)
        net.to(memory_format=torch.channels_last)
        threads = torch.get_num_threads()
        wanted = model_threads() if self.threads is None else self.threads
        if wanted and wanted != threads:
            torch.set_num_threads(wanted)  # the detector keeps its own (restored below)

        def images(rows):
            batch = preprocess_patches([groups[g][0][r] for g, r in rows]).to(device)
            return batch.contiguous(memory_format=torch.channels_last)

        try:
            alone = [(g, a) for g, sp in enumerate(spans) for a, b in sp if b - a == 1]
            together = [(g, r) for g, sp in enumerate(spans) for a, b in sp if b - a > 1 for r in range(a, b)]
            maps = {}
            for rows in [[row] for row in alone] + _calls(together, batch_size):
                x = images(rows)
                with self._autocast(device):
                    for row, m in zip(rows, net.trunk_eval(x)):
                        maps[row] = m
            out = []
            for g, sp in enumerate(spans):
                parts = []
                for a, b in sp:
                    x = torch.stack([maps[(g, r)] for r in range(a, b)])
                    with self._autocast(device):
                        y = net.head(x, torch.from_numpy(feats[g][a:b]).to(device))
                    parts.append(y[:, 0].float().cpu().numpy())
                out.append(self.ranges.denormalise_mass(np.concatenate(parts)) if parts else
                           np.zeros(0, dtype=np.float32))
        finally:
            net.train(was_training)
            if torch.get_num_threads() != threads:
                torch.set_num_threads(threads)
        return out


def _calls(rows: list, size: int) -> list[list]:
    """``rows`` cut into calls of ``size`` rows, the last one taking a lone last row (never a call of one row)."""
    calls = [rows[i:i + size] for i in range(0, len(rows), size)]
    if len(calls) > 1 and len(calls[-1]) == 1:
        lone = calls.pop()
        calls[-1] = calls[-1] + lone
    return calls


__all__ = ["DEVICE_CALL_ROWS", "MODEL_THREADS", "MassPredictor", "model_threads"]
