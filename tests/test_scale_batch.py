"""The mass CNN batches patches across frames: ``run(..., batch=N)`` predicts the patches of N frames in
one ``MassPredictor.predict_groups`` call, and every prediction and estimate stays bit for bit what one call per frame
gives (on the samples and CCM 618), because a row of the convolutions does not depend on the other rows of a call of
two rows or more, and the head runs on each frame's own rows (see ``MassPredictor.predict_groups``)."""
from __future__ import annotations

import numpy as np
import pytest

from massviz.core.pipeline import run
from support import samples_and_618

#: the frontal camera of CCM recording 618 (as tests/test_scale.py)
INTR_618 = {"fx": 923.3, "fy": 923.3, "cx": 640.0, "cy": 360.0, "width": 1280, "height": 720}



def _patches(n_groups: int, seed: int = 0):
    """Random crops of a sample frame and random features: groups of 0, 1, 2, 16, 17 and 33 patches (a call of
    one row, a full call, a lone last row)."""
    from massviz.core.patches import crop

    rng = np.random.default_rng(seed)
    rgb = rng.integers(0, 256, (360, 640, 3), dtype=np.uint8)
    out = []
    sizes = [3, 1, 17, 0, 2, 16, 1, 33, 5, 1, 2, 4]
    for j in range(n_groups):
        n = sizes[j % len(sizes)]
        boxes = [(x, y, x + int(rng.integers(8, 150)), y + int(rng.integers(8, 150)))
                 for x, y in zip(rng.integers(0, 480, n), rng.integers(0, 200, n), strict=False)]
        feats = np.stack([rng.uniform(0.05, 0.3, n), rng.uniform(0.05, 0.3, n), rng.uniform(300, 900, n)], axis=1)
        out.append(([crop(rgb, np.array(b)) for b in boxes], feats))
    return out


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_predict_groups_is_predict_per_group_bit_for_bit(model, precision):
    import copy

    m = copy.deepcopy(model).set_precision(precision)
    groups = _patches(14)
    assert {len(p) for p, _ in groups} >= {1, 17}
    want = [m.predict(p, f) for p, f in groups]
    for size in (2, 5, 14):
        got = [x for s in range(0, len(groups), size) for x in m.predict_groups(groups[s:s + size])]
        assert len(got) == len(want)
        for g, w in zip(got, want, strict=False):
            assert g.dtype == w.dtype and np.array_equal(g, w)  # equal, not close
    # the convolutions of one patch alone do differ from in company: why predict_groups keeps lone rows alone
    p, f = next((p, f) for p, f in groups if len(p) >= 2)
    alone = np.array([m.predict([p[i]], f[i:i + 1])[0] for i in range(len(p))])
    print(f"{precision}: one patch per call vs {len(p)} per call: max |diff| {np.abs(alone - m.predict(p, f)).max():.3g} g")


def test_calls_cover_every_row_once_for_any_group_and_call_size():
    """Any rows (several groups' rows, in any sizes) cut into calls: every row exactly once, in order, no call of
    one row when there are two rows or more, no call over size + 1 rows."""
    from massviz.core.predictor import _calls

    rng = np.random.default_rng(0)
    for _ in range(3000):
        size = int(rng.integers(1, 40))
        groups = rng.integers(0, 3 * size + 3, int(rng.integers(0, 6)))
        rows = [(g, r) for g, n in enumerate(groups) for r in range(int(n))]
        calls = _calls(rows, size)
        assert [row for call in calls for row in call] == rows, (size, groups)
        assert all(1 <= len(c) <= size + 1 for c in calls), (size, groups, [len(c) for c in calls])
        if size > 1 and len(rows) > 1:
            assert all(len(c) >= 2 for c in calls), (size, groups, [len(c) for c in calls])


