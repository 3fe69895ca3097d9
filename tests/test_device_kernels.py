"""The device path's fused and overlapped pieces, on the CPU (the path CI runs; CUDA runs the same functions) and,
where a CUDA GPU is at hand, on it:

* ``massviz.core.windows.window_features`` (the mask windows, d and the mask bits in ``np.packbits`` layout in one
  function) equals the eager pieces it replaces bit for bit: ``MaskWindows.windows``, the depth sum, ``np.packbits``;
  compiled with ``torch.compile`` it gives the same bits;
* ``massviz.core.resample``: the tables kept per device, the bucketed passes equal to Pillow, ``to_unit_float``;
* ``FrameStage(detect_ahead=True)`` (the detector of batch n + 1 in a thread of its own while batch n is
  post-processed) gives what the serial path gives;
* ``massviz.core.streams`` on a CPU is the plain operation; Mask R-CNN's device path changes no shared state.
"""
from __future__ import annotations

import threading

import numpy as np
import pytest
import torch

from massviz.core.types import Detections, Frame
from support import random_mask_case

CUDA = torch.cuda.is_available()
needs_cuda = pytest.mark.skipif(not CUDA, reason="no CUDA GPU")


def _mask_case(n, seed=0, width=320, height=240):
    probs, boxes, _ = random_mask_case(n, seed, width, height)
    return probs, boxes


def _eager_reference(mw, depth, frame_of, xyxy):
    """What the device path computed before the fused function: the windows, d by the same arithmetic, the host's
    ``np.packbits`` of each window inside its box."""
    h = int(max((xyxy[:, 3] - xyxy[:, 1]).max(), 1))
    w = int(max((xyxy[:, 2] - xyxy[:, 0]).max(), 1))
    win = mw.windows(np.arange(len(xyxy)), xyxy, h, w)
    g = torch.from_numpy(np.concatenate([frame_of[:, None], xyxy], axis=1).astype(np.int64))
    ys = (g[:, 2:3] + torch.arange(h)).clamp(max=depth.shape[1] - 1)
    xs = (g[:, 1:2] + torch.arange(w)).clamp(max=depth.shape[2] - 1)
    z = depth[g[:, 0, None, None], ys[:, :, None], xs[:, None, :]].to(torch.int64) & 0xFFFF
    z = torch.where(win, z, 0)
    total, count = z.sum(dim=(1, 2)), (z > 0).sum(dim=(1, 2))
    mean = total.double() / count.double()
    d = torch.where(count > 0, torch.round(mean * 100.0) / 100.0, float("nan")).numpy()
    bits = [np.packbits(win[i, :y2 - y1, :x2 - x1].numpy(), axis=None) for i, (x1, y1, x2, y2) in enumerate(xyxy)]
    return d, bits


