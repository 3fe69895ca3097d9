"""``massviz.core.predictor.MassPredictor``: the mass CNN's policy (ranges, calls, device, threads, precision) beside a
network that is only layers and forward (``massviz.core.model.MassNet``)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from massviz.core.model import MassNet
from massviz.core.predictor import MassPredictor


@pytest.fixture(scope="module")
def model(weights):
    from massviz.io.checkpoint import load_checkpoint

    return load_checkpoint(weights)


def test_the_network_is_a_plain_module_and_the_checkpoint_gives_a_predictor(model):
    net = MassNet()
    assert isinstance(net, torch.nn.Module) and not isinstance(model, torch.nn.Module)
    for name in ("ranges", "weights_id", "precision", "predict", "predict_groups", "set_precision"):
        assert not hasattr(net, name), name
    assert isinstance(model.net, MassNet) and model.ranges is not None and len(model.weights_id) == 12
    assert model.device == torch.device("cpu") and model.to("cpu") is model
    import massviz as mv

    assert mv.MassNet is MassNet and mv.MassPredictor is MassPredictor


def test_precision_names_the_weights_it_predicts_with():
    p = MassPredictor(MassNet(), weights_id="0123456789ab")
    assert p.set_precision("bf16") is p and (p.precision, p.weights_id) == ("bf16", "0123456789ab+bf16")
    assert p.set_precision("bf16").weights_id == "0123456789ab+bf16"  # not appended twice
    assert p.set_precision("fp16").weights_id == "0123456789ab" and p.precision == "fp32"  # fp16: the CNN stays fp32
    assert MassPredictor(MassNet(), precision="bf16").weights_id is None
    with pytest.raises(ValueError, match="fp32, bf16, fp16"):
        p.set_precision("fp64")


def test_predictions_run_with_the_predictors_threads_and_restore_torchs(model, monkeypatch):
    seen = []
    hook = model.net.linear1.register_forward_hook(lambda *a: seen.append(torch.get_num_threads()))
    before = torch.get_num_threads()
    patches = [np.full((20, 30, 3), 90, np.uint8)] * 3
    feats = np.array([[0.1, 0.2, 600.0]] * 3)
    try:
        monkeypatch.delenv("MASSVIZ_MODEL_THREADS", raising=False)
        model.predict(patches, feats)
        monkeypatch.setenv("MASSVIZ_MODEL_THREADS", "2")
        model.predict(patches, feats)
        model.threads = 3  # the predictor's own setting wins over the environment
        model.predict(patches, feats)
    finally:
        model.threads = None
        hook.remove()
    assert seen == [1, 2, 3] and torch.get_num_threads() == before


@pytest.mark.slow
def test_predict_boxes_is_the_device_kernels_prediction_of_the_crops(model):
    """On the CPU the device kernels' patches are Pillow's bytes exactly; the network's calls differ in size
    (128 padded rows against 16), so the grams agree within float rounding."""
    from massviz.core.patches import crop

    rng = np.random.default_rng(2)
    rgb = rng.integers(0, 256, (240, 320, 3), dtype=np.uint8)
    xy = rng.integers(0, 200, (7, 2))
    boxes = np.concatenate([xy, xy + rng.integers(5, 100, (7, 2))], axis=1).clip(max=[320, 240, 320, 240])
    feats = np.stack([rng.uniform(0.05, 0.3, 7), rng.uniform(0.05, 0.3, 7), rng.uniform(300, 900, 7)], axis=1)
    got = model.predict_boxes(rgb, boxes, feats)
    want = model.predict([crop(rgb, b) for b in boxes], feats)
    assert got.dtype == np.float32 and got.shape == (7,)
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4)
    assert model.predict_boxes(rgb, np.zeros((0, 4), np.int64), np.zeros((0, 3))).shape == (0,)
    with pytest.raises(ValueError, match="boxes but"):
        model.predict_boxes(rgb, boxes, feats[:3])
