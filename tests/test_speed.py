"""Faithful speed-ups: batched detection and background reading give the plain run's trace exactly; the fast Mask
R-CNN runtime equals torchvision's up to float rounding; precision is recorded and keys the cache.

Mask R-CNN runs with random weights rigged like a detector (box regressors scaled down so boxes stay near their
anchors, the cup classifier biased so a few boxes per frame pass 0.4) on a bundled sample at half size, with fewer
RPN proposals: a forward costs a fraction of a second on 2 cores.
"""
from __future__ import annotations

import threading

import numpy as np
import pytest
import torch

from fakes import rig, rig_sizes
from massviz.core.pipeline import run
from massviz.core.prefetch import Prefetcher
from massviz.core.types import Frame
from massviz.detect.maskrcnn import MaskRCNNDetector, bf16_supported, fold_batchnorm, paste_mask_crops
from massviz.errors import MassvizError

STRIDE = 9  # frames 0, 9, 18, 27 of cup_handover




@pytest.fixture(scope="module")
def weights_file(tmp_path_factory, recording):
    """One random, rigged Mask R-CNN state_dict shared by every detector of this module."""
    torch.manual_seed(0)
    det = rig(MaskRCNNDetector(pretrained=False, device="cpu"), recording.width, recording.height)
    path = tmp_path_factory.mktemp("maskrcnn") / "rigged.pth"
    torch.save(det.model.state_dict(), path)
    return path


def detector(weights_file, recording, **kw) -> MaskRCNNDetector:
    return rig_sizes(MaskRCNNDetector(weights=weights_file, device="cpu", **kw), recording.width, recording.height)



@pytest.fixture(scope="module")
def mass_model(weights):
    from massviz.io.checkpoint import load_checkpoint

    return load_checkpoint(weights)


@pytest.fixture(scope="module")
def plain(weights_file, recording, mass_model):
    """(detector, trace): the plain fp32 run, one frame per forward, frames read in this thread."""
    det = detector(weights_file, recording)
    return det, run(recording, det, mass_model, stride=STRIDE, batch=1, prefetch=0)


def assert_traces_equal(a, b):
    np.testing.assert_array_equal(a.frames, b.frames)
    da, db = a.detections, b.detections
    assert len(da) == len(db)
    for name in ("frame", "xyxy", "score", "class_id", "d", "a", "b", "pred"):
        np.testing.assert_array_equal(getattr(da, name), getattr(db, name), err_msg=name)
    for i in range(len(da)):
        np.testing.assert_array_equal(da.mask(i), db.mask(i), err_msg=f"mask {i}")
        pa, pb = da.patches[i], db.patches[i]
        assert (pa is None) == (pb is None)
        if pa is not None:
            np.testing.assert_array_equal(pa, pb)
    np.testing.assert_array_equal(a.selection, b.selection)
    assert a.estimate == b.estimate
    assert a.detector == b.detector


@pytest.mark.slow
def test_the_plain_run_is_worth_comparing(plain):
    _, trace = plain
    dets = trace.detections
    assert len(trace.frames) == 4
    assert len(dets) >= 8 and len(set(dets.frame.tolist())) >= 3  # detections on most frames
    assert np.isfinite(dets.d).sum() >= 8 and np.isfinite(dets.pred).sum() >= 8
    assert any(dets.mask(i).any() and not dets.mask(i).all() for i in range(len(dets)))  # real masks
    assert len(trace.selection) == 5 and trace.estimate > 0
    assert trace.detector["precision"] == "fp32"


@pytest.mark.slow
def test_background_read_run_equals_the_plain_run_exactly(plain, recording, mass_model):
    det, reference = plain
    assert_traces_equal(run(recording, det, mass_model, stride=STRIDE, batch=1, prefetch=2), reference)


