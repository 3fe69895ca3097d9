"""One copy of each small thing: the shared helpers equal the library calls they stand for."""
from __future__ import annotations

import numpy as np
import pytest
import torch


def test_box_iou_equals_torchvisions_box_iou_in_float64():
    from torchvision.ops import box_iou as tv_box_iou

    from massviz.core.tracks import box_iou

    rng = np.random.default_rng(0)
    boxes = rng.integers(0, 50, (200, 4)).astype(np.float64)
    boxes[:, 2:] = boxes[:, :2] + rng.integers(0, 20, (200, 2))  # some empty boxes too
    expected = torch.nan_to_num(tv_box_iou(torch.from_numpy(boxes[:20]), torch.from_numpy(boxes)), nan=0.0).numpy()
    got = box_iou(boxes[:20], boxes)
    assert got.shape == (20, 200) and got.dtype == np.float64
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12)
    assert (got == 0).any() and (got == 1).any() and ((got > 0) & (got < 1)).any()
    np.testing.assert_array_equal(box_iou(boxes[3], boxes), got[3:4])  # one box against many
    assert box_iou(boxes[:0], boxes).shape == (0, 200)


def test_box_iou_is_the_one_copy():
    import massviz.core.tracks as tracks
    import massviz.evaluation.compare as compare
    import massviz.evaluation.failures as failures

    assert compare.box_iou is tracks.box_iou and failures.box_iou is tracks.box_iou


def test_one_precision_list():
    import argparse

    import massviz.app as app
    import massviz.detect.maskrcnn as maskrcnn
    from massviz.commands._common import add_pipeline_args
    from massviz.core.model import MassNet
    from massviz.core.predictor import MassPredictor
    from massviz.core.types import PRECISIONS

    assert PRECISIONS[0] == "fp32" and app.PRECISIONS is PRECISIONS and maskrcnn.PRECISIONS is PRECISIONS
    p = argparse.ArgumentParser()
    add_pipeline_args(p)
    (action,) = [a for a in p._actions if a.dest == "precision"]
    assert tuple(action.choices) == PRECISIONS and action.default == "fp32"
    with pytest.raises(ValueError, match="fp32, bf16, fp16"):
        MassPredictor(MassNet()).set_precision("fp64")


def test_png_header_size_is_the_one_png_header_reader(tmp_path):
    import struct

    import cv2

    import massviz.io.untrusted as untrusted

    buf = cv2.imencode(".png", np.zeros((7, 13, 3), np.uint8))[1].tobytes()
    assert untrusted.png_header_size(buf[:24]) == (13, 7)
    assert untrusted.png_header_size(buf[:23]) is None and untrusted.png_header_size(b"\0" * 24) is None
    big = buf[:16] + struct.pack(">II", 70000, 3) + buf[24:]
    assert untrusted.png_header_size(big) == (70000, 3)
    assert untrusted.image_header_size("x.png", big) == (70000, 3)  # header only, never decoded
    path = tmp_path / "a.png"
    path.write_bytes(buf)
    assert untrusted.image_header_size(path) == (13, 7)
    # the trace file's patch check reads headers through it (no second parser)
    import inspect

    import massviz.io.trace_file as trace_file

    assert "png_header_size" in inspect.getsource(trace_file.check_trace_arrays)
    assert b"IHDR" not in inspect.getsource(trace_file).encode()


