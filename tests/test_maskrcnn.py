"""massviz.detect.maskrcnn: the real torchvision code path with random weights.

The box classifier is rigged so cups (kept) and persons (dropped) score around the threshold, then massviz's
detector is compared with torchvision's stock model (same state_dict, default box_score_thresh=0.05) filtered the
paper's way afterwards: score > t, class in {cup, book, wine glass, bottle}, int boxes, masks = probability > 0.5.

Speed: both models get ``transform.min_size/max_size`` equal to the test image's size, so torchvision does not
upscale the 160x120 image to 800 px (a forward pass then costs ~20 s on a 2-core CPU instead of a few). The
resize is torchvision's, identical in both models, and not what these tests are about.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

from massviz.core.types import COCO_KEEP, Frame
from massviz.detect import make_detector
from massviz.detect.maskrcnn import MASK_THRESHOLD, MaskRCNNDetector, build_model
from massviz.errors import WeightsError

pytestmark = pytest.mark.slow  # Mask R-CNN (random weights) on CPU frames

THRESHOLD = 0.4
CUP, PERSON = COCO_KEEP["cup"], 1
IMAGE_H, IMAGE_W = 120, 160


def small_images(model: torch.nn.Module) -> torch.nn.Module:
    model.transform.min_size, model.transform.max_size = (IMAGE_H,), IMAGE_W
    return model


def count_mask_head_boxes(model: torch.nn.Module) -> list[int]:
    seen: list[int] = []
    model.roi_heads.mask_head.register_forward_hook(lambda mod, inp, out: seen.append(int(inp[0].shape[0])))
    return seen


@pytest.fixture(scope="module")
def frame() -> Frame:
    rgb = np.random.default_rng(0).integers(0, 256, (IMAGE_H, IMAGE_W, 3), dtype=np.uint8)
    return Frame(index=7, rgb=rgb, depth=np.zeros((IMAGE_H, IMAGE_W), np.uint16))


@pytest.fixture(scope="module")
def random_run(frame):
    """(detector, its detections, boxes its mask head saw): MaskRCNNDetector(pretrained=False), rigged classifier."""
    torch.manual_seed(0)
    det = MaskRCNNDetector(threshold=THRESHOLD, pretrained=False, device="cpu", fused=False)  # torchvision's arithmetic
    model = small_images(det.model)
    with torch.no_grad():
        cls = model.roi_heads.box_predictor.cls_score
        rows = torch.zeros(cls.weight.shape[0], 1)
        rows[[PERSON, CUP]] = 1
        cls.weight.mul_(rows)  # every other class (and background) gets logit 0
        cls.bias.zero_()
        cls.bias[CUP], cls.bias[PERSON] = -1.3, 6.7  # a few percent of the proposals above 0.4, for each
    seen = count_mask_head_boxes(model)
    return det, det.detect(frame), seen


@pytest.fixture(scope="module")
def stock_output(random_run, frame):
    """torchvision's own Mask R-CNN with the same weights and its default settings, unfiltered."""
    from torchvision.models.detection import maskrcnn_resnet50_fpn

    model = maskrcnn_resnet50_fpn(weights=None, weights_backbone=None, num_classes=91).eval()
    assert model.roi_heads.score_thresh == 0.05
    model.load_state_dict(random_run[0].model.state_dict())
    seen = count_mask_head_boxes(small_images(model))
    with torch.no_grad():
        out = model([torch.from_numpy(frame.rgb).permute(2, 0, 1).float() / 255])[0]
    return {k: v.numpy() for k, v in out.items()}, seen


def test_only_kept_classes_above_threshold(random_run, stock_output):
    _, dets, _ = random_run
    out, _ = stock_output
    # the rig works: the stock model has kept-class and dropped-class boxes both above and below the threshold
    assert ((out["labels"] == PERSON) & (out["scores"] > THRESHOLD)).any()
    assert ((out["labels"] == CUP) & (out["scores"] <= THRESHOLD)).any()
    assert len(dets) > 3
    assert set(dets.class_id.tolist()) <= set(COCO_KEEP.values())
    assert (dets.score > THRESHOLD).all()
    assert (dets.frame == 7).all()