def assert_equal_up_to_float_rounding(trace, reference):
    """Every detection matched (IoU >= 0.9), scores within 1e-4, integer boxes within 1 px, d within 1 mm,
    predictions within 0.5 g, the same chosen patches and estimate within 0.5 g (a box edge within ~1e-4 px of an
    integer can truncate the other way, moving that box, its mask and patch by one pixel)."""
    from massviz.evaluation.compare import compare_traces

    c = compare_traces(reference, trace, iou=0.9)
    s = c.summary()
    assert s["unmatched_a"] == s["unmatched_b"] == 0 and s["class_changes"] == 0
    assert s["matched"] == len(reference.detections)
    assert s["max_abs_d_score"] <= 1e-4 and s["max_abs_d_d_mm"] <= 1.0 and s["max_abs_d_pred_g"] <= 0.5
    a, b = reference.detections.xyxy[c.match_a], trace.detections.xyxy[c.match_b]
    assert np.abs(a - b).max() <= 1
    assert s["chosen_changed"] == [] and abs(s["estimate_delta_g"]) <= 0.5


@pytest.mark.slow
@pytest.mark.parametrize("batch,prefetch", [(3, 2)], ids=["batch3+prefetch"])
def test_batched_runs_equal_the_plain_run(plain, recording, mass_model, batch, prefetch):
    """One forward for several frames of one size: torchvision pads them all to the same size as one frame alone,
    so the inputs are identical; oneDNN may still pick other kernels for another batch size (equal up to float
    rounding; bit-identical at 1280x720 on the machine the README names)."""
    det, reference = plain
    calls = []
    original = det.detect_batch
    det.detect_batch = lambda frames: calls.append(len(frames)) or original(frames)
    try:
        trace = run(recording, det, mass_model, stride=STRIDE, batch=batch, prefetch=prefetch)
    finally:
        del det.detect_batch
    assert calls == ([batch, 4 - batch] if batch < 4 else [4])  # really batched (the last batch shorter)
    assert_equal_up_to_float_rounding(trace, reference)
    assert trace.timings["detect"] > 0


@pytest.mark.slow
def test_fast_runtime_equals_torchvision_up_to_float_rounding(weights_file, recording):
    """BatchNorm folding + channels_last change the order of the arithmetic only."""
    frame = recording.read_frame(9)
    exact = detector(weights_file, recording, fused=False).detect(frame)
    fast = detector(weights_file, recording).detect(frame)
    assert len(exact) >= 3
    assert abs(len(fast) - len(exact)) <= 1
    n = min(len(fast), len(exact))
    same = fast.class_id[:n] == exact.class_id[:n]
    assert same.mean() >= 0.9
    np.testing.assert_allclose(fast.score[:n][same], exact.score[:n][same], atol=1e-3)
    assert np.abs(fast.xyxy[:n][same] - exact.xyxy[:n][same]).max() <= 1


@pytest.mark.slow
def test_runtime_leaves_the_torchvision_model_untouched(weights_file, plain):
    det, _ = plain  # it ran: its fast copy exists
    before = torch.load(weights_file, weights_only=True)
    after = det.model.state_dict()
    assert before.keys() == after.keys()
    assert all(torch.equal(before[k], after[k]) for k in before)
    assert any(isinstance(m, torch.nn.BatchNorm2d) for m in det.model.modules())
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in det.runtime.backbone.modules())


@pytest.mark.slow
def test_fold_batchnorm_keeps_the_function():
    from torchvision.models import resnet18

    torch.manual_seed(0)
    net = resnet18(weights=None).eval()
    for m in net.modules():  # non-trivial statistics
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.uniform_(-0.5, 0.5)
            m.running_var.uniform_(0.5, 2.0)
            m.weight.data.uniform_(0.5, 1.5)
            m.bias.data.uniform_(-0.2, 0.2)
    x = torch.rand(2, 3, 64, 64)
    with torch.no_grad():
        expected = net(x)
        assert fold_batchnorm(net) == 20  # stem + 8 blocks x 2 + 3 downsamples
        got = net(x)
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in net.modules())
    torch.testing.assert_close(got, expected, rtol=1e-4, atol=1e-4)


def test_mask_crops_equal_torchvision_full_image_paste():
    from torchvision.models.detection.roi_heads import paste_masks_in_image

    torch.manual_seed(0)
    h, w = 60, 80
    boxes = torch.tensor([[10.3, 5.7, 40.9, 30.2], [0.0, 0.0, 80.0, 60.0], [70.5, 50.5, 80.0, 60.0],
                          [20.0, 20.0, 20.6, 45.0], [33.0, 12.0, 34.0, 13.0], [0.2, 40.0, 12.7, 59.99]])
    masks = torch.rand(len(boxes), 1, 28, 28)
    full = paste_masks_in_image(masks, boxes, (h, w))[:, 0]
    crops = paste_mask_crops(masks, boxes, h, w)
    for i, box in enumerate(boxes.tolist()):
        x1, y1, x2, y2 = (int(v) for v in box)
        assert crops[i].dtype == bool and crops[i].shape == (y2 - y1, x2 - x1)
        np.testing.assert_array_equal(crops[i], (full[i, y1:y2, x1:x2] > 0.5).numpy())
    assert sum(c.sum() for c in crops) > 0
    assert paste_mask_crops(masks[:0], boxes[:0], h, w) == []