def test_file_hasher_memo_is_written_through_atomic_path(tmp_path, monkeypatch):
    import json
    import os

    import massviz.io.filehash as filehash

    data = tmp_path / "a.bin"
    data.write_bytes(b"abc")
    store = tmp_path / "hashes"
    (digest,) = filehash.FileHasher(store).digests([data], "rec")
    assert digest == filehash.file_digest(data)
    (memo,) = store.iterdir()  # one memo file, no temporary left beside it
    assert json.loads(memo.read_text())[os.path.abspath(data)][1] == digest
    assert filehash.FileHasher(store).digests([data], "rec") == [digest]

    def fail(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(filehash.json, "dumps", fail)  # the memo cannot be written: ignored, nothing half-written
    data.write_bytes(b"abcd")
    assert filehash.FileHasher(store).digests([data], "rec") == [filehash.file_digest(data)]
    assert list(store.iterdir()) == [memo] and json.loads(memo.read_text())[os.path.abspath(data)][1] == digest
    assert "atomic_path" in filehash.write_memo.__code__.co_names


def test_fold_batchnorm_is_torchs_fuse_conv_bn_weights():
    from torchvision.ops.misc import FrozenBatchNorm2d

    from massviz.detect.maskrcnn import fold_batchnorm

    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Conv2d(3, 8, 3, padding=1, bias=False), FrozenBatchNorm2d(8), torch.nn.ReLU(),
                              torch.nn.Conv2d(8, 4, 3, padding=1, bias=False), torch.nn.BatchNorm2d(4),
                              torch.nn.Conv2d(4, 4, 1), torch.nn.BatchNorm2d(4)).eval()  # last conv has a bias: kept
    for bn in (net[1], net[4], net[6]):
        bn.running_mean.uniform_(-0.5, 0.5)
        bn.running_var.uniform_(0.5, 2.0)
        bn.weight.data.uniform_(-1.5, 1.5)
        bn.bias.data.uniform_(-0.2, 0.2)
    expected_conv = torch.nn.utils.fuse_conv_bn_eval(net[3], net[4])
    x = torch.rand(2, 3, 16, 16)
    with torch.no_grad():
        expected = net(x)
        assert fold_batchnorm(net) == 2
        got = net(x)
    assert [type(m).__name__ for m in net] == ["Conv2d", "Identity", "ReLU", "Conv2d", "Identity", "Conv2d",
                                               "BatchNorm2d"]
    assert torch.equal(net[3].weight, expected_conv.weight) and torch.equal(net[3].bias, expected_conv.bias)
    assert not net[3].weight.requires_grad and net[3].weight.device.type == "cpu"
    torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-5)


def test_roialign_torchvision_privates_are_those_of_the_pinned_version():
    """roialign.py calls private torchvision helpers: another torchvision must fail here, loudly, until re-checked."""
    import inspect
    import re
    from pathlib import Path

    import torchvision
    from torchvision.ops import poolers

    import massviz.detect.roialign as roialign

    constraints = (Path(__file__).parents[1] / "constraints.txt").read_text()  # the tested pins
    assert f"torchvision=={roialign.TESTED_TORCHVISION}\n" in constraints
    assert torchvision.__version__.split("+")[0] == roialign.TESTED_TORCHVISION, (
        f"torchvision {torchvision.__version__} is not {roialign.TESTED_TORCHVISION}: re-check the private helpers "
        f"massviz/detect/roialign.py uses ({', '.join(roialign.TORCHVISION_PRIVATES)}) and MultiScaleRoIAlign's "
        "attributes, then update TESTED_TORCHVISION")
    source = inspect.getsource(roialign)
    used = set(re.findall(r"from torchvision\.ops\.poolers import ([\w, ]+)", source)[0].replace(" ", "").split(","))
    assert used == set(roialign.TORCHVISION_PRIVATES)
    for name in roialign.TORCHVISION_PRIVATES:
        assert callable(getattr(poolers, name, None)), f"torchvision.ops.poolers.{name} is gone"
    pool = poolers.MultiScaleRoIAlign(["0", "1"], 7, 2)
    for attr in ("featmap_names", "sampling_ratio", "output_size", "scales", "map_levels", "canonical_scale",
                 "canonical_level"):
        assert hasattr(pool, attr), f"MultiScaleRoIAlign has no {attr}"
    assert list(inspect.signature(poolers._setup_scales).parameters) == ["features", "image_shapes", "canonical_scale",
                                                                          "canonical_level"]


@pytest.fixture(scope="module")
def random_maskrcnn():
    from massviz.detect.maskrcnn import build_model

    return build_model(0.4, pretrained=False)


