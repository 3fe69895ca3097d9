"""massviz.core.pipeline / trace / cache: a run's trace against values computed by hand, persistence, reselection and
the trace cache (which must never run the detector again for another K, a higher threshold or another model)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from fakes import DETECTIONS, SCENE_H, SCENE_N, SCENE_W, DistanceModel, ListDetector, scene
from massviz.app import PipelineOptions, process
from massviz.core.pipeline import FramePipeline, run
from massviz.core.selection import Selection
from massviz.core.trace import Trace
from massviz.errors import MassvizError
from massviz.io.cache import TraceCache
from massviz.io.checkpoint import load_checkpoint
from massviz.io.trace_file import load_trace, save_trace

W, H, N = SCENE_W, SCENE_H, SCENE_N




@pytest.fixture(scope="module")
def other_model(weights):
    return load_checkpoint(weights.with_name("Encoder_pool_aug_fold0_94.torch"))


@pytest.fixture
def fast():
    """A stand-in model (d / 10 grams) for the tests about selection and caching, not about the CNN."""
    return DistanceModel()



def expected(model, threshold: float, k: int, stride: int = 1):
    """(rows, preds, estimate) computed from the scene itself: rows are (frame, box, d) of each detection."""
    rgbs, depths = scene()
    rows = [(f, box, float(depths[f][box[1], box[0]])) for f in range(0, N, stride)
            for box, score, _ in DETECTIONS.get(f, []) if np.float32(score) > threshold]
    patches = [rgbs[f][y1:y2, x1:x2] for f, (x1, y1, x2, y2), _ in rows]
    feats = [[round((b[2] - b[0]) / W, 2), round((b[3] - b[1]) / H, 2), d] for _, b, d in rows]
    preds = model.predict(patches, np.array(feats))
    nearest = sorted(range(len(rows)), key=lambda i: (rows[i][2], i))[:k]
    est = float(np.mean(preds[nearest].astype(np.float64))) if nearest else -1.0
    return rows, preds, est


def same_selection(a: Trace, b: Trace) -> bool:
    """Same chosen detections (frame and box, in order) in two traces whose detection lists may differ."""
    pick = lambda t: [(int(t.detections.frame[i]), t.detections.xyxy[i].tolist()) for i in t.selection]  # noqa
    return pick(a) == pick(b)


# ------------------------------------------------------------------------------------------------------------ run
@pytest.mark.slow
def test_run_builds_the_trace(rec, model):
    trace = run(rec, ListDetector(DETECTIONS), model, k=3)
    rows, preds, est = expected(model, 0.4, 3)
    dets = trace.detections
    assert trace.frames.tolist() == list(range(N))
    assert [(int(f), b.tolist(), float(d)) for f, b, d in zip(dets.frame, dets.xyxy, dets.d, strict=False)] == \
        [(f, list(b), d) for f, b, d in rows]
    np.testing.assert_allclose(dets.pred, preds, rtol=1e-5)
    assert len(trace.selection) == 3
    assert trace.estimate == pytest.approx(est, rel=1e-5)
    assert trace.estimate == pytest.approx(float(np.mean(dets.pred[trace.selection])), rel=1e-6)
    assert (trace.k, trace.threshold, trace.detect_threshold, trace.stride) == (3, 0.4, 0.4, 1)
    assert trace.weights_id == model.weights_id and trace.recording.id == "scene"
    assert {"read", "detect", "features", "predict", "select", "total"} <= set(trace.timings)


def test_the_selection_travels_explicitly_and_step_changes_no_detector_output(rec, fast):
    # one Selection value from the options to FramePipeline and the trace; the detector keeps only its score cut
    assert PipelineOptions(threshold=0.5, k=3, stride=2).selection == Selection(k=3, threshold=0.5, stride=2)
    det = ListDetector(DETECTIONS, threshold=0.4)
    sel = Selection(k=2, threshold=0.6, exclude=[1])
    trace = run(rec, det, fast, selection=sel)
    assert (trace.k, trace.threshold, trace.detect_threshold, trace.excluded.tolist()) == (2, 0.6, 0.4, [1])
    assert trace.selection_params == sel and det.threshold == 0.4
    same = run(rec, ListDetector(DETECTIONS), fast, k=2).reselect(threshold=0.6, exclude=[1])
    assert trace.selection.tolist() == same.selection.tolist() and len(trace.selection) == 2
    assert 1 not in trace.selection.tolist() and trace.estimate == same.estimate
    with pytest.raises(ValueError, match="below the score cut 0.4 of the detector"):
        FramePipeline(det, fast, selection=Selection(threshold=0.3))
    with pytest.raises(ValueError, match="not both"):
        FramePipeline(det, fast, selection=sel, k=3)
    # step returns new arrays: the detector's Detections stay as it made them; the running estimate skips exclusions
    fp = FramePipeline(det, fast, selection=sel, recording=rec.info())
    running = []
    for frame in rec.frames():
        raw = det.detect(frame)
        out = fp.step(frame)
        assert np.isnan(raw.d).all() and np.isnan(raw.pred).all() and (raw.track == 0).all()
        assert len(out.detections) == len(raw) and np.isfinite(out.detections.d).all() and out.detections is not raw
        running.append(out.running_estimate)
    stepped = fp.finish()
    assert stepped.selection.tolist() == trace.selection.tolist() and running[-1] == stepped.estimate
    np.testing.assert_array_equal(running, stepped.running_estimate())


def test_run_with_stride(rec, model):
    det = ListDetector(DETECTIONS)
    trace = run(rec, det, model, k=5, stride=2)
    rows, _, est = expected(model, 0.4, 5, stride=2)
    assert trace.frames.tolist() == [0, 2, 4] and det.calls == 3
    assert len(trace.detections) == len(rows) and trace.estimate == pytest.approx(est, rel=1e-5)


def test_trace_save_load_round_trip(rec, model, tmp_path):
    trace = run(rec, ListDetector(DETECTIONS), model, k=2).reselect(exclude=[0])
    back = load_trace(save_trace(trace, tmp_path / "t.npz"))
    a, b = trace.detections, back.detections
    for name in ("frame", "xyxy", "score", "class_id", "d", "a", "b", "pred"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    for i in range(len(a)):
        np.testing.assert_array_equal(a.mask(i), b.mask(i))
        assert (a.patches[i] is None) == (b.patches[i] is None)
        if a.patches[i] is not None:
            np.testing.assert_array_equal(a.patches[i], b.patches[i])
    assert sum(p is not None for p in b.patches) == len(b)  # 10 detections < KEEP_PATCHES: all kept
    assert back.events == trace.events and back.timings == trace.timings
    assert back.selection.tolist() == trace.selection.tolist() and back.excluded.tolist() == [0]
    assert (back.estimate, back.k, back.threshold, back.weights_id) == (trace.estimate, 2, 0.4, model.weights_id)
    assert back.recording == trace.recording and back.detector == trace.detector


def test_trace_load_of_an_incomplete_file_names_it(rec, fast, tmp_path):
    path = save_trace(run(rec, ListDetector(DETECTIONS), fast, k=2), tmp_path / "t.npz")
    with np.load(path) as z:
        arrays = {name: z[name] for name in z.files if name != "mask_sizes"}
    np.savez(path, **arrays)  # a valid header without one of the arrays
    with pytest.raises(MassvizError, match=r"t\.npz: not a complete massviz trace \(KeyError"):
        load_trace(path)


def test_reselect_equals_a_fresh_run(rec, fast):
    model = fast
    base = run(rec, ListDetector(DETECTIONS, threshold=0.4), model, k=5)
    for k, t in ((1, 0.4), (2, 0.55), (4, 0.7), (5, 0.95)):
        fresh = run(rec, ListDetector(DETECTIONS, threshold=t), model, k=k)
        again = base.reselect(k=k, threshold=t)
        assert same_selection(again, fresh), (k, t)
        assert again.estimate == pytest.approx(fresh.estimate, rel=1e-6), (k, t)
        assert again.estimate == pytest.approx(expected(model, t, k)[2], rel=1e-5), (k, t)
        assert [(e.kind, e.message) for e in again.events] == [(e.kind, e.message) for e in fresh.events], (k, t)  # the log describes the new selection
    with pytest.raises(MassvizError, match="below the score cut 0.4 of this trace"):
        base.reselect(threshold=0.3)


def test_keep_patches_keeps_only_the_nearest(rec, fast):
    model = fast
    trace = run(rec, ListDetector(DETECTIONS), model, k=2, keep_patches=3)
    d = trace.detections.d
    kept = [i for i, p in enumerate(trace.detections.patches) if p is not None]
    assert kept == sorted(np.argsort(d, kind="stable")[:3].tolist())
    rgbs, _ = scene()
    for i in kept:
        x1, y1, x2, y2 = trace.detections.xyxy[i]
        np.testing.assert_array_equal(trace.detections.patches[i], rgbs[trace.detections.frame[i]][y1:y2, x1:x2])
    assert len(kept) == 3 < len(d)
    assert len([p for p in run(rec, ListDetector(DETECTIONS), model, k=4, keep_patches=1).detections.patches
                if p is not None]) == 4  # never fewer than K


# ---------------------------------------------------------------------------------------------------------- cache
def test_cache_reuses_detections(rec, fast, tmp_path):
    model = fast
    cache = TraceCache(tmp_path / "cache")
    det = ListDetector(DETECTIONS, threshold=0.4)
    first = process(rec, det, model, k=5, cache=cache)
    assert det.calls == N and len(list((tmp_path / "cache").rglob("*.npz"))) == 1

    # another K: the detector does not run, the result is a fresh run's
    second = process(rec, det, model, k=2, cache=cache)
    assert det.calls == N
    fresh = run(rec, ListDetector(DETECTIONS), model, k=2)
    assert same_selection(second, fresh) and second.estimate == pytest.approx(fresh.estimate, rel=1e-6)
    assert any("reused cached detections" in e.message and e.kind == "cache" and e.level == "debug" for e in second.events)
    assert first.estimate != second.estimate

    # a higher threshold reuses the entry made at the lower one
    high = ListDetector(DETECTIONS, threshold=0.75)
    third = process(rec, high, model, k=3, cache=cache)
    assert high.calls == 0
    fresh = run(rec, ListDetector(DETECTIONS, threshold=0.75), model, k=3)
    assert same_selection(third, fresh) and third.estimate == pytest.approx(fresh.estimate, rel=1e-6)
    assert third.threshold == 0.75 and third.detect_threshold == 0.4

    # a threshold below every cached one needs the detector again
    low = ListDetector(DETECTIONS, threshold=0.2)
    process(rec, low, model, k=5, cache=cache)
    assert low.calls == N


def test_an_empty_box_is_kept_skipped_saved_and_served_from_the_cache(rec, fast, tmp_path):
    """A box less than a pixel wide or high, cut to integers (random-weight Mask R-CNN makes them), has no pixel: the
    trace keeps it, skipped for having no depth, and its file loads back, so the cache serves it (a trace file refused
    on loading would be dropped and the recording detected again on every run)."""
    dets = {0: [((7, 12, 7, 30), 0.95, None), ((5, 10, 30, 40), 0.9, None)], 1: [((40, 5, 60, 5), 0.8, None)]}
    cache = TraceCache(tmp_path / "cache")
    det = ListDetector(dets, threshold=0.4)
    first = process(rec, det, fast, k=5, cache=cache)
    empty = [i for i, (x1, y1, x2, y2) in enumerate(first.detections.xyxy) if x1 == x2 or y1 == y2]
    assert len(empty) == 2 and not np.isfinite(first.detections.d[empty]).any()
    assert sum("its mask has no depth" in e.message for e in first.events) == 2
    assert len(first.selection) == 1 and first.estimate > 0
    again = process(rec, det, fast, k=5, cache=cache)
    assert det.calls == N and [e for e in again.events if e.kind == "cache"]  # from the cache: no detection again
    assert again.detections.xyxy.tolist() == first.detections.xyxy.tolist() and again.estimate == first.estimate
    assert len(list((tmp_path / "cache").rglob("*.npz"))) == 1


@pytest.mark.slow
def test_cache_another_model_repredicts_without_detecting(rec, model, other_model, tmp_path):
    cache = TraceCache(tmp_path / "cache")
    det = ListDetector(DETECTIONS, threshold=0.4)
    first = process(rec, det, model, k=5, cache=cache)
    assert det.calls == N
    counted = []
    real_predict = other_model.predict
    other_model.predict = lambda p, f: counted.append(len(p)) or real_predict(p, f)
    try:
        fourth = process(rec, ListDetector(DETECTIONS, threshold=0.4), other_model, k=5, cache=cache)
    finally:
        del other_model.predict
    assert det.calls == N and sum(counted) == len(fourth.detections)
    fresh = run(rec, ListDetector(DETECTIONS), other_model, k=5)
    np.testing.assert_allclose(fourth.detections.pred, fresh.detections.pred, rtol=1e-6)
    assert fourth.weights_id == other_model.weights_id != model.weights_id
    assert fourth.estimate == pytest.approx(fresh.estimate, rel=1e-6) and fourth.estimate != pytest.approx(
        first.estimate)
    # the entry now holds the new model's predictions; the first model gets its own back, still without detecting
    again = process(rec, det, model, k=5, cache=cache)
    assert det.calls == N and again.estimate == pytest.approx(first.estimate, rel=1e-6)


def test_cache_separates_detector_settings_and_stride(rec, fast, tmp_path):
    model = fast
    cache = TraceCache(tmp_path / "cache")
    process(rec, ListDetector(DETECTIONS), model, k=5, cache=cache)
    other = ListDetector({f: v[:1] for f, v in DETECTIONS.items()})  # different detections: different entry
    trace = process(rec, other, model, k=5, cache=cache)
    assert other.calls == N and len(trace.detections) == len(DETECTIONS)
    strided = ListDetector(DETECTIONS)
    assert process(rec, strided, model, k=5, stride=3, cache=cache).frames.tolist() == [0, 3]
    assert strided.calls == 2


# --------------------------------------------------------------------------------------------------------- replay
def test_replay_json_detections(rec, fast, tmp_path):
    import cv2

    from massviz.detect.saved import ReplayDetector
    from massviz.errors import DataError

    mask = np.zeros((H, W), np.uint8)
    mask[12:30, 8:20] = 255  # full-frame mask PNG: only this part of box (5, 10, 30, 40) is the object
    cv2.imwrite(str(tmp_path / "m.png"), mask)
    rows = [{"frame": 1, "box": [5.9, 10, 30, 40], "score": 0.9, "class": "cup", "mask": "m.png"},
            {"frame": 3, "box": [40, 5, 60, 25], "score": 0.3, "class": "bottle"},  # below the threshold
            {"frame": 3, "box": [40, 5, 60, 25], "class": 84}]
    (tmp_path / "d.json").write_text(json.dumps({"detections": rows}))
    trace = run(rec, ReplayDetector(tmp_path / "d.json", threshold=0.4), fast, k=5)
    dets = trace.detections
    assert dets.frame.tolist() == [1, 3] and dets.class_id.tolist() == [47, 84]
    assert dets.xyxy.tolist() == [[5, 10, 30, 40], [40, 5, 60, 25]]  # floats truncated
    np.testing.assert_array_equal(dets.mask(0), mask[10:40, 5:30] > 0)
    assert dets.mask(1).all() and dets.score[1] == 1.0
    np.testing.assert_array_equal(dets.d, [1500 - 70, 900 + 150])

    # a box that does not fit this recording's frames is a data error naming the replay file, not a crash
    rows.append({"frame": 5, "box": [50, 30, 70, 50], "score": 0.9})
    (tmp_path / "d.json").write_text(json.dumps({"detections": rows}))
    with pytest.raises(DataError, match=r"box \[50, 30, 70, 50\] lies outside the 64x48 frame") as info:
        run(rec, ReplayDetector(tmp_path / "d.json"), fast)
    assert str(info.value).startswith(f"{tmp_path / 'd.json'}: ")

    # a mask PNG that is neither box-sized nor a full frame holding the box is a data error, not a silent empty mask
    cv2.imwrite(str(tmp_path / "small.png"), np.full((20, 20), 255, np.uint8))
    rows = [{"frame": 1, "box": [5, 10, 30, 40], "score": 0.9, "mask": "small.png"}]
    (tmp_path / "d.json").write_text(json.dumps({"detections": rows}))
    with pytest.raises(DataError, match=r"detection 0: mask small.png declares 20x20 pixels, neither the box's 25x30"):
        ReplayDetector(tmp_path / "d.json")


def test_cache_keeps_thresholds_exact(rec, fast, tmp_path):
    """Entries are named by their exact threshold: one made at 0.40005 serves 0.40005 but never 0.40001."""
    cache = TraceCache(tmp_path / "cache")
    made = ListDetector(DETECTIONS, threshold=0.40005)
    process(rec, made, fast, k=5, cache=cache)
    again = ListDetector(DETECTIONS, threshold=0.40005)
    process(rec, again, fast, k=5, cache=cache)
    assert made.calls == N and again.calls == 0
    lower = ListDetector(DETECTIONS, threshold=0.40001)
    trace = process(rec, lower, fast, k=5, cache=cache)
    assert lower.calls == N and trace.detect_threshold == 0.40001


def test_mask_that_does_not_fit_its_box_is_refused():
    from massviz.core.features import mask_distance

    depth = np.full((10, 10), 1000, np.uint16)
    assert mask_distance(depth, (2, 2, 6, 5), np.ones((3, 4), bool)) == 1000.0
    with pytest.raises(ValueError, match="does not fit box"):
        mask_distance(depth, (2, 2, 6, 5), np.ones((4, 3), bool))


# ---------------------------------------------------------------------------------------------- the per-frame step
def test_frame_step_running_selection_equals_a_selection_over_the_frames_so_far(rec, fast):
    from massviz.core.pipeline import FramePipeline
    from massviz.core.selection import estimate_mass, select_k_nearest

    det = ListDetector(DETECTIONS, threshold=0.5)
    fp = FramePipeline(det, fast, k=3, recording=rec.info())
    results = [fp.step(frame) for frame in rec.frames()]
    trace = fp.finish()
    d, score = trace.detections.d, trace.detections.score
    for r in results:
        so_far = r.offset + len(r.detections)
        expected = select_k_nearest(d[:so_far], score[:so_far], 3, 0.5)
        assert r.selection.tolist() == expected.tolist(), r.frame.index
        assert r.running_estimate == estimate_mass(trace.detections.pred, expected)
        assert set(r.timings) == {"read", "detect", "features", "predict", "select"}
    assert results[-1].selection.tolist() == trace.selection.tolist()
    assert results[-1].running_estimate == trace.estimate


def test_run_is_a_loop_over_the_step(rec, fast):
    from massviz.core.pipeline import FramePipeline

    det = ListDetector(DETECTIONS, threshold=0.4)
    fp = FramePipeline(det, fast, k=5, stride=2, recording=rec.info())
    for frame in rec.frames(stride=2):
        fp.step(frame)
    stepped, ran = fp.finish(), run(rec, det, fast, k=5, stride=2)
    assert stepped.frames.tolist() == ran.frames.tolist() == [0, 2, 4]
    assert same_selection(stepped, ran) and stepped.estimate == ran.estimate
    assert np.array_equal(stepped.detections.d, ran.detections.d, equal_nan=True)
    assert [(e.kind, e.message) for e in stepped.events] == [(e.kind, e.message) for e in ran.events]


def test_step_takes_what_a_frame_stage_computed_on_a_batch(rec, fast):
    from massviz.core.frame_stage import FrameStage
    from massviz.core.pipeline import FramePipeline

    det = ListDetector(DETECTIONS, threshold=0.4)
    plain, given = (FramePipeline(det, fast, k=5, recording=rec.info()) for _ in range(2))
    frames = list(rec.frames())
    staged = FrameStage(det, fast, batch=3).process(frames[:3]) + FrameStage(det, fast).process(frames[3:])
    for frame, item in zip(frames, staged, strict=False):
        plain.step(frame)
        given.step(frame, staged=item)
    a, b = plain.finish(), given.finish()
    assert same_selection(a, b) and a.estimate == b.estimate
    assert np.array_equal(a.detections.pred, b.detections.pred, equal_nan=True)


def test_builder_makes_the_pipeline_the_cli_uses(weights, tmp_path):
    import massviz as mv

    p = mv.build_pipeline(mv.PipelineOptions(detector="depth", k=3, weights=str(weights), cache=str(tmp_path)))
    assert (p.detector.name, p.options.k, p.model.weights_id) == ("depth", 3, load_checkpoint(weights).weights_id)
    assert isinstance(p.cache, TraceCache) and p.cache.root == tmp_path
    with pytest.raises(MassvizError, match="--k must be >= 1"):
        mv.build_pipeline(detector="depth", k=0, weights=str(weights))
    import argparse

    args = argparse.Namespace(detector="depth", threshold=0.6, k=2, stride=3, weights=weights, detector_weights=None,
                              replay=None, cache=None, no_cache=True, quiet=True, view=3)
    opts = mv.PipelineOptions.from_args(args)
    assert (opts.threshold, opts.k, opts.stride, opts.weights, opts.no_cache) == (0.6, 2, 3, str(weights), True)


def test_a_recording_recognised_but_not_opened_is_served_only_by_the_cache(rec, fast):
    # the warm path's LocatedRecording (file identities, no frames) is told apart by its type
    from pathlib import Path

    from massviz.io.identity import LocatedRecording

    located = LocatedRecording(path=Path(rec.path), id=rec.id, kind="folder", config_id=rec.id,
                               num_frames=rec.num_frames, recording_info=rec.info(), _fingerprint="x")
    det = ListDetector(DETECTIONS)
    with pytest.raises(MassvizError, match="could not be read now"):
        process(located, det, fast, k=3)
    assert det.calls == 0
    assert process(rec, det, fast, k=3, prefetch=0).estimate > 0 and det.calls == N