@pytest.mark.parametrize("sizes", [(20, 13), (10, 7), (16, 1, 16, 1), (2, 15), (31, 2), (9, 8, 16)])
def test_groups_whose_rows_sum_to_16n_plus_1_are_predicted(model, sizes):
    """Several frames' rows summing to 16n+1 (a lone last row of the joint calls) once lost or duplicated rows
    (KeyError / IndexError): each group is predicted, equal to predict on it alone."""
    rng = np.random.default_rng(sum(sizes))
    groups = [([rng.integers(0, 256, (int(rng.integers(8, 90)), int(rng.integers(8, 90)), 3), dtype=np.uint8)
                for _ in range(n)],
               np.stack([rng.uniform(0.05, 0.3, n), rng.uniform(0.05, 0.3, n), rng.uniform(300, 900, n)], axis=1))
              for n in sizes]
    got = model.predict_groups(groups, 16)
    assert [len(g) for g in got] == list(sizes)
    for g, (p, f) in zip(got, groups, strict=False):
        assert np.array_equal(g, model.predict(p, f))


@pytest.fixture(scope="module")
def recordings(tmp_path_factory, shared_dir, samples_dir):
    from massviz.io.recording import find_recordings, open_recording

    root = samples_and_618(tmp_path_factory.mktemp("batch") / "ds", shared_dir, samples_dir, INTR_618)
    return [open_recording(p) for p in find_recordings(root)]


@pytest.mark.slow
def test_batched_runs_predict_across_frames_and_equal_batch_1(recordings, model, monkeypatch):
    from massviz.detect import make_detector

    assert sorted(r.id for r in recordings) == ["618", "box_handover", "cup_handover", "glass_handover"]
    sizes = []
    real = type(model).predict_groups

    def counting(self, groups, batch_size=16):
        sizes.append(len(groups))
        return real(self, groups, batch_size)

    for rec in recordings:
        det = make_detector("depth", 0.4, quiet=True)
        one = run(rec, det, model, k=5, batch=1, prefetch=0)
        monkeypatch.setattr(type(model), "predict_groups", counting)
        sizes.clear()
        four = run(rec, det, model, k=5, batch=4, prefetch=0)
        monkeypatch.undo()
        a, b = one.detections, four.detections
        assert np.isfinite(a.pred).sum() >= 2, rec.id
        for name in ("frame", "xyxy", "score", "d", "a", "b", "pred"):
            assert np.array_equal(getattr(a, name), getattr(b, name), equal_nan=True), (rec.id, name)
        assert np.array_equal(one.selection, four.selection) and one.estimate == four.estimate, rec.id
        assert max(sizes) > 1, (rec.id, sizes)  # several frames' patches in one call
        print(f"{rec.id}: {len(one.frames)} frames, {int(np.isfinite(a.pred).sum())} predictions, "
              f"estimate {one.estimate!r} g; predict calls with batch 4: {len(sizes)} (frames per call {sizes})")


class CrowdDetector:
    """~100 detections a frame (as a GPU run of Mask R-CNN keeps), boxes and masks drawn from the frame index:
    100 a frame, 101 on every 4th processed frame, so that 4 frames' joint rows are 16n + 1."""

    name, threshold = "crowd", 0.4

    def settings(self) -> dict:
        return {}

    def detect(self, frame):
        from massviz.core.types import Detections

        rng = np.random.default_rng(frame.index)
        n = 101 if frame.index % 16 == 12 else 100
        h, w = frame.depth.shape
        xy = rng.integers(0, [w - 40, h - 40], (n, 2))
        box = np.concatenate([xy, xy + rng.integers(8, 40, (n, 2))], 1)
        masks = [rng.random((y2 - y1, x2 - x1)) < 0.7 for x1, y1, x2, y2 in box]
        return Detections(frame=np.full(n, frame.index), xyxy=box, score=rng.uniform(0.41, 1.0, n),
                          class_id=np.full(n, 47), masks=masks)


@pytest.mark.slow
def test_batch_4_equals_batch_1_at_100_detections_a_frame(samples_dir, model):
    from massviz.io.recording import open_recording

    rec = open_recording(samples_dir / "box_handover")
    one = run(rec, CrowdDetector(), model, k=5, stride=4, batch=1, prefetch=0)
    four = run(rec, CrowdDetector(), model, k=5, stride=4, batch=4, prefetch=0)
    assert len(one.frames) >= 8 and len(one.detections) >= 90 * len(one.frames)
    for name in ("xyxy", "d", "pred"):
        assert np.array_equal(getattr(one.detections, name), getattr(four.detections, name), equal_nan=True), name
    assert np.isfinite(one.detections.pred).sum() > 500
    assert np.array_equal(one.selection, four.selection) and one.estimate == four.estimate