@pytest.mark.slow
def test_precision_is_recorded_and_keys_the_cache(weights_file, recording, tmp_path):
    from massviz.io.cache import TraceCache

    fp32 = MaskRCNNDetector(weights=weights_file, device="cpu")
    cache = TraceCache(tmp_path)
    key32 = cache.entry(recording, {"name": fp32.name, **fp32.settings()}, 1)
    assert fp32.settings()["precision"] == "fp32"
    if bf16_supported():
        bf16 = MaskRCNNDetector(weights=weights_file, device="cpu", precision="bf16")
        assert bf16.settings()["precision"] == "bf16"
        assert cache.entry(recording, {"name": bf16.name, **bf16.settings()}, 1) != key32
    with pytest.raises(MassvizError, match="fp16 needs a CUDA GPU"):
        MaskRCNNDetector(weights=weights_file, device="cpu", precision="fp16")


@pytest.mark.slow
@pytest.mark.skipif(not bf16_supported(), reason="this CPU has no bfloat16 support")
def test_bf16_run_is_recorded_in_its_trace(weights_file, recording, mass_model, plain):
    det = detector(weights_file, recording, precision="bf16")
    trace = run(recording, det, mass_model, stride=2 * STRIDE, batch=2)  # 2 frames
    assert trace.detector["precision"] == "bf16"
    assert len(trace.detections) > 0 and trace.detections.xyxy.dtype == np.int32
    assert trace.detector != plain[1].detector


def test_precision_of_a_detector_without_one_is_a_clear_error():
    from massviz.app import PipelineOptions
    from massviz.detect import make_detector

    with pytest.raises(MassvizError, match="depth detector runs in fp32 only"):
        make_detector("depth", precision="bf16")
    with pytest.raises(MassvizError, match="--precision"):
        PipelineOptions(precision="fp8").check()
    with pytest.raises(MassvizError, match="--batch"):
        PipelineOptions(batch=0).check()


