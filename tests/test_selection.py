"""massviz.core.features and massviz.core.selection: the per-detection features (d, a, b) and the K-nearest
selection, from first principles.

``ListDetector`` and ``DistanceModel`` (a stand-in mass model whose prediction is a known function of the features)
are also used by test_pipeline.
"""
from __future__ import annotations

import numpy as np
import pytest

from fakes import DistanceModel, ListDetector, write_recording
from massviz.core.features import box_ratios, compute_features, mask_distance
from massviz.core.pipeline import run
from massviz.core.selection import estimate_mass, select_k_nearest
from massviz.core.types import Detections
from massviz.io.recording import open_recording


# ---------------------------------------------------------------------------------------------------------- features
def test_d_is_mean_over_mask_pixels_with_depth():
    depth = np.full((6, 8), 9999, np.uint16)  # outside the box: never counted
    x1, y1, x2, y2 = 1, 1, 5, 4
    depth[y1:y2, x1:x2] = 5000  # inside the box but outside the mask: never counted
    mask = np.zeros((3, 4), bool)
    for (r, c), v in {(0, 0): 1000, (0, 1): 1001, (1, 1): 1001, (2, 3): 0}.items():  # the 0 has no depth
        mask[r, c] = True
        depth[y1 + r, x1 + c] = v
    assert mask_distance(depth, (x1, y1, x2, y2), mask) == 1000.67  # 3002 / 3 = 1000.666.. -> 2 decimals


def test_d_rounds_half_to_even_and_does_not_overflow():
    depth = np.zeros((2, 8), np.uint16)
    depth[0] = [1000] * 7 + [1001]  # mean 1000.125 exactly: numpy rounds half to even -> 1000.12
    assert mask_distance(depth, (0, 0, 8, 1), np.ones((1, 8), bool)) == 1000.12
    depth[1] = 60000  # 8 x 60000 overflows uint16 if summed in the input dtype
    assert mask_distance(depth, (0, 1, 8, 2), np.ones((1, 8), bool)) == 60000.0


def test_d_without_depth_is_nan():
    depth = np.zeros((4, 4), np.uint16)
    depth[0, 0] = 700  # has depth, but not under the mask
    mask = np.zeros((3, 3), bool)
    mask[1:, 1:] = True
    assert np.isnan(mask_distance(depth, (0, 0, 3, 3), mask))
    assert np.isnan(mask_distance(depth + 1, (0, 0, 3, 3), np.zeros((3, 3), bool)))  # empty mask


def test_box_ratios_round_to_two_decimals():
    a, b = box_ratios(np.array([[10, 20, 50, 80], [0, 0, 320, 240], [5, 5, 38, 29], [0, 0, 50, 1]]), 320, 240)
    # 40/320 = 0.125 (exact: half to even -> 0.12), 320/320, 33/320 = 0.103125, 50/320 = 0.15625
    np.testing.assert_array_equal(a, [0.12, 1.0, 0.1, 0.16])
    # 60/240 = 0.25, 240/240, 24/240 = 0.1, 1/240 = 0.004166..
    np.testing.assert_array_equal(b, [0.25, 1.0, 0.1, 0.0])


def test_compute_features_fills_every_detection():
    depth = np.zeros((240, 320), np.uint16)
    depth[20:80, 10:50] = 800
    depth[100:110, 100:120] = 0
    dets = Detections(frame=[0, 0], xyxy=[[10, 20, 50, 80], [100, 100, 120, 110]], score=[0.9, 0.8],
                      class_id=[47, 47], masks=[np.ones((60, 40), bool), np.ones((10, 20), bool)])
    out = compute_features(dets, depth)
    assert out.d[0] == 800.0 and np.isnan(out.d[1])
    np.testing.assert_array_equal(out.a, [0.12, 0.06])  # 40/320, 20/320 = 0.0625
    np.testing.assert_array_equal(out.b, [0.25, 0.04])  # 60/240, 10/240 = 0.041666..
    assert np.isnan(dets.d).all() and np.isnan(dets.a).all()  # a new Detections: the detector's output is unchanged


# --------------------------------------------------------------------------------------------------------- selection
def test_k_nearest_by_distance():
    d = np.array([5.0, 3.0, 4.0, 1.0, 2.0])
    assert select_k_nearest(d, np.full(5, 0.9), 3, 0.4).tolist() == [3, 4, 1]


