"""``massviz.core.pipeline.repredict``: predictions recomputed for another model on a trace's detections are
computed as a run of that model computes them (its kernels, inside the run's faithful settings), and the trace
records it."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from massviz.core.pipeline import repredict, run
from massviz.detect import make_detector


@pytest.fixture(scope="module")
def recording(samples_dir):
    from massviz.io.recording import open_recording

    return open_recording(samples_dir / "cup_handover")


@pytest.fixture(scope="module")
def models(weights):
    """The 158 weights (the run's) and the fold-0 weights (another model to re-predict with)."""
    from massviz.io.checkpoint import load_checkpoint

    return load_checkpoint(weights), load_checkpoint(weights.with_name("Encoder_pool_aug_fold0_94.torch"))


def depth():
    return make_detector("depth", 0.4, quiet=True)


@pytest.mark.parametrize("kernels", ["exact", pytest.param("device", marks=pytest.mark.slow)])
def test_repredict_equals_a_run_of_the_other_model_with_the_same_kernels(recording, models, kernels):
    """Bit for bit, with either kernels (the device kernels on the CPU: the code CUDA runs)."""
    model, other = models
    first = run(recording, depth(), model, k=5, stride=9, prefetch=0, kernels=kernels)
    direct = run(recording, depth(), other, k=5, stride=9, prefetch=0, kernels=kernels)
    again = repredict(first, recording, other, kernels=kernels)
    assert np.isfinite(direct.detections.pred).sum() >= 3
    assert np.array_equal(again.detections.pred, direct.detections.pred, equal_nan=True)
    assert again.estimate == direct.estimate and again.weights_id == other.weights_id
    c = again.compute
    assert (c["predict_device"], c["predict_kernels"], c["predict_precision"], c["predict_mode"]) == (
        "cpu", kernels, "fp32", "faithful")
    assert c["mode"] == "faithful" and c["kernels"] == kernels  # the detections' own record stays


def test_a_repredicted_trace_is_saved_and_read_back_with_its_record(recording, models, tmp_path):
    from massviz.io.trace_file import load_trace, save_trace

    model, other = models
    again = repredict(run(recording, depth(), model, k=5, stride=9, prefetch=0), recording, other)
    back = load_trace(save_trace(again, tmp_path / "t.npz"))
    assert back.compute == again.compute and "predict_kernels" in back.compute


def test_the_mode_is_faithful_only_when_detections_and_predictions_both_are(recording, models):
    model, other = models
    trace = run(recording, depth(), model, k=5, stride=9, prefetch=0)

    class Fp16:  # a run in --precision fp16 (its detector's), the mass CNN staying fp32
        precision = "fp16"

    fast = repredict(trace, recording, other, detector=Fp16())
    assert fast.compute["predict_mode"] == "fast" and fast.compute["mode"] == "fast"
    assert fast.compute["predict_precision"] == "fp16"
    fast_detections = dataclasses.replace(trace, compute={**trace.compute, "mode": "fast"})
    assert repredict(fast_detections, recording, other).compute["mode"] == "fast"
    old = dataclasses.replace(trace, compute={})  # a trace made before massviz recorded it
    assert set(repredict(old, recording, other).compute) == {"predict_device", "predict_kernels",
                                                             "predict_precision", "predict_mode"}


class CudaModel:
    """Wraps a real model, says it is on CUDA (it computes on the CPU) and records the flags of each prediction."""

    device = torch.device("cuda")
    precision = "fp32"

    def __init__(self, model):
        self.model, self.weights_id, self.seen = model, "cuda-" + model.weights_id, []

    def predict(self, patches, features):
        from massviz.core.device import faithful_users

        self.seen.append((faithful_users(), torch.backends.cudnn.deterministic))
        return self.model.predict(patches, features)


def test_repredict_on_cuda_runs_inside_the_faithful_settings(recording, models, monkeypatch):
    import massviz.core.device as device

    model, other = models
    monkeypatch.setattr(device, "describe", lambda d: f"{torch.device(d)} (stand-in)")
    trace = run(recording, depth(), model, k=5, stride=9, prefetch=0)
    wrapped = CudaModel(other)
    was = torch.backends.cudnn.deterministic
    again = repredict(trace, recording, wrapped, kernels="exact")
    assert wrapped.seen and all(users == 1 and det is True for users, det in wrapped.seen)
    assert torch.backends.cudnn.deterministic == was and device.faithful_users() == 0
    assert again.compute["predict_device"] == "cuda (stand-in)" and again.compute["mode"] == "faithful"