def test_equals_stock_model_filtered_the_papers_way(random_run, stock_output):
    _, dets, _ = random_run
    out, _ = stock_output
    keep = (out["scores"] > THRESHOLD) & np.isin(out["labels"], list(COCO_KEEP.values()))
    boxes = [[int(v) for v in box] for box in out["boxes"][keep]]  # the paper's int() truncation
    assert dets.xyxy.tolist() == boxes
    np.testing.assert_array_equal(dets.score, out["scores"][keep])
    np.testing.assert_array_equal(dets.class_id, out["labels"][keep])
    probs = out["masks"][keep][:, 0]
    for i, (x1, y1, x2, y2) in enumerate(boxes):
        expected = probs[i, y1:y2, x1:x2] > 0.5
        got = dets.mask(i)
        assert got.dtype == bool and got.shape == (y2 - y1, x2 - x1)
        np.testing.assert_array_equal(got, expected)
        np.testing.assert_array_equal(dets.full_mask(i, IMAGE_H, IMAGE_W)[y1:y2, x1:x2], expected)
    assert MASK_THRESHOLD == 0.5
    assert any(dets.mask(i).any() and not dets.mask(i).all() for i in range(len(dets)))  # a real threshold


def test_mask_head_never_sees_dropped_boxes(random_run, stock_output):
    _, dets, seen = random_run
    _, stock_seen = stock_output
    assert seen == [len(dets)]
    assert stock_seen[0] > len(dets)  # the stock model computes masks for the boxes the filter then drops


def test_detector_weights_file_round_trip(random_run, frame, tmp_path):
    det, dets, _ = random_run
    path = tmp_path / "maskrcnn_state.pth"
    torch.save(det.model.state_dict(), path)
    loaded = MaskRCNNDetector(threshold=THRESHOLD, weights=path, device="cpu", fused=False)
    assert loaded.settings()["weights"].startswith(str(path.resolve()))
    again = small_images(loaded.model) and loaded.detect(frame)
    assert again.xyxy.tolist() == dets.xyxy.tolist()
    np.testing.assert_array_equal(again.score, dets.score)
    np.testing.assert_array_equal(again.class_id, dets.class_id)
    for i in range(len(dets)):
        np.testing.assert_array_equal(again.mask(i), dets.mask(i))


def test_bad_detector_weights_name_the_file(tmp_path):
    missing = tmp_path / "nope.pth"
    with pytest.raises(WeightsError, match="not found") as info:
        build_model(THRESHOLD, missing)
    assert str(missing) in str(info.value)
    garbage = tmp_path / "garbage.pth"
    garbage.write_bytes(b"not a torch file at all" * 10)
    with pytest.raises(WeightsError) as info:
        MaskRCNNDetector(weights=garbage).model  # noqa: B018 - loading is lazy
    assert str(info.value).startswith(f"{garbage}: ") and "\n" not in str(info.value)
    wrong = tmp_path / "wrong.pth"
    torch.save({"conv.weight": torch.zeros(2, 2)}, wrong)
    with pytest.raises(WeightsError, match="state_dict") as info:
        build_model(THRESHOLD, wrong)
    assert str(wrong) in str(info.value)


def test_auto_falls_back_to_depth_offline(monkeypatch, caplog, tmp_path):
    """auto's choice from local files only (tests/test_detector_auto.py has the rest): nothing cached -> depth, said
    (a log record; on stderr from the command line) even with quiet; Mask R-CNN weights cached -> maskrcnn."""
    import logging

    caplog.set_level(logging.INFO, logger="massviz")

    def said():
        lines = "\n".join(r.getMessage() for r in caplog.records if r.name.startswith("massviz"))
        caplog.clear()
        return lines

    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    monkeypatch.setenv("MASSVIZ_CACHE_DIR", str(tmp_path / "cache"))
    det = make_detector("auto", 0.4)
    assert det.name == "depth" and det.threshold == 0.4
    err = said()
    assert len(err.strip().splitlines()) == 1 and "using depth" in err
    make_detector("auto", 0.4, quiet=True)
    assert "using depth" in said()  # --quiet never hides a fallback
    ckpt = tmp_path / "torch" / "hub" / "checkpoints"
    ckpt.mkdir(parents=True)
    (ckpt / "maskrcnn_resnet50_fpn_coco-bf2d0c1e.pth").write_bytes(b"x")
    assert make_detector("auto", 0.5).name == "maskrcnn"
    assert "using maskrcnn" in said()
