"""The depth detector against the synthetic samples' ground truth, plus its contract (threshold, settings, empty)."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from massviz.core.detector import Detector
from massviz.core.types import OBJECT_CLASS_ID, Frame, Rejection
from massviz.detect.depth import DepthDetector

NAMES = ["cup_handover", "glass_handover", "box_handover"]
CONTAINER, PITCHER = 1, 2


def _frame(rec: Path, i: int) -> tuple[Frame, np.ndarray]:
    name = f"{i:06d}.png"
    rgb = cv2.cvtColor(cv2.imread(str(rec / "rgb" / name), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    depth = cv2.imread(str(rec / "depth" / name), cv2.IMREAD_UNCHANGED)
    gt = cv2.imread(str(rec / "gt" / name), cv2.IMREAD_UNCHANGED)
    return Frame(i, rgb, depth), gt


def _best_iou(dets, target: np.ndarray) -> float:
    h, w = target.shape
    ious = [(m & target).sum() / (m | target).sum() for m in (dets.full_mask(j, h, w) for j in range(len(dets)))]
    return float(max(ious, default=0.0))


@pytest.fixture(scope="module", params=NAMES)
def results(request, samples_dir):
    """Per frame of one sample: container_nearest, best IoU with the container and with the pitcher, detections."""
    rec = samples_dir / request.param
    meta = json.loads((rec / "meta.json").read_text())
    det = DepthDetector()
    rows = []
    for f in meta["frames"]:
        frame, gt = _frame(rec, f["index"])
        dets = det.detect(frame)
        rows.append((f["container_nearest"], _best_iou(dets, gt == CONTAINER), _best_iou(dets, gt == PITCHER), dets))
        assert det.pop_notes(f["index"]) == [], (request.param, f["index"])  # nothing border-cut or implausible here
    return request.param, rows


@pytest.mark.slow
def test_container_found_where_it_is_nearest(results):
    name, rows = results
    ious = np.array([c for nearest, c, _, _ in rows if nearest])
    good = (ious >= 0.7).mean()
    print(f"{name}: container nearest in {len(ious)} frames, IoU>=0.7 in {good:.0%}, "
          f"IoU min {ious.min():.2f} median {np.median(ious):.2f}")
    assert len(ious) >= 10 and good >= 0.9


@pytest.mark.slow
def test_pitcher_and_container_returned_where_pitcher_is_nearer(results):
    name, rows = results
    pitcher_frames = [(c, p) for nearest, c, p, _ in rows if not nearest]
    pitcher = np.array([p for _, p in pitcher_frames])
    container = np.array([c for c, _ in pitcher_frames])
    print(f"{name}: pitcher nearer in {len(pitcher)} frames, pitcher IoU>=0.7 in {(pitcher >= 0.7).mean():.0%}, "
          f"container IoU>=0.5 in {(container >= 0.5).mean():.0%}")
    assert len(pitcher) >= 10
    assert (pitcher >= 0.7).mean() >= 0.9
    assert (container >= 0.5).mean() >= 0.8


@pytest.mark.slow
def test_detections_are_well_formed(results):
    _, rows = results
    for _, _, _, dets in rows:
        assert 0 < len(dets) <= 2
        assert np.all((dets.score > 0.4) & (dets.score <= 1))
        assert np.all(dets.class_id == OBJECT_CLASS_ID)
        for j, (x1, y1, x2, y2) in enumerate(dets.xyxy):
            mask = dets.mask(j)
            assert mask.dtype == bool and mask.shape == (y2 - y1, x2 - x1)
            # the box is tight: the mask touches all four sides
            assert mask[0].any() and mask[-1].any() and mask[:, 0].any() and mask[:, -1].any()


def test_threshold_keeps_scores_above_it(samples_dir):
    frame, _ = _frame(samples_dir / "cup_handover", 8)
    everything = DepthDetector(threshold=0.0, max_objects=4).detect(frame)
    assert len(everything) >= 3 and everything.score.min() < 0.4 < 0.7 < everything.score.max()
    for threshold in (0.0, 0.4, 0.7):
        kept = DepthDetector(threshold=threshold, max_objects=4).detect(frame)
        expected = everything[everything.score > threshold]
        assert np.array_equal(kept.xyxy, expected.xyxy)
        assert np.all(kept.score > threshold)


def test_max_objects(samples_dir):
    frame, _ = _frame(samples_dir / "box_handover", 30)
    assert len(DepthDetector(max_objects=1, threshold=0.0).detect(frame)) == 1
    assert len(DepthDetector(max_objects=3, threshold=0.0).detect(frame)) == 3


@pytest.mark.parametrize("depth", [np.zeros((270, 480), np.uint16), np.full((270, 480), 5000, np.uint16),
                                   np.zeros((0, 0), np.uint16)])
def test_no_depth_no_detections(depth):
    frame = Frame(3, np.zeros(depth.shape + (3,), np.uint8), depth)
    dets = DepthDetector(threshold=0.0).detect(frame)
    assert len(dets) == 0 and dets.xyxy.shape == (0, 4)


def test_isolated_object_scores_one():
    depth = np.full((120, 160), 1500, np.uint16)
    depth[40:80, 60:90] = 600
    dets = DepthDetector(threshold=0.0).detect(Frame(0, np.zeros((120, 160, 3), np.uint8), depth))
    assert dets.xyxy[0].tolist() == [60, 40, 90, 80] and dets.score[0] == 1.0 and dets.frame[0] == 0
    assert dets.mask(0).all()


def test_settings_key_everything_but_threshold():
    a, b = DepthDetector(threshold=0.2), DepthDetector(threshold=0.7)
    assert isinstance(a, Detector) and a.name == "depth"
    assert a.settings() == b.settings() and "threshold" not in a.settings()
    assert DepthDetector(slab_mm=120).settings() != a.settings()
    json.dumps(a.settings())  # a cache key must serialise


def test_deterministic(samples_dir):
    frame, _ = _frame(samples_dir / "glass_handover", 30)
    a, b = DepthDetector().detect(frame), DepthDetector().detect(frame)
    assert np.array_equal(a.xyxy, b.xyxy) and np.array_equal(a.score, b.score)


def test_real_ccm_frame(shared_dir):
    """Frame 20 of a real CCM recording: the robot gripper (bottom right, cut by the image border) is nearer than the
    held box, and a sliver touches the top-right border; neither is a container candidate: the box is found."""
    root = shared_dir / "ccm_real"
    depth = cv2.imread(str(root / "view1" / "depth" / "000000" / "0001.png"), cv2.IMREAD_UNCHANGED)
    rgb = cv2.cvtColor(cv2.imread(str(root / "frame_20_rgb.png")), cv2.COLOR_BGR2RGB)
    det = DepthDetector()
    dets = det.detect(Frame(20, rgb, depth))
    assert 1 <= len(dets) <= 2
    centres = (dets.xyxy[:, :2] + dets.xyxy[:, 2:]) / 2
    assert not np.any((centres[:, 0] > 0.75 * 1280) & (centres[:, 1] > 0.6 * 720)), "the gripper, bottom right"
    assert not np.any((dets.xyxy[:, 0] <= 1) | (dets.xyxy[:, 1] <= 1) | (dets.xyxy[:, 2] >= 1279)
                      | (dets.xyxy[:, 3] >= 719))
    box = np.flatnonzero((centres[:, 0] > 640) & (centres[:, 0] < 850) & (centres[:, 1] > 250) & (centres[:, 1] < 440))
    assert len(box) == 1 and dets.score[box[0]] > 0.4, dets.xyxy  # the pasta box, held at 1.2 m
    notes = det.pop_notes(20)
    assert any(n.reason == "border-cut object" and n.text.startswith("border-cut object (box [1256, 0, 1280,")
               for n in notes), notes  # the sliver
    assert any(n.reason == "part of a border-cut object" and "part of a border-cut object" in n.text
               for n in notes), notes  # the gripper's top, inside the view
    assert det.pop_notes(20) == []


def test_border_cut_and_implausibly_sized_objects_are_not_candidates():
    depth = np.full((120, 160), 1500, np.uint16)
    depth[40:80, 60:90] = 600  # a free object
    depth[90:120, 0:30] = 500  # nearer, cut by the bottom-left corner
    det = DepthDetector(threshold=0.0)
    dets = det.detect(Frame(0, np.zeros((120, 160, 3), np.uint8), depth))
    assert dets.xyxy.tolist() == [[60, 40, 90, 80]]
    assert det.pop_notes(0) == [Rejection("border-cut object", "border-cut object (box [0, 90, 30, 120] at 500 mm)")]
    big = np.full((120, 160), 2500, np.uint16)  # the room, beyond the working range
    big[20:100, 40:115] = 1900  # 75 × 80 px at 1.9 m with fx = 0.72 × 160: 1237 × 1319 mm
    det = DepthDetector(threshold=0.0)
    assert len(det.detect(Frame(1, np.zeros((120, 160, 3), np.uint8), big))) == 0
    assert det.pop_notes(1) == [Rejection("implausibly sized object",
                                          "implausibly sized object, 1237×1319 mm (box [40, 20, 115, 100] at 1900 mm)")]


@pytest.mark.parametrize("seed", range(6))
def test_closing_near_the_mask_is_the_closing_of_the_whole_image(seed):
    """``close_near`` (the closing computed on the mask's bounding box grown by the kernel) gives exactly the pixels
    of OpenCV's closing of the whole image: masks in the middle, at every border and corner, sparse and dense."""
    from massviz.detect.depth import close_near

    rng = np.random.default_rng(seed)
    h, w = (270, 480) if seed % 2 else (72, 128)
    k = 2 * int(round(0.02 * w / 2)) + 1 + 2 * (seed % 3)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    for _ in range(12):
        mask = np.zeros((h, w), bool)
        y, x = rng.integers(-10, h), rng.integers(-10, w)
        mask[max(0, y):y + rng.integers(1, h // 2), max(0, x):x + rng.integers(1, w // 2)] = True
        mask &= rng.random((h, w)) < rng.choice([0.2, 0.6, 0.95])  # holes the closing fills, or does not
        expected = cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_CLOSE, kernel) > 0
        assert np.array_equal(close_near(mask, kernel), expected)
    assert not close_near(np.zeros((h, w), bool), kernel).any()