def test_class_filter_is_a_roiheads_subclass_with_torchvisions_settings(random_maskrcnn):
    from torchvision.models.detection import maskrcnn_resnet50_fpn
    from torchvision.models.detection.roi_heads import RoIHeads

    from massviz.detect.maskrcnn import ClassFilterRoIHeads

    heads = random_maskrcnn.roi_heads
    assert type(heads) is ClassFilterRoIHeads and isinstance(heads, RoIHeads)
    assert "postprocess_detections" not in vars(heads)  # no instance patch
    stock = maskrcnn_resnet50_fpn(weights=None, weights_backbone=None, num_classes=91, box_score_thresh=0.4).roi_heads
    for get in (lambda h: h.proposal_matcher.high_threshold, lambda h: h.proposal_matcher.low_threshold,
                lambda h: h.proposal_matcher.allow_low_quality_matches, lambda h: h.fg_bg_sampler.batch_size_per_image,
                lambda h: h.fg_bg_sampler.positive_fraction, lambda h: h.box_coder.weights,
                lambda h: h.box_coder.bbox_xform_clip, lambda h: h.score_thresh, lambda h: h.nms_thresh,
                lambda h: h.detections_per_img, lambda h: h.has_mask(), lambda h: h.has_keypoint(),
                lambda h: h.training):
        assert get(heads) == get(stock.eval())
    assert heads.state_dict().keys() == stock.state_dict().keys()  # keep_classes is not saved
    assert heads.keep_classes.tolist() == [44, 46, 47, 84]
    # one proposal scoring 0.45 as a person (1) and as a cup (47): torchvision keeps both, the subclass the cup
    logits = torch.zeros(1, 91)
    logits[0, [1, 47]] = 6.0
    args = (logits, torch.zeros(1, 91 * 4), [torch.tensor([[10.0, 10.0, 50.0, 50.0]])], [(100, 100)])
    _, s_scores, s_labels = stock.postprocess_detections(*args)
    boxes, scores, labels = heads.postprocess_detections(*args)
    assert sorted(s_labels[0].tolist()) == [1, 47] and labels[0].tolist() == [47]
    assert scores[0].tolist() == s_scores[0][s_labels[0] == 47].tolist() and boxes[0].shape == (1, 4)


def test_mask_crop_transform_is_a_transform_subclass_with_torchvisions_settings(random_maskrcnn):
    from massviz.detect.maskrcnn import MaskCropTransform, runtime_model

    stock = random_maskrcnn.transform
    fast = runtime_model(random_maskrcnn).transform
    assert type(fast) is MaskCropTransform and "postprocess" not in vars(fast)
    for attr in ("min_size", "max_size", "image_mean", "image_std", "size_divisible", "fixed_size", "_skip_resize",
                 "training"):
        assert getattr(fast, attr) == getattr(stock, attr)
    assert type(random_maskrcnn.transform) is not MaskCropTransform  # the torchvision model is left as it was


def test_download_is_torch_hubs_with_the_sha256_checked(tmp_path, monkeypatch):
    import email.message
    import hashlib
    import subprocess
    import sys

    import torch.hub

    import massviz.io.weights as W
    from massviz.errors import WeightsError

    src = tmp_path / "src" / "model.bin"
    src.parent.mkdir()
    src.write_bytes(b"x" * 200_000)
    digest = hashlib.sha256(src.read_bytes()).hexdigest()
    calls = []
    real = torch.hub.download_url_to_file
    monkeypatch.setattr(torch.hub, "download_url_to_file", lambda *a, **k: calls.append((a, k)) or real(*a, **k))
    dst = tmp_path / "cache" / "sub" / "model.bin"
    assert W.download(src.as_uri(), dst, digest.upper(), progress=False) == dst  # the folder is made
    assert dst.read_bytes() == src.read_bytes() and calls[0][1]["hash_prefix"] == digest
    assert sorted(p.name for p in dst.parent.iterdir()) == ["model.bin"]

    other = tmp_path / "other"  # a wrong sha256: an error naming the URL, nothing kept, an existing file untouched
    with pytest.raises(WeightsError, match="sha256") as e:
        W.download(src.as_uri(), other / "model.bin", "0" * 64, progress=False)
    assert src.as_uri() in str(e.value) and W.ENV_WEIGHTS in str(e.value) and list(other.iterdir()) == []
    with pytest.raises(WeightsError, match="sha256"):
        W.download(src.as_uri(), dst, "1" * 64, progress=False)
    assert dst.read_bytes() == src.read_bytes() and sorted(p.name for p in dst.parent.iterdir()) == ["model.bin"]
    with pytest.raises(ValueError, match="64 hex"):  # torch.hub checks a prefix: an empty one must not pass
        W.download(src.as_uri(), other / "x.bin", "", progress=False)

    class Broken:  # the connection drops after the first chunk
        def __init__(self, *a, **k):
            self.sent = False

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

        def info(self):
            msg = email.message.Message()
            msg["Content-Length"] = "1000000"
            return msg

        def read(self, n):
            if self.sent:
                raise ConnectionResetError(104, "Connection reset by peer")
            self.sent = True
            return b"y" * 1000

    monkeypatch.setattr(torch.hub, "urlopen", Broken)
    with pytest.raises(WeightsError, match="cannot download"):
        W.download("https://example.invalid/model.bin", other / "model.bin", digest, progress=False)
    assert list(other.iterdir()) == []
    code = "import sys, massviz.io.weights; sys.exit('torch' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0  # importing it stays torch-free
