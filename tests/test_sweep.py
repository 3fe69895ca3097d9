"""Threshold × K sweeps: equal to reselecting every trace and scoring, and never re-running a detector."""
from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from massviz.core.trace import Trace
from massviz.core.types import Detections
from massviz.errors import MassvizError
from massviz.evaluation.metrics import score_from_estimates
from massviz.evaluation.sweep import SweepTable, annotations_from_meta, best_pair, parse_range, sweep
from massviz.views.score_plot import plot_heatmap


def make_trace(rng, n, mass, cls="cup", detect_threshold=0.3, rec_id="r"):
    d = rng.uniform(300, 1500, n)
    d[rng.random(n) < 0.1] = np.nan  # masks without depth
    d[:2] = 500.0  # a tie
    dets = Detections(frame=np.arange(n) // 2, xyxy=np.tile([0, 0, 4, 4], (n, 1)),
                      score=rng.uniform(detect_threshold + 1e-3, 1, n), class_id=np.full(n, 47),
                      masks=[np.ones((4, 4), bool)] * n, d=d, a=np.full(n, .1), b=np.full(n, .2),
                      pred=rng.uniform(1, 150, n))
    t = Trace(recording={"id": rec_id, "config_id": rec_id, "meta": {"container": {"mass_g": mass, "class": cls}}},
              detector={"name": "fake"}, detect_threshold=detect_threshold, threshold=detect_threshold, k=5, stride=1,
              frames=np.arange(n // 2 + 1), detections=dets, selection=np.zeros(0, np.int64), estimate=-1.0)
    return t.reselect()


@pytest.fixture
def traces():
    rng = np.random.default_rng(7)
    out = [make_trace(rng, n, m, c, rec_id=f"rec{i}") for i, (n, m, c) in
           enumerate([(12, 20.0, "cup"), (30, 80.0, "box"), (1, 5.0, "glass"), (9, 50.0, "cup")])]
    out.append(make_trace(rng, 0, 10.0, "glass", rec_id="empty"))  # nothing detected: not estimated
    return out


def test_parse_range():
    assert parse_range("0.3:0.5:0.1") == [0.3, 0.4, 0.5]
    assert parse_range("1:4", int) == [1, 2, 3, 4]
    assert parse_range("1,3,5", int) == [1, 3, 5]
    assert parse_range("0.4") == [0.4]
    assert len(parse_range("0.3:0.9:0.05")) == 13
    for bad in ("a:b", "0.5:0.3", "1:2:0", "1:2:3:4"):
        with pytest.raises(MassvizError):
            parse_range(bad)


def test_estimates_equal_reselect(traces):
    table = SweepTable(traces)
    for thr in (0.3, 0.45, 0.8, 0.99):
        for k in (1, 2, 5, 40):
            expected = [t.reselect(k=k, threshold=thr).estimate for t in traces]
            np.testing.assert_allclose(table.estimates(thr, k), expected, rtol=1e-12)


def test_sweep_scores_equal_evaluate(traces):
    thresholds, ks = [0.3, 0.5, 0.7], [1, 3, 10]
    table = sweep(traces, thresholds, ks)
    ann, classes = annotations_from_meta(traces)
    assert len(table) == 9
    for _, row in table.iterrows():
        est = {i: t.reselect(k=int(row.k), threshold=row.threshold).estimate for i, t in enumerate(traces)}
        report = score_from_estimates(est, ann, classes)
        assert row.score == pytest.approx(100 * report.score, abs=1e-9)
        assert row.estimated == report.n_estimated
    # by hand for one pair: K=1 at 0.3 → the nearest finite-d prediction of each recording
    expected = []
    for t in traces:
        d, p = t.detections.d, t.detections.pred
        ok = np.flatnonzero(np.isfinite(d))
        if len(ok) == 0:
            expected.append(0.0)
            continue
        m = t.ground_truth_mass
        expected.append(math.exp(-abs(p[ok[np.argmin(d[ok])]] - m) / m))
    assert table.query("threshold == 0.3 and k == 1").score.iloc[0] == pytest.approx(100 * np.mean(expected))


def test_sweep_with_annotation_file_matches_ids(traces):
    for i, t in enumerate(traces):
        t.recording.config_id = str(100 + i)
    ann = pd.DataFrame({"id": [100, 101, 999], "container id": [1, 7, 4], "container mass": [20.0, 80.0, 9.0]})
    table = sweep(traces, [0.3], [5], ann)
    est = {100: traces[0].reselect(k=5).estimate, 101: traces[1].reselect(k=5).estimate}
    assert table.score.iloc[0] == pytest.approx(100 * score_from_estimates(est, ann).score)
    assert table.estimated.iloc[0] == 2  # id 999 is not in the dataset: not estimated


def test_threshold_below_traces_refused(traces):
    with pytest.raises(MassvizError, match="below"):
        SweepTable(traces).estimates(0.1, 5)


def test_heatmap_written(traces, tmp_path):
    table = sweep(traces, parse_range("0.3:0.9:0.05"), parse_range("1:10", int))
    assert len(table) == 130
    best = best_pair(table)
    assert best.score == table.score.max()
    out = plot_heatmap(table, tmp_path / "heat.png")
    assert out.stat().st_size > 5000
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]