def test_threshold_is_strict():
    d = np.array([1.0, 2.0, 3.0])
    score = np.array([0.4, 0.41, 0.39])  # a score equal to the threshold is dropped
    assert select_k_nearest(d, score, 5, 0.4).tolist() == [1]
    # scores are stored as float32 (Detections.score): float32(0.4) must still count as "equal to 0.4"
    assert select_k_nearest(d, score.astype(np.float32), 5, 0.4).tolist() == [1]
    det = Detections(frame=[0, 0], xyxy=[[0, 0, 1, 1]] * 2, score=[0.4, 0.41], class_id=[47, 47])
    assert select_k_nearest([1.0, 2.0], det.score, 5, 0.4).tolist() == [1]


def test_ties_go_to_the_earliest_and_never_repeat():
    d = np.array([2.0, 1.0, 1.0, 1.0, 3.0])
    chosen = select_k_nearest(d, np.ones(5), 4, 0.4)
    assert chosen.tolist() == [1, 2, 3, 0]
    # The original code (CORSMAL/Visual) looked each sorted distance up with np.where(d == value)[0][0], so equal
    # distances all resolved to the first of them: the same patch three times. massviz must not do that.
    original = [int(np.where(d == v)[0][0]) for v in np.sort(d)[:4]]
    assert original == [1, 1, 1, 0]
    assert len(set(chosen.tolist())) == len(chosen) != len(set(original))


def test_fewer_candidates_than_k_and_none():
    d = np.array([7.0, np.nan, 3.0])
    score = np.array([0.9, 0.99, 0.3])
    assert select_k_nearest(d, score, 5, 0.4).tolist() == [0]  # NaN d and low score never selected
    empty = select_k_nearest(d, score, 5, 0.95)
    assert empty.tolist() == []
    assert estimate_mass(np.array([1.0, 2.0, 3.0]), empty) == -1.0
    assert select_k_nearest(np.zeros(0), np.zeros(0), 5, 0.4).tolist() == []
    with pytest.raises(ValueError):
        select_k_nearest(d, score, 0, 0.4)


def test_nan_distance_is_never_selected():
    d = np.array([np.nan, 500.0, np.nan, 400.0])
    assert select_k_nearest(d, np.ones(4), 4, 0.0).tolist() == [3, 1]


def test_exclude_indices_or_bool_mask():
    d = np.array([1.0, 2.0, 3.0, 4.0])
    score = np.ones(4)
    assert select_k_nearest(d, score, 2, 0.4, exclude=np.array([0])).tolist() == [1, 2]
    assert select_k_nearest(d, score, 2, 0.4, exclude=np.array([False, True, True, False])).tolist() == [0, 3]
    assert select_k_nearest(d, score, 2, 0.4, exclude=np.array([], dtype=np.int64)).tolist() == [0, 1]


def test_estimate_is_mean_of_selected():
    pred = np.array([10.0, 20.0, 40.0, 1000.0], np.float32)
    assert estimate_mass(pred, np.array([0, 2, 1])) == pytest.approx(70.0 / 3)


# -------------------------------------------------------------------------------- masks without depth, end to end
def test_mask_without_depth_is_skipped_and_reported(tmp_path):
    rgbs = [np.full((24, 32, 3), 90 + 10 * i, np.uint8) for i in range(3)]
    depths = [np.full((24, 32), 1200 - 100 * i, np.uint16) for i in range(3)]
    depths[1][0:8, 0:8] = 0  # the hole frame 1's nearest-looking detection sits in
    rec = open_recording(write_recording(tmp_path / "r", rgbs, depths))
    hole = np.zeros((8, 8), bool)
    hole[2:6, 2:6] = True
    det = ListDetector({0: [((10, 10, 20, 20), 0.9, None)],
                        1: [((0, 0, 8, 8), 0.95, hole), ((20, 4, 30, 14), 0.8, None)],
                        2: [((4, 4, 12, 12), 0.3, None)]})  # below the threshold: not even a detection
    model = DistanceModel()
    trace = run(rec, det, model, k=5)
    dets = trace.detections
    assert len(dets) == 3 and np.isnan(dets.d[1])
    np.testing.assert_array_equal(dets.d[[0, 2]], [1200.0, 1100.0])
    assert trace.selection.tolist() == [2, 0]  # the no-depth detection is never chosen, whatever K
    assert trace.estimate == pytest.approx((110.0 + 120.0) / 2)
    assert np.isnan(dets.pred[1])  # and never predicted
    assert sum(len(p) for p, _ in model.seen) == 2
    skipped = [e for e in trace.events if "no depth" in e.message and e.kind == "skipped" and e.level == "warn"]
    assert len(skipped) == 1 and skipped[0][0] == 1 and "[0, 0, 8, 8]" in skipped[0][1]
    assert trace.reselect(k=1, threshold=0.9).estimate == -1.0  # only the no-depth one scores > 0.9