def test_cli_rejects_fp16_on_a_cpu_in_one_line(weights, samples_dir, tmp_path, capsys):
    from massviz.cli import main

    if torch.cuda.is_available():
        pytest.skip("a CUDA GPU is present: fp16 is allowed")
    code = main(["estimate", str(samples_dir / "cup_handover"), "--detector", "maskrcnn", "--precision", "fp16",
                 "--weights", str(weights), "--detector-weights", "/nonexistent.pth", "--out",
                 str(tmp_path / "never.csv"), "--no-cache"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "fp16 needs a CUDA GPU" in err[0]
    assert not (tmp_path / "never.csv").exists()


# ------------------------------------------------------------------------------------------------ the prefetcher
def test_prefetcher_keeps_order_and_reraises_where_the_error_happened():
    def source():
        yield from range(5)
        raise ValueError("frame 5 is corrupt")

    got = []
    with pytest.raises(ValueError, match="frame 5"):
        for item in Prefetcher(source(), size=2):
            got.append(item)
    assert got == [0, 1, 2, 3, 4]


def test_prefetcher_reads_at_most_its_size_ahead_and_closes_the_source():
    read, closed = [], threading.Event()

    def source():
        try:
            for i in range(100):
                read.append(i)
                yield i
        finally:
            closed.set()

    with Prefetcher(source(), size=3) as items:
        assert next(items) == 0
        for _ in range(50):  # let the thread fill the queue
            if len(read) >= 5:
                break
            threading.Event().wait(0.01)
        assert len(read) <= 1 + 3 + 1  # consumed + queued + the one waiting to be put
    assert closed.wait(2.0)  # the consumer stopped early: the source was closed (a video would be released)
    assert not any(t.name == "massviz-prefetch" and t.is_alive() for t in threading.enumerate())


# ------------------------------------------------------------------------------------------------------- CUDA
@pytest.mark.slow
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU")
def test_cuda_fp16_batches_run_and_are_recorded(weights_file, recording):
    """fp16 on CUDA: a batch of frames runs and says so in the cache key. What fp32 guarantees on CUDA (deterministic,
    batches within float rounding of single frames) is tests/test_device_path.py's."""
    frames = [recording.read_frame(i) for i in (0, 9, 18)]
    fp16 = rig_sizes(MaskRCNNDetector(weights=weights_file, device="cuda", precision="fp16"), recording.width,
                     recording.height)
    out = fp16.detect_batch([Frame(f.index, f.rgb, f.depth) for f in frames])
    assert len(out) == 3 and fp16.settings()["precision"] == "fp16" and fp16.settings()["device"] == "cuda"
    assert fp16.default_batch == 8


# ----------------------------------------------------------------------------------- RoIAlign, mass CNN, tracker
def _rois(n: int, width: float, height: float, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    xy = torch.rand(n, 2, generator=g) * torch.tensor([width, height])
    wh = torch.rand(n, 2, generator=g) * torch.tensor([width, height]) * 0.4 + 0.01
    boxes = torch.cat([xy, xy + wh], 1)
    edge = torch.tensor([[-10.0, -10.0, 3.0, 4.0], [width - 5, height - 5, width + 60, height + 40],
                         [0.0, 0.0, width, height], [5.0, 5.0, 5.3, 5.2], [width - 1, height - 1, width, height]])
    boxes = torch.cat([edge, boxes])
    return torch.cat([torch.randint(0, 2, (len(boxes), 1), generator=g).float(), boxes], 1)


@pytest.mark.parametrize("output_size,sampling_ratio,scale", [((7, 7), 2, 0.25), ((14, 14), 2, 0.125),
                                                              ((7, 5), 1, 0.5), ((3, 4), 3, 1.0)])
def test_channels_last_roi_align_equals_torchvision_up_to_float_rounding(output_size, sampling_ratio, scale):
    from torchvision.ops import roi_align

    from massviz.detect.roialign import roi_align_channels_last

    torch.manual_seed(0)
    x = torch.randn(2, 16, 37, 53)
    rois = _rois(300, 53 / scale, 37 / scale)
    expected = roi_align(x, rois, output_size, scale, sampling_ratio, aligned=False)
    for feats in (x, x.contiguous(memory_format=torch.channels_last)):
        got = roi_align_channels_last(feats, rois, output_size, scale, sampling_ratio)
        assert got.shape == expected.shape
        torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-5)
    assert roi_align_channels_last(x, rois[:0], output_size, scale, sampling_ratio).shape == (0, 16, *output_size)
    with pytest.raises(ValueError, match="sampling_ratio"):
        roi_align_channels_last(x, rois, output_size, scale, 0)


def test_channels_last_multiscale_pool_equals_torchvision_on_every_level():
    from collections import OrderedDict

    from torchvision.ops import MultiScaleRoIAlign

    from massviz.detect.roialign import ChannelsLastMultiScaleRoIAlign

    torch.manual_seed(0)
    sizes = [(64, 96), (32, 48), (16, 24), (8, 12)]
    x = OrderedDict((str(i), torch.randn(2, 8, h, w).contiguous(memory_format=torch.channels_last))
                    for i, (h, w) in enumerate(sizes))
    rois = _rois(400, 384, 256)
    boxes = [rois[rois[:, 0] == i, 1:] for i in range(2)]
    shapes = [(256, 384), (256, 384)]
    stock = MultiScaleRoIAlign(["0", "1", "2", "3"], 7, 2)
    expected = stock(x, boxes, shapes)
    levels = stock.map_levels(boxes)
    assert len(torch.unique(levels)) >= 3  # small and large boxes: several FPN levels are pooled
    fast = ChannelsLastMultiScaleRoIAlign(MultiScaleRoIAlign(["0", "1", "2", "3"], 7, 2))
    torch.testing.assert_close(fast(x, boxes, shapes), expected, rtol=1e-5, atol=1e-5)


@pytest.mark.slow
def test_fast_runtime_pools_with_the_gather_and_still_matches_torchvision(weights_file, recording):
    from massviz.detect.roialign import ChannelsLastMultiScaleRoIAlign

    det = detector(weights_file, recording)
    assert isinstance(det.runtime.roi_heads.box_roi_pool, ChannelsLastMultiScaleRoIAlign)
    assert isinstance(det.runtime.roi_heads.mask_roi_pool, ChannelsLastMultiScaleRoIAlign)
    assert not isinstance(det.model.roi_heads.box_roi_pool, ChannelsLastMultiScaleRoIAlign)  # torchvision's own


@pytest.mark.slow
def test_mass_cnn_eval_forward_is_bit_identical_to_the_papers_forward(mass_model):
    """ReLU/BatchNorm moved after the max-pool (monotone per channel, negated convolutions for the norms with a
    negative weight) gives the very same numbers, in both memory formats."""
    from massviz.core.model import MassNet

    published = mass_model.net
    assert any((b.weight < 0).any() for _, b in published._blocks())  # the published weights have both signs
    torch.manual_seed(0)
    random = MassNet().eval()
    with torch.no_grad():
        for _, bn in random._blocks():  # both signs and zeros, non-trivial statistics
            bn.weight.uniform_(-1, 1)
            bn.weight[0] = 0.0
            bn.running_mean.uniform_(-0.5, 0.5)
            bn.running_var.uniform_(0.5, 2.0)
    images = torch.rand(9, 3, 112, 112)
    features = torch.rand(9, 3)
    for model in (published, random):
        with torch.inference_mode():
            expected = model(images, features)
            assert torch.equal(model.forward_eval(images, features), expected)
            cl = images.contiguous(memory_format=torch.channels_last)
            model.to(memory_format=torch.channels_last)
            assert torch.equal(model.forward_eval(cl, features), model(cl, features))
    random.train()
    with pytest.raises(RuntimeError, match="eval mode"):
        random.forward_eval(images, features)


@pytest.mark.slow
@pytest.mark.skipif(not bf16_supported(), reason="this CPU has no bfloat16 support")
def test_mass_cnn_precision_changes_its_id_and_stays_close(weights):
    from massviz.io.checkpoint import load_checkpoint

    fp32, bf16 = load_checkpoint(weights), load_checkpoint(weights).set_precision("bf16")
    assert bf16.weights_id == fp32.weights_id + "+bf16" and bf16.precision == "bf16"
    assert bf16.set_precision("bf16").weights_id == fp32.weights_id + "+bf16"  # not appended twice
    rng = np.random.default_rng(0)
    patches = [rng.integers(0, 256, (int(rng.integers(20, 120)), int(rng.integers(20, 120)), 3), dtype=np.uint8)
               for _ in range(20)]
    feats = np.c_[rng.uniform(0.05, 0.3, (20, 2)), rng.uniform(400, 900, 20)]
    a, b = fp32.predict(patches, feats), bf16.predict(patches, feats)
    assert not np.array_equal(a, b)  # it did run in bf16
    np.testing.assert_allclose(b, a, rtol=0.1, atol=2.0)
    assert load_checkpoint(weights).set_precision("fp16").weights_id == fp32.weights_id  # fp16: stays fp32


@pytest.mark.slow
def test_a_model_built_for_loaded_weights_skips_random_init_and_is_the_same_model(weights_file):
    from massviz.detect.maskrcnn import _construct, build_model

    loaded = build_model(0.4, weights_file)
    stock = _construct(0.4, skip_init=False)
    stock.load_state_dict(torch.load(weights_file, weights_only=True))
    assert not any(t.is_meta for t in [*loaded.parameters(), *loaded.buffers()])
    a, b = loaded.state_dict(), stock.state_dict()
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    cells_a, cells_b = loaded.rpn.anchor_generator.cell_anchors, stock.rpn.anchor_generator.cell_anchors
    assert len(cells_a) == len(cells_b) == 5
    assert all(x.device.type == "cpu" and torch.equal(x, y) for x, y in zip(cells_a, cells_b, strict=False))
    image = torch.rand(3, 90, 160)
    loaded.transform.min_size, loaded.transform.max_size = (90,), 160
    stock.transform.min_size, stock.transform.max_size = (90,), 160
    with torch.inference_mode():
        out_a, out_b = loaded([image])[0], stock.eval()([image])[0]
    assert torch.equal(out_a["boxes"], out_b["boxes"]) and torch.equal(out_a["scores"], out_b["scores"])