def _fused(mw, depth, frame_of, xyxy, fn=None, pad=(0, 0)):
    from massviz.core.windows import packed_bytes, window_features

    fn = fn or window_features
    h = int(max((xyxy[:, 3] - xyxy[:, 1]).max(), 1)) + pad[0]
    w = int(max((xyxy[:, 2] - xyxy[:, 0]).max(), 1)) + pad[1]
    geo = torch.from_numpy(np.concatenate([frame_of[:, None], xyxy], axis=1).astype(np.int64))
    d, bits = fn(mw.padded, mw.expanded, depth, geo, torch.tensor(100.0, dtype=torch.float64), h, w,
                 (h * w + 7) // 8, mw.im_h, mw.im_w, mw.threshold)
    nb = packed_bytes(xyxy[:, 3] - xyxy[:, 1], xyxy[:, 2] - xyxy[:, 0])
    return d.numpy(), [bits[i, :nb[i]].numpy() for i in range(len(xyxy))]


def _depth_case(seed, frames, width, height):
    rng = np.random.default_rng(seed)
    depth = rng.integers(0, 4000, (frames, height, width)).astype(np.uint16)
    depth[:, :, : width // 8] = 0  # a band without depth: d is NaN for a box inside it
    return torch.from_numpy(depth.view(np.int16))


def test_window_features_equal_the_eager_windows_d_and_packbits_bit_for_bit():
    from massviz.detect.maskrcnn import MaskWindows

    probs, boxes = _mask_case(90)
    mw = MaskWindows(probs, boxes, 240, 320)
    xyxy = boxes.numpy().astype(np.int32)
    xyxy = np.concatenate([xyxy, [[1, 1, 20, 30], [5, 5, 5, 9], [300, 200, 301, 201]]]).astype(np.int32)
    mw = MaskWindows(torch.cat([probs, torch.rand(3, 1, 28, 28)]), torch.from_numpy(xyxy).float(), 240, 320)
    frame_of = np.arange(len(xyxy)) % 2
    depth = _depth_case(1, 2, 320, 240)
    want_d, want_bits = _eager_reference(mw, depth, frame_of, xyxy)
    for pad in ((0, 0), (13, 7)):  # bucketed (larger) windows give the same bits
        got_d, got_bits = _fused(mw, depth, frame_of, xyxy, pad=pad)
        assert np.array_equal(got_d, want_d, equal_nan=True)
        assert np.isnan(got_d).any() and np.isfinite(got_d).sum() > 50
        assert all(np.array_equal(a, b) for a, b in zip(got_bits, want_bits))
    assert want_bits[-2].size == 0  # an empty box: no bytes


@pytest.mark.slow
def test_window_features_compiled_equal_the_eager_function_on_the_cpu():
    """torch.compile (inductor's C++ code on this CPU) of the fused function: the same d and bits."""
    from massviz.core.windows import window_features
    from massviz.detect.maskrcnn import MaskWindows

    probs, boxes = _mask_case(40, seed=3)
    mw = MaskWindows(probs, boxes, 240, 320)
    xyxy = boxes.numpy().astype(np.int32)
    frame_of = np.zeros(len(xyxy), np.int64)
    depth = _depth_case(2, 1, 320, 240)
    want_d, want_bits = _fused(mw, depth, frame_of, xyxy)
    got_d, got_bits = _fused(mw, depth, frame_of, xyxy, fn=torch.compile(window_features, dynamic=False))
    assert np.array_equal(got_d, want_d, equal_nan=True)
    assert all(np.array_equal(a, b) for a, b in zip(got_bits, want_bits))


# -------------------------------------------------------------------------------------------------- resample
def test_device_tables_are_kept_per_device_and_grow_with_new_sides(monkeypatch):
    import massviz.core.resample as resample
    from massviz.core.resample import coefficients, device_tables

    first, weights = device_tables("cpu", [7, 300])

    def made_again(side):
        raise AssertionError(f"the table of side {side} was made again")

    with monkeypatch.context() as m:
        m.setattr(resample, "_coefficients", made_again)
        again = device_tables("cpu", [7, 300])
    assert again[0] is first and again[1] is weights  # nothing made or copied again
    for side in (7, 300):
        f, w = coefficients(side)
        assert np.array_equal(first[side].numpy(), f)
        assert np.array_equal(weights[side, :, :w.shape[1]].numpy(), w) and not weights[side, :, w.shape[1]:].any()
    bigger = device_tables("cpu", [900])
    assert bigger[0].shape[0] > 900 and torch.equal(bigger[0][300], first[300])


def test_resize_chunk_gives_the_same_bytes_for_larger_buckets():
    from massviz.core.resample import device_tables, resize_chunk, taps

    rng = np.random.default_rng(4)
    frames = torch.from_numpy(rng.integers(0, 256, (1, 120, 160, 3), dtype=np.uint8))
    boxes = np.array([[3, 4, 60, 40], [10, 10, 11, 90], [0, 0, 160, 120]])
    side = np.maximum(boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1])
    left, top = (side - (boxes[:, 2] - boxes[:, 0])) // 2, (side - (boxes[:, 3] - boxes[:, 1])) // 2
    geo = torch.from_numpy(np.stack([np.zeros(3, np.int64), boxes[:, 0] - left, boxes[:, 1] - top, boxes[:, 0],
                                     boxes[:, 2], boxes[:, 1], boxes[:, 3]], axis=1))
    first, weights = device_tables("cpu", side)
    s = torch.from_numpy(side)
    exact = resize_chunk(frames, geo, first[s], weights[s], int(side.max()), taps(int(side.max())))
    padded = resize_chunk(frames, geo, first[s], weights[s], 256, taps(256))
    assert torch.equal(exact, padded)


def test_to_unit_float_on_the_cpu_is_the_division_the_table_holds():
    from massviz.core.resample import to_unit_float

    u8 = torch.arange(256, dtype=torch.uint8).reshape(16, 16)
    assert torch.equal(to_unit_float(u8), torch.arange(256, dtype=torch.float32).div(255).reshape(16, 16))
    hwc = torch.randint(0, 256, (5, 7, 3), dtype=torch.uint8).permute(2, 0, 1)
    assert to_unit_float(hwc).stride() == hwc.float().stride()


# --------------------------------------------------------------------------------------------------- streams
def test_streams_on_a_cpu_are_the_plain_operations():
    from massviz.core.streams import Lane, bucket, compiled, to_host

    lane = Lane("cpu")
    with lane:
        t = torch.arange(5)
    assert lane.record() is None
    lane.wait(None)
    lane.keep(t)
    got = to_host([t, None, t * 2])
    assert np.array_equal(got[0], np.arange(5)) and got[1] is None and np.array_equal(got[2], 2 * np.arange(5))

    def f(x):
        return x + 1

    assert compiled(f, "cpu") is f
    sizes = [bucket(n) for n in range(1, 3000)]
    assert all(s >= n for n, s in zip(range(1, 3000), sizes)) and len(set(sizes)) <= 20
    assert all(s < 1.5 * n for n, s in zip(range(17, 3000), sizes[16:]))


# --------------------------------------------------------------------------------------------- detect ahead
class _DeviceDetector:
    """A detector with ``detect_device``: seeded random boxes and mask probabilities per frame (a stand-in for
    Mask R-CNN's outputs), a little slow, recording the thread it ran in."""

    name = "fake-device"
    device = torch.device("cpu")
    precision = "fp32"

    def __init__(self):
        self.threads = set()

    def settings(self):
        return {}

    def detect_device(self, frames, rgb):
        import time

        from massviz.detect.maskrcnn import MaskWindows

        self.threads.add(threading.current_thread().name)
        time.sleep(0.01)
        dets, probs, boxes = [], [], []
        h, w = int(rgb.shape[1]), int(rgb.shape[2])
        for f in frames:
            p, b = _mask_case(5 + f.index % 4, seed=f.index, width=w, height=h)
            xyxy = b.numpy().astype(np.int32)
            dets.append(Detections(frame=np.full(len(xyxy), f.index), xyxy=xyxy,
                                   score=np.full(len(xyxy), 0.9, np.float32), class_id=np.full(len(xyxy), 47)))
            probs.append(p)
            boxes.append(b)
        return dets, MaskWindows(torch.cat(probs), torch.cat(boxes), h, w)


@pytest.fixture(scope="module")
def model(weights):
    from massviz.io.checkpoint import load_checkpoint

    return load_checkpoint(weights)


def _frames(n, width=160, height=120):
    rng = np.random.default_rng(5)
    return [Frame(i, rng.integers(0, 256, (height, width, 3), dtype=np.uint8),
                  rng.integers(300, 3000, (height, width)).astype(np.uint16)) for i in range(n)]


def test_detect_ahead_gives_what_the_serial_path_gives(model):
    from massviz.core.frame_stage import FrameStage

    frames = _frames(7)
    det = _DeviceDetector()
    serial = list(FrameStage(det, model, batch=2, kernels="device", detect_ahead=False).stream(frames))
    assert det.threads == {threading.current_thread().name}
    det.threads.clear()
    stage = FrameStage(det, model, batch=2, kernels="device", detect_ahead=True)
    ahead = list(stage.stream(frames))
    assert det.threads and all(t.startswith("massviz-detect") for t in det.threads)  # the detector's own thread
    assert [s.frame.index for s in ahead] == [s.frame.index for s in serial] == list(range(7))
    for a, b in zip(serial, ahead):
        da, db = a.detections, b.detections
        for name in ("xyxy", "score", "d", "a", "b", "pred"):
            assert np.array_equal(getattr(da, name), getattr(db, name), equal_nan=True), name
        assert all(np.array_equal(da.mask(i), db.mask(i)) for i in range(len(da)))
        assert set(b.timings) == {"read", "detect", "features", "predict"}
    assert sum(np.isfinite(s.detections.pred).sum() for s in ahead) > 20


def test_detect_ahead_raises_a_detector_error_at_its_batch():
    from massviz.core.frame_stage import FrameStage

    class Failing(_DeviceDetector):
        def detect_device(self, frames, rgb):
            if any(f.index == 4 for f in frames):
                raise RuntimeError("frame 4 is broken")
            return super().detect_device(frames, rgb)

    stage = FrameStage(Failing(), _Stub(), batch=2, kernels="device", detect_ahead=True)
    seen = []
    with pytest.raises(RuntimeError, match="frame 4 is broken"):
        for staged in stage.stream(_frames(7)):
            seen.append(staged.frame.index)
    assert seen == [0, 1, 2, 3]


class _Stub(torch.nn.Module):
    """A mass CNN stand-in with what the device kernels use: ranges and ``predict_normalised``."""

    def __init__(self):
        super().__init__()
        from massviz.core.model import Ranges

        self.ranges = Ranges(min_distance=0.0, max_distance=5000.0, min_ratio_width=0.0, max_ratio_width=1.0,
                             min_ratio_height=0.0, max_ratio_height=1.0, min_mass=0.0, max_mass=100.0)

    def predict_normalised(self, images, feats):
        return images.mean(dim=(1, 2, 3))


# ------------------------------------------------------------------------------------------------ Mask R-CNN
@pytest.mark.slow
def test_mask_rcnn_device_path_changes_no_shared_state_and_equals_detect():
    from massviz.core.device import upload
    from massviz.detect.maskrcnn import MaskCropTransform, MaskRCNNDetector

    torch.manual_seed(0)
    det = MaskRCNNDetector(pretrained=False, device="cpu", threshold=0.0)
    frames = _frames(2, 96, 64)
    before = dict(vars(det.runtime.transform))
    assert not hasattr(MaskCropTransform, "paste")
    host = det.detect_batch(frames)
    dets, windows = det.detect_device(frames, upload([f.rgb for f in frames], "cpu"))
    assert dict(vars(det.runtime.transform)).keys() == before.keys()
    for a, b in zip(host, dets):
        assert np.array_equal(a.xyxy, b.xyxy) and np.array_equal(a.score, b.score)
    assert len(windows) == sum(len(d) for d in dets)


# ------------------------------------------------------------------------------------------------ on a CUDA GPU
@needs_cuda
def test_cuda_window_features_compiled_equal_eager_up_to_rounding_at_the_threshold():
    """On CUDA the fused function runs compiled: the same d where no mask bit differs, and bits that differ only
    where a probability is within float rounding of 0.5 (a compiled kernel may contract a*b + c into one rounding)."""
    from massviz.core.streams import compiled
    from massviz.core.windows import window_features
    from massviz.detect.maskrcnn import MaskWindows

    probs, boxes = _mask_case(300, seed=6, width=1280, height=720)
    mw = MaskWindows(probs.cuda(), boxes.cuda(), 720, 1280)
    xyxy = boxes.numpy().astype(np.int32)
    frame_of = np.arange(len(xyxy)) % 3
    depth = _depth_case(3, 3, 1280, 720).cuda()
    eager_d, eager_bits = _fused(mw, depth, frame_of, xyxy)
    fn = compiled(window_features, "cuda")
    assert fn is not window_features
    got_d, got_bits = _fused(mw, depth, frame_of, xyxy, fn=fn)
    assert not fn.failed
    differ = [i for i in range(len(xyxy)) if not np.array_equal(got_bits[i], eager_bits[i])]
    flipped = sum(int(np.unpackbits(got_bits[i] ^ eager_bits[i]).sum()) for i in differ)
    assert flipped <= 1e-4 * sum(8 * b.size for b in eager_bits), flipped
    same = np.setdiff1d(np.arange(len(xyxy)), differ)
    assert np.array_equal(got_d[same], eager_d[same], equal_nan=True)


@needs_cuda
def test_cuda_resize_boxes_compiled_equals_pillow_and_the_cpu():
    from massviz.core.resample import resize_boxes

    rng = np.random.default_rng(8)
    frames = torch.from_numpy(rng.integers(0, 256, (2, 720, 1280, 3), dtype=np.uint8))
    x1, y1 = rng.integers(0, 1000, 150), rng.integers(0, 500, 150)
    boxes = np.stack([x1, y1, x1 + rng.integers(1, 280, 150), y1 + rng.integers(1, 220, 150)], axis=1)
    frame_of = rng.integers(0, 2, 150)
    assert torch.equal(resize_boxes(frames.cuda(), frame_of, boxes).cpu(), resize_boxes(frames, frame_of, boxes))


@needs_cuda
@pytest.mark.slow
def test_cuda_mask_rcnn_through_the_device_path_equals_the_cpu_estimate(model, tmp_path):
    """Mask R-CNN (random, detector-like weights) through the device path on CUDA, the detector a batch ahead on
    its own stream: the same detections and choice as the CPU's exact path, the estimate within 0.5 %."""
    import copy
    import sys

    from support import ROOT

    sys.path.insert(0, str(ROOT / "benchmarks"))
    from vs_paper_loop import make_recording, make_weights

    from massviz.core.pipeline import run
    from massviz.detect.maskrcnn import MaskRCNNDetector
    from massviz.io.recording import open_recording

    rec = open_recording(make_recording(tmp_path / "rec", 3))
    w = make_weights(tmp_path / "w.pth", "b")
    cpu = run(rec, MaskRCNNDetector(weights=w, device="cpu"), model, k=5)
    gpu_model = copy.deepcopy(model).to("cuda")
    cuda = run(rec, MaskRCNNDetector(weights=w, device="cuda"), gpu_model, k=5)
    assert cuda.compute["kernels"] == "device" and cuda.compute["mode"] == "faithful" and cuda.compute["batch"] == 1
    assert len(cpu.detections) > 100 and abs(len(cuda.detections) - len(cpu.detections)) <= 3
    assert cuda.estimate == pytest.approx(cpu.estimate, rel=0.005)


def test_device_tables_made_in_inference_mode_grow_outside_it():
    """The tables outlive the call that made them: made while a pipeline runs in inference mode, they still take the
    rows of new sides in a later call outside it (an inference tensor would refuse the in-place update)."""
    import torch

    from massviz.core import resample

    with resample._TABLES_LOCK:
        saved = dict(resample._TABLES)
        resample._TABLES.clear()
    try:
        with torch.inference_mode():
            first, _ = resample.device_tables("cpu", [40, 60])
        assert not first.is_inference()
        first, weights = resample.device_tables("cpu", [41, 300])  # new sides, and a larger table
        want_first, want_weights = resample.coefficients(41)
        assert first[41].tolist() == want_first.tolist()
        assert weights[41, :, :want_weights.shape[1]].tolist() == want_weights.tolist()
    finally:
        with resample._TABLES_LOCK:
            resample._TABLES.clear()
            resample._TABLES.update(saved)
