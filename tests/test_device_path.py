"""The device path (``massviz.core.frame_stage``, ``kernels="device"``): what runs on a GPU, run here on the CPU so that CI
tests it, against the exact CPU path; ``--device``; and, where a CUDA GPU is at hand, the same checks on it plus what
the faithful fp32 mode guarantees there (README, "GPU").

* Pillow's resize as integer tensor arithmetic (``massviz.core.resample``) equals Pillow byte for byte.
* Mask R-CNN's masks pasted on the device for many boxes at once (``MaskWindows``) equal ``paste_mask_crops``
  except where a probability is within float rounding of 0.5.
* The whole pipeline through the device kernels gives the exact path's detections, d and selection, and predictions
  within float rounding (the mass CNN's calls are padded to a fixed size there).
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

from massviz.core.model import preprocess_patch
from massviz.core.pipeline import run
from massviz.core.resample import coefficients, resize_boxes
from massviz.io.recording import open_recording
from support import random_mask_case, run_massviz

CUDA = torch.cuda.is_available()
needs_cuda = pytest.mark.skipif(not CUDA, reason="no CUDA GPU")


def _boxes(rng, n, width, height, sides=None):
    boxes = []
    for i in range(n):
        if sides is not None:
            s = int(sides[i])
            w, h = s, int(rng.integers(1, s + 1))
            if rng.random() < 0.5:
                w, h = h, w
        else:
            w, h = int(rng.integers(1, width + 1)), int(rng.integers(1, height + 1))
        x, y = int(rng.integers(0, width - w + 1)), int(rng.integers(0, height - h + 1))
        boxes.append((x, y, x + w, y + h))
    return np.array(boxes, dtype=np.int64)


def _pillow(frames, frame_of, boxes):
    return torch.stack([preprocess_patch(frames[f].cpu().numpy()[y1:y2, x1:x2]) for f, (x1, y1, x2, y2)
                        in zip(frame_of, boxes, strict=False)])


# ------------------------------------------------------------------------------------------------ resize, on the CPU
def test_pillow_coefficients_sum_to_one_in_fixed_point():
    for side in (1, 2, 55, 111, 112, 113, 224, 799, 1280):
        first, w = coefficients(side)
        assert first.shape == (112,) and (first >= 0).all() and (first < side).all()
        assert np.abs(w.sum(axis=1) - (1 << 22)).max() <= w.shape[1]  # each row: 1.0 up to rounding per tap
    first, w = coefficients(112)  # the identity: one tap of weight 1.0 per pixel
    assert np.array_equal(first, np.arange(112)) and (w[:, 0] == 1 << 22).all() and (w[:, 1:] == 0).all()


def test_resize_boxes_equals_pillow_for_every_side_up_to_260_and_large_crops():
    rng = np.random.default_rng(0)
    frames = torch.from_numpy(rng.integers(0, 256, (2, 360, 640, 3), dtype=np.uint8))
    sides = np.arange(1, 261)
    boxes = np.concatenate([_boxes(rng, len(sides), 640, 360, sides), _boxes(rng, 6, 640, 360)])
    frame_of = rng.integers(0, 2, len(boxes))
    got = resize_boxes(frames, frame_of, boxes, chunk=48)
    want = _pillow(frames, frame_of, boxes)
    assert got.dtype == torch.float32 and got.shape == (len(boxes), 3, 112, 112)
    differ = [tuple(boxes[i]) for i in range(len(boxes)) if not torch.equal(got[i], want[i])]
    assert differ == []
    with pytest.raises(ValueError, match="one pixel"):
        resize_boxes(frames, [0], [[5, 5, 5, 9]])
    assert resize_boxes(frames, [], np.zeros((0, 4))).shape == (0, 3, 112, 112)


# ---------------------------------------------------------------------------------------- mask windows, on the CPU
def _mask_case(n, seed=0, width=200, height=150):
    probs, boxes, g = random_mask_case(n, seed, width, height)
    edge = torch.tensor([[0.0, 0.0, width - 0.5, height - 0.5], [3.2, 4.7, 3.9, 5.1], [width - 9.5, height - 9.5,
                                                                                        width - 0.1, height - 0.1]])
    return torch.cat([probs, torch.rand(3, 1, 28, 28, generator=g)]), torch.cat([boxes, edge]), width, height


def _windows_vs_paste(probs, boxes, width, height, device):
    import torch.nn.functional as F
    from torchvision.models.detection.roi_heads import expand_boxes, expand_masks

    from massviz.detect.maskrcnn import MaskWindows, paste_mask_crops

    xyxy = boxes.numpy().astype(np.int32)
    want = paste_mask_crops(probs, boxes, height, width)
    h = max(int((xyxy[:, 3] - xyxy[:, 1]).max()), 1)
    w = max(int((xyxy[:, 2] - xyxy[:, 0]).max()), 1)
    mw = MaskWindows(probs.to(device), boxes.to(device), height, width)
    got = mw.windows(np.arange(len(boxes)), xyxy, h, w).cpu().numpy()
    # the probabilities torchvision thresholds, to tell rounding at 0.5 from a real difference
    padded, scale = expand_masks(probs, padding=1)
    ex = expand_boxes(boxes, scale).to(torch.int64).tolist()
    bad, near = 0, 0
    for i, (x1, y1, x2, y2) in enumerate(xyxy):
        g = got[i, :y2 - y1, :x2 - x1]
        assert g.shape == want[i].shape and not got[i, y2 - y1:].any() and not got[i, :, x2 - x1:].any()
        diff = np.argwhere(g != want[i])
        if len(diff):
            ex0, ey0, ex1, ey1 = ex[i]
            r = F.interpolate(padded[i][None], size=(max(ey1 - ey0 + 1, 1), max(ex1 - ex0 + 1, 1)),
                              mode="bilinear", align_corners=False)[0, 0]
            for yy, xx in diff:
                p = float(r[y1 + yy - ey0, x1 + xx - ex0])
                near += abs(p - 0.5) < 1e-5
                bad += abs(p - 0.5) >= 1e-5
    return bad, near, sum(m.size for m in want)


def test_mask_windows_equal_paste_mask_crops_up_to_rounding_at_the_threshold():
    probs, boxes, width, height = _mask_case(120)
    bad, near, total = _windows_vs_paste(probs, boxes, width, height, "cpu")
    assert total > 100_000 and bad == 0 and near <= total * 1e-4, (bad, near, total)
    print(f"mask windows on the CPU: {near} of {total} pixels differ, all within 1e-5 of the 0.5 threshold")


# -------------------------------------------------------------------------------------- the whole path, on the CPU
@pytest.fixture(scope="module")
def samples(samples_dir):
    return [open_recording(samples_dir / n) for n in ("cup_handover", "box_handover")]



def _same_detections(a, b, rtol=1e-4):
    da, db = a.detections, b.detections
    for name in ("frame", "xyxy", "score", "class_id", "d", "a", "b"):
        assert np.array_equal(getattr(da, name), getattr(db, name), equal_nan=True), name
    assert all(np.array_equal(da.mask(i), db.mask(i)) for i in range(len(da)))
    np.testing.assert_allclose(db.pred, da.pred, rtol=rtol, equal_nan=True)
    assert np.array_equal(a.selection, b.selection)
    assert b.estimate == pytest.approx(a.estimate, rel=rtol)


@pytest.mark.slow
def test_device_kernels_on_the_cpu_equal_the_exact_path_with_the_depth_detector(samples, model):
    from massviz.detect import make_detector

    for rec in samples:
        det = make_detector("depth", 0.4, quiet=True)
        exact = run(rec, det, model, k=5, batch=1, prefetch=0)
        device = run(rec, det, model, k=5, batch=4, prefetch=0, kernels="device")
        assert exact.compute["kernels"] == "exact" and device.compute["kernels"] == "device"
        assert exact.compute["device"] == device.compute["device"] == "cpu" and device.compute["batch"] == 4
        assert np.isfinite(exact.detections.pred).sum() >= 2
        _same_detections(exact, device)


@pytest.mark.slow
def test_device_kernels_on_the_cpu_with_mask_rcnn_masks_on_the_device(samples, model):
    from fakes import rig
    from massviz.detect.maskrcnn import MaskRCNNDetector

    rec = samples[0]
    torch.manual_seed(0)
    det = rig(MaskRCNNDetector(pretrained=False, device="cpu"), rec.width, rec.height)
    # the same detector batches on both sides (a batch of 2 may round differently from single frames)
    exact = run(rec, det, model, k=5, stride=9, batch=2, prefetch=0)
    device = run(rec, det, model, k=5, stride=9, batch=2, prefetch=0, kernels="device")
    assert len(exact.detections) >= 4
    _same_detections(exact, device)


def test_mass_cnn_calls_of_a_fixed_size_do_not_depend_on_their_company(model):
    rng = np.random.default_rng(3)
    images = torch.rand(150, 3, 112, 112, generator=torch.Generator().manual_seed(3))
    feats = torch.from_numpy(rng.uniform(0, 1, (150, 3)).astype(np.float32))
    whole = model.predict_normalised(images, feats, rows=64)
    for lo, hi in ((0, 1), (5, 70), (64, 150), (149, 150)):
        assert torch.equal(model.predict_normalised(images[lo:hi], feats[lo:hi], rows=64), whole[lo:hi])


# ------------------------------------------------------------------------------------------------------ --device
def test_device_option_resolves_and_names_what_is_wrong():
    from massviz.core.device import resolve_device
    from massviz.errors import MassvizError

    assert resolve_device("cpu").type == "cpu"
    assert resolve_device("auto").type == ("cuda" if CUDA else "cpu")
    for bad, says in (("tpu", "not a device"), ("mps", "cpu or cuda"), ("cuda:x", "not a device"),
                      ("cuda:99", "CUDA")):
        with pytest.raises(MassvizError, match=says):
            resolve_device(bad)
    if not CUDA:
        with pytest.raises(MassvizError, match="no CUDA GPU is available here"):
            resolve_device("cuda")


@pytest.mark.slow
def test_estimate_device_option_on_the_command_line(samples_dir, weights, tmp_path):
    rec = samples_dir / "cup_handover"
    ok = run_massviz("estimate", rec, "--detector", "depth", "--device", "cpu", "--no-cache", "--quiet",
                     "--weights", weights, "--out", tmp_path / "cpu.csv")
    assert ok.returncode == 0, ok.stderr
    if not CUDA:
        bad = run_massviz("estimate", rec, "--detector", "depth", "--device", "cuda", "--no-cache", "--out",
                          tmp_path / "gpu.csv", "--weights", weights)
        assert bad.returncode == 2 and not (tmp_path / "gpu.csv").exists()
        lines = bad.stderr.strip().splitlines()
        assert len(lines) == 1 and "--device cuda: no CUDA GPU is available here" in lines[0], bad.stderr


# ------------------------------------------------------------------------------------------------- on a CUDA GPU
@needs_cuda
def test_cuda_resize_boxes_equals_pillow():
    rng = np.random.default_rng(1)
    frames = torch.from_numpy(rng.integers(0, 256, (2, 720, 1280, 3), dtype=np.uint8))
    boxes = np.concatenate([_boxes(rng, 400, 1280, 720, np.arange(1, 401)), _boxes(rng, 20, 1280, 720)])
    frame_of = rng.integers(0, 2, len(boxes))
    got = resize_boxes(frames.cuda(), frame_of, boxes).cpu()
    want = _pillow(frames, frame_of, boxes)
    assert [tuple(boxes[i]) for i in range(len(boxes)) if not torch.equal(got[i], want[i])] == []


@needs_cuda
def test_cuda_mask_windows_equal_paste_mask_crops_up_to_rounding_at_the_threshold():
    probs, boxes, width, height = _mask_case(300, seed=4, width=1280, height=720)
    bad, near, total = _windows_vs_paste(probs, boxes, width, height, "cuda")
    assert bad == 0 and near <= total * 1e-4, (bad, near, total)


@needs_cuda
def test_cuda_mass_cnn_is_call_invariant_and_equals_the_cpu_within_rounding(model):
    import copy

    gpu = copy.deepcopy(model).to("cuda")
    g = torch.Generator().manual_seed(5)
    images, feats = torch.rand(300, 3, 112, 112, generator=g), torch.rand(300, 3, generator=g)
    with torch.inference_mode():
        from massviz.core.device import faithful_fp32

        with faithful_fp32("cuda"):
            whole = gpu.predict_normalised(images.cuda(), feats.cuda())
            again = gpu.predict_normalised(images.cuda(), feats.cuda())
            parts = torch.cat([gpu.predict_normalised(images[a:b].cuda(), feats[a:b].cuda())
                               for a, b in ((0, 1), (1, 90), (90, 299), (299, 300))])
    assert torch.equal(whole, again) and torch.equal(whole, parts)  # deterministic, whatever the company
    cpu = model.predict_normalised(images, feats)
    grams = model.ranges.denormalise_mass
    np.testing.assert_allclose(grams(whole.cpu().numpy()), grams(cpu.numpy()), rtol=1e-4, atol=1e-3)


@needs_cuda
@pytest.mark.slow
def test_cuda_faithful_fp32_detection_is_deterministic_and_batches_agree(samples_dir):
    """What --precision fp32 guarantees on CUDA: the same frames give the same bits run after run (IEEE fp32,
    deterministic cuDNN); a batch of frames may round differently from single frames, within float rounding (why the
    faithful default batch on CUDA is 1)."""
    from fakes import rig
    from massviz.core.device import upload
    from massviz.detect.maskrcnn import MaskRCNNDetector

    rec = open_recording(samples_dir / "cup_handover")
    torch.manual_seed(0)
    det = rig(MaskRCNNDetector(pretrained=False, device="cpu"), rec.width, rec.height)
    det.device = torch.device("cuda")
    det._model = det.model.to("cuda")
    frames = [rec.read_frame(i) for i in (0, 9, 18, 27)]
    one = [det.detect(f) for f in frames]
    again = [det.detect(f) for f in frames]
    for a, b in zip(one, again, strict=False):
        assert np.array_equal(a.xyxy, b.xyxy) and np.array_equal(a.score, b.score)
        assert all(np.array_equal(a.mask(i), b.mask(i)) for i in range(len(a)))
    many = det.detect_batch(frames)
    identical = all(len(a) == len(b) and np.array_equal(a.xyxy, b.xyxy) and np.array_equal(a.score, b.score)
                    for a, b in zip(one, many, strict=False))
    for a, b in zip(one, many, strict=False):
        assert len(a) == len(b)
        np.testing.assert_allclose(b.score, a.score, atol=1e-4)
        assert np.abs(b.xyxy - a.xyxy).max(initial=0) <= 1
    dets, windows = det.detect_device(frames, upload([f.rgb for f in frames], "cuda"))
    for a, b in zip(many, dets, strict=False):
        assert np.array_equal(a.xyxy, b.xyxy) and np.array_equal(a.score, b.score)
    print(f"CUDA fp32: batch of 4 bit-identical to single frames: {identical}")


@needs_cuda
@pytest.mark.slow
def test_cuda_end_to_end_equals_the_cpu_within_half_a_percent(samples, model):
    import copy

    from massviz.detect import make_detector

    gpu = copy.deepcopy(model).to("cuda")
    for rec in samples:
        cpu = run(rec, make_detector("depth", 0.4, quiet=True), model, k=5)
        cuda = run(rec, make_detector("depth", 0.4, quiet=True), gpu, k=5, batch=4)
        assert cuda.compute["device"].startswith("cuda:0") and cuda.compute["kernels"] == "device"
        assert cuda.compute["mode"] == "faithful"
        assert np.array_equal(cpu.detections.d, cuda.detections.d, equal_nan=True)
        assert np.array_equal(cpu.selection, cuda.selection)
        assert cuda.estimate == pytest.approx(cpu.estimate, rel=0.005)


def test_depth_decoded_by_several_threads_gives_the_same_frames_and_errors_in_place(samples_dir, tmp_path):
    import shutil

    from massviz.errors import RecordingError

    rec = open_recording(samples_dir / "box_handover")
    for stride in (1, 5):
        one = list(rec.frames(stride=stride))
        many = list(rec.frames(stride=stride, workers=3))
        assert [f.index for f in many] == [f.index for f in one]
        assert all(np.array_equal(a.depth, b.depth) and np.array_equal(a.rgb, b.rgb) for a, b in zip(one, many, strict=False))
    copy = tmp_path / "rec"
    shutil.copytree(samples_dir / "box_handover", copy)
    bad = sorted((copy / "depth").glob("*.png"))[7]
    bad.write_bytes(b"not a png")
    broken = open_recording(copy)
    seen = []
    with pytest.raises(RecordingError, match=bad.name):
        for frame in broken.frames(workers=3):
            seen.append(frame.index)
    assert seen == list(range(7))
