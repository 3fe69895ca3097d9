"""Tracks and flags (``massviz.core.tracks``, ``massviz.core.flags``) on the bundled samples at the paper's settings
(depth detector, threshold 0.4, K 5, every frame), and what the commands and the Rerun recording show of them.

In ``cup_handover`` a hand lifts the pitcher nearer than the cup in frames 8-10: three of the five chosen patches are
the pitcher (57.4 g against 9 g). In ``box_handover`` and ``glass_handover`` all five are the container. Other
strides reach back to frames where the pitcher standing on the table is chosen (a second case for the flags).
"""
from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from massviz.core.flags import analyse, ground_truth_overlap
from massviz.core.trace import Trace, analyse_trace
from massviz.core.tracks import Tracker, assign_tracks
from massviz.core.types import Detections
from massviz.evaluation.failures import track_of
from massviz.evaluation.tuning import retune
from massviz.io.trace_file import load_trace, save_trace
from massviz.views.widgets import FailurePanel, Tuner
from support import run_massviz as _run

ROOT = Path(__file__).resolve().parents[1]
SETTINGS = [(1, 5), (1, 3), (1, 12), (2, 5), (3, 8), (6, 5), (6, 3)]  # (stride, K)


@pytest.fixture(scope="module")
def traces(sample_traces):
    return {t.recording.id: t for t in sample_traces}


def _is_container(trace, i) -> bool:
    return ground_truth_overlap(trace, int(i))["iou_container"] >= 0.5


def test_the_lifted_pitcher_is_one_track(traces):
    t = traces["cup_handover"]
    dets = t.detections
    pitcher = [i for i in range(len(dets)) if not _is_container(t, i)]
    cup = [i for i in range(len(dets)) if _is_container(t, i)]
    assert set(dets.frame[pitcher]) == set(range(24)) and set(dets.frame[cup]) == set(range(36))
    assert len(set(dets.track[pitcher])) == 1, "the pitcher, lifted in frames 7-11, must stay one track"
    assert len(set(dets.track[cup])) == 1 and dets.track[cup[0]] != dets.track[pitcher[0]]
    # the lift itself: IoU 0.39 and 221 mm between frames 7 and 8, yet the same object
    assert set(dets.track[np.isin(dets.frame, [8, 9, 10]) & ~np.isin(np.arange(len(dets)), cup)]) == \
        {dets.track[pitcher[0]]}
    # the online tracker (what FramePipeline.step runs) and the batch helper agree
    np.testing.assert_array_equal(assign_tracks(dets, t.recording.fps), dets.track)


def test_tracker_keeps_objects_apart_and_opens_tracks():
    tr = Tracker(fps=30)
    a = Detections(frame=[0, 0], xyxy=[[0, 0, 10, 10], [50, 50, 60, 60]], score=[1, 1], class_id=[-1, -1],
                   d=[500.0, 500.0])
    first = tr.update(0, a)
    assert list(first) == [1, 2]
    # same places, one object jumped 60 % in depth (another object in front): a new track
    b = Detections(frame=[1, 1], xyxy=[[1, 0, 11, 10], [50, 50, 60, 60]], score=[1, 1], class_id=[-1, -1],
                   d=[505.0, 200.0])
    assert list(tr.update(1, b)) == [1, 3]


def _one_track_at_a_time(frames, fps=30):
    """The tracker of ``massviz.core.tracks``' docstring written plainly, one open track at a time: the oracle."""
    import math

    from massviz.core.tracks import DEPTH_GATE, IOU_MIN, MAX_GAP_S, SIZE_GATE, SIZE_HISTORY, box_iou

    tracks, next_id, max_gap, out = {}, 1, max(1, int(round(MAX_GAP_S * fps))), []
    for frame, dets in frames:
        tracks = {t: tr for t, tr in tracks.items() if frame - tr["frame"] <= max_gap}
        boxes, depths = dets.xyxy.astype(float), dets.d.astype(float)
        cands = []
        for tid, tr in tracks.items():
            gap = frame - tr["frame"]
            for j in range(len(boxes)):
                iou = max(box_iou(tr["box"], boxes[j])[0, 0], box_iou(tr["box"] + tr["vel"] * gap, boxes[j])[0, 0])
                d, both = depths[j], math.isfinite(depths[j]) and math.isfinite(tr["d"])
                ok = iou >= IOU_MIN and not (both and abs(d - tr["d"]) > DEPTH_GATE * max(d, tr["d"]))
                if tr["sizes"] and both:
                    sw, sh = np.median(np.asarray(tr["sizes"]), axis=0)
                    w, h = (boxes[j, 2] - boxes[j, 0]) * d, (boxes[j, 3] - boxes[j, 1]) * d
                    if min(sw, sh) <= 0 or min(w, h) <= 0 or max(w / sw, sw / w, h / sh, sh / h) > SIZE_GATE:
                        ok = False
                if ok:
                    cands.append((-iou, gap, tid, j))
        ids, used = [0] * len(boxes), set()
        for _, _, tid, j in sorted(cands):
            if ids[j] or tid in used:
                continue
            used.add(tid)
            ids[j], tr = tid, tracks[tid]
            tr["vel"] = (boxes[j] - tr["box"]) / max(frame - tr["frame"], 1)
            tr.update(frame=frame, box=boxes[j], d=depths[j])
            if math.isfinite(depths[j]):
                tr["sizes"] = (tr["sizes"] + [((boxes[j, 2] - boxes[j, 0]) * depths[j],
                                               (boxes[j, 3] - boxes[j, 1]) * depths[j])])[-SIZE_HISTORY:]
        for j in range(len(boxes)):
            if not ids[j]:
                ids[j], next_id = next_id, next_id + 1
                tracks[ids[j]] = {"frame": frame, "box": boxes[j], "vel": np.zeros(4), "d": depths[j], "sizes": [
                    ((boxes[j, 2] - boxes[j, 0]) * depths[j], (boxes[j, 3] - boxes[j, 1]) * depths[j])]
                    if math.isfinite(depths[j]) else []}
        out.append(ids)
    return out


def test_the_tracker_equals_one_track_at_a_time_on_random_scenes():
    """The open tracks are gated as arrays (thousands of them in a GPU run of ~100 detections a frame): the same ids
    as gating one track at a time, on scenes of objects that move, flicker, lose depth and skip frames."""
    for seed in range(12):
        rng = np.random.default_rng(seed)
        n = int(rng.integers(1, 25))
        base, wh, depth = rng.uniform(0, 500, (n, 2)), rng.uniform(10, 150, (n, 2)), rng.uniform(300, 2000, n)
        frames = []
        for i in range(40):
            idx = rng.choice(n, int(rng.integers(0, n + 1)), replace=False)
            xy = base[idx] + rng.normal(0, 6, (len(idx), 2)) + 2 * i
            box = np.concatenate([xy, xy + wh[idx] * rng.uniform(0.8, 1.25, (len(idx), 1))], 1).clip(0).astype(int)
            d = depth[idx] * rng.uniform(0.8, 1.2, len(idx))
            d[rng.random(len(idx)) < 0.1] = np.nan
            frames.append((i * (1 + seed % 3), Detections(frame=np.full(len(idx), i), xyxy=box,
                                                          score=np.ones(len(idx)), class_id=np.zeros(len(idx)), d=d)))
        tr = Tracker(fps=30)
        got = [tr.update(f, dets).tolist() for f, dets in frames]
        assert got == _one_track_at_a_time(frames), seed


def test_flags_match_the_ground_truth_on_all_samples(traces):
    for name, t in traces.items():
        for stride, k in SETTINGS:
            cur = retune(t, k=k, stride=stride)
            truth = [not _is_container(cur, i) for i in cur.selection]
            got = [p.flagged for p in cur.flags.patches]
            assert got == truth, f"{name} stride {stride} K {k}"
            assert all(p.ground_truth is not None for p in cur.flags.patches)
    paper = traces["cup_handover"].flags
    assert [p.frame for p in paper.flagged] == [9, 10, 8]
    assert {p.ground_truth for p in paper.flagged} == {"pitcher"}
    assert paper.estimate_without == pytest.approx(8.3, abs=0.05)
    assert traces["box_handover"].flags.flagged == [] and traces["glass_handover"].flags.flagged == []


def test_cues_alone_still_flag_the_pitcher(traces):
    t = traces["cup_handover"]
    cues = analyse(t, ground_truth=False)
    assert [p.frame for p in cues.flagged] == [9, 10, 8]
    assert all(p.ground_truth is None and {"track", "size", "time"} <= set(p.cue_kinds) for p in cues.flagged)
    assert cues.estimate_without == pytest.approx(8.3, abs=0.05)
    # a recording without ground-truth masks (or with a mask pattern pointing outside its folder) gets the same
    for meta in ({k: v for k, v in t.recording.meta.items() if k != "instance_masks"},
                 {**t.recording.meta, "instance_masks": "../../{frame:06d}.png"}):
        bare = analyse_trace(dataclasses.replace(t, recording=dataclasses.replace(t.recording, meta=meta)))
        assert [p.frame for p in bare.flags.flagged] == [9, 10, 8]
        assert all(p.ground_truth is None for p in bare.flags.patches)
    # cue-only precision and recall against the ground truth over several strides and K on all three samples
    tp = fp = fn = 0
    for tr in traces.values():
        for stride, k in SETTINGS:
            cur = retune(tr, k=k, stride=stride)
            for p in analyse(cur, ground_truth=False).patches:
                other = not _is_container(cur, p.detection)
                tp, fp, fn = tp + (p.flagged and other), fp + (p.flagged and not other), fn + (other and not p.flagged)
    print(f"cue-only flags on the samples: precision {tp / max(tp + fp, 1):.2f}, recall {tp / max(tp + fn, 1):.2f} "
          f"({tp} TP, {fp} FP, {fn} FN)")
    assert tp > 0 and fp == 0 and fn == 0


def test_one_exclude_track_removes_the_lifted_pitcher(traces):
    ordered = list(traces.values())
    cup = next(i for i, t in enumerate(ordered) if t.recording.id == "cup_handover")
    tuner = Tuner(ordered, k=5, stride=1)
    panel = FailurePanel(tuner)
    lifted = int(tuner.selection(cup)[0])  # ★0: the pitcher in frame 9
    assert int(ordered[cup].detections.frame[lifted]) == 9
    panel.set_mode(lifted, "exclude track", i=cup)
    cur = tuner.current[cup]
    assert cur.estimate == pytest.approx(8.3, abs=0.05)
    chosen_frames = set(ordered[cup].detections.frame[tuner.selection(cup)].tolist())
    assert not chosen_frames & {8, 9, 10}
    assert set(tuner.excluded(cup)) == set(track_of(ordered[cup], lifted)) and len(tuner.excluded(cup)) == 24
    assert cur.flags.flagged == []


def test_flags_and_tracks_are_saved_recomputed_and_upgraded(traces, tmp_path):
    t = traces["cup_handover"]
    path = save_trace(t, tmp_path / "cup.npz")
    back = load_trace(path)
    np.testing.assert_array_equal(back.detections.track, t.detections.track)
    assert back.flags == t.flags
    three = t.reselect(k=3)
    assert len(three.flags.patches) == 3 and len(three.flags.flagged) == 3 and three.flags.estimate_without == -1
    assert "no patch left" in three.flags.warning()
    # a trace file written before tracks, flags and ground-truth overlaps existed: all are made on load
    with np.load(path, allow_pickle=False) as z:
        data = {n: z[n] for n in z.files if n != "det_track" and not n.startswith("det_gt_")}
    import json

    header = json.loads(data["header"].tobytes().decode())
    del header["flags"], header["ground_truth_source"]
    data["header"] = np.frombuffer(json.dumps(header).encode(), dtype=np.uint8)
    np.savez_compressed(tmp_path / "old.npz", **data)
    old = load_trace(tmp_path / "old.npz")
    np.testing.assert_array_equal(old.detections.track, t.detections.track)
    assert [p.to_dict() for p in old.flags.patches] == [p.to_dict() for p in t.flags.patches]


class _FileOpens:
    """Counts the files opened while active: the ``open`` audit event (builtins.open, io.open, os.open, np.load,
    pathlib's read_*), plus cv2.imread and cv2.VideoCapture, which open files in C++ without an audit event."""

    installed = None

    def __init__(self, monkeypatch):
        import cv2

        self.opened, self.active = [], False
        if _FileOpens.installed is None:  # an audit hook cannot be removed: one per session, forwarding to the active
            _FileOpens.installed = [None]
            sys.addaudithook(lambda event, args: _FileOpens.installed[0] and event == "open"
                             and _FileOpens.installed[0](str(args[0])))
        for name in ("imread", "VideoCapture"):
            real = getattr(cv2, name)
            monkeypatch.setattr(cv2, name, lambda path, *a, _real=real, **kw: (self.record(str(path)),
                                                                                _real(path, *a, **kw))[1])

    def record(self, path: str) -> None:
        if self.active:
            self.opened.append(path)

    def __enter__(self):
        self.opened, self.active = [], True
        _FileOpens.installed[0] = self.record
        return self

    def __exit__(self, *exc):
        self.active = False
        _FileOpens.installed[0] = None


def test_making_replacing_and_reselecting_a_trace_opens_no_file(traces, monkeypatch):
    # the flags (with the ground truth of the samples' instance masks) are made when a trace is made: pure computation
    # on what the trace holds, so none of these opens a file
    from massviz.io import ground_truth
    from massviz.io.ground_truth import with_ground_truth

    t = traces["cup_handover"]
    fields = {f.name: getattr(t, f.name) for f in dataclasses.fields(t)}
    opens = _FileOpens(monkeypatch)
    with opens:
        made = analyse_trace(Trace(**{**fields, "flags": None}))
        replaced = analyse_trace(dataclasses.replace(t, threshold=0.5))
        three = t.reselect(k=3)
        retuned = retune(t, k=4, stride=2)
        bare = analyse_trace(dataclasses.replace(t, recording=dataclasses.replace(
            t.recording, meta={k: v for k, v in t.recording.meta.items() if k != "instance_masks"})))
    assert opens.opened == []
    assert made.flags == t.flags and [p.frame for p in made.flags.flagged] == [9, 10, 8]
    for cur in (replaced, three, retuned, made):  # their flags were made again, with the ground truth
        assert cur.flags.describes(cur) and all(p.ground_truth is not None for p in cur.flags.patches)
    assert len(three.flags.patches) == 3 and all(p.ground_truth is None for p in bare.flags.patches)
    # the counter sees what io opens: reading the ground truth's masks again opens them (the check can fail)
    ground_truth.read_instance_image.cache_clear()
    with opens:
        again = with_ground_truth(dataclasses.replace(t, ground_truth_source=""))
    assert again.flags is None  # io reads the overlaps; the analysis stage makes the flags with them
    again = analyse_trace(again)
    assert again.flags == t.flags
    assert {Path(p).parent.name for p in opens.opened} == {"gt"}
    assert len({p for p in opens.opened if p.endswith(".png")}) == len(np.unique(t.detections.frame))


@pytest.mark.slow
def test_log_and_estimate_print_the_warning_and_the_rrd_shows_the_flags(weights, sample_cache, tmp_path):
    rrd = tmp_path / "cup.rrd"
    log = _run("log", "data_samples/cup_handover", "--detector", "depth", "--weights", weights, "--cache", sample_cache,
               "--rrd", rrd, "--quiet")
    assert log.returncode == 0, log.stderr
    warnings = [line for line in log.stderr.splitlines() if "warning" in line]
    assert warnings == ["massviz log: warning: cup_handover: 3 of 5 chosen patches look like another object "
                        "(frames 8–10, track 1): without them 8.3 g [ground truth: the pitcher]"]
    est = _run("estimate", "data_samples", "--detector", "depth", "--weights", weights, "--cache", sample_cache,
               "--out", tmp_path / "p.csv", "--quiet")
    assert est.returncode == 0, est.stderr
    lines = [line for line in est.stderr.splitlines() if "warning" in line]
    assert len(lines) == 1 and "cup_handover: 3 of 5 chosen patches" in lines[0]
    printed = subprocess.run([str(Path(sys.executable).parent / "rerun"), "rrd", "print", "-vvv", str(rrd)],
                             capture_output=True, text=True, timeout=120)
    assert printed.returncode == 0, printed.stderr
    out = printed.stdout
    warn = [line for line in out.splitlines() if "[WARN]" in line]
    assert sum("flagged patch ★" in line for line in warn) == 3
    assert any("3 of 5 chosen patches look like another object" in line for line in warn)
    # /camera/detections: the flagged class ids (FLAGGED_ID + rank), the flagged colour and label
    from massviz.views.palette import FLAGGED_COLOUR, rgb255
    from massviz.views.rerun import FLAGGED_ID

    packed = str(int.from_bytes(bytes([*rgb255(FLAGGED_COLOUR), 255]), "big"))
    boxes = [line for line in out.splitlines() if "track 1 ★" in line]
    assert boxes and all("⚑ flagged" in line and packed in line for line in boxes)
    assert any(f"[{FLAGGED_ID}, " in line for line in boxes)
    assert "★0 ⚑ flagged: the pitcher" in out  # the patch tile's outline
    assert "/predictions/estimate_without_flagged" in out


@pytest.mark.slow
def test_render_marks_a_flagged_patch_and_refuses_a_frame_without_one(weights, sample_cache, tmp_path):
    common = ["data_samples/cup_handover", "--detector", "depth", "--weights", weights, "--cache", sample_cache,
              "--quiet"]
    bad = _run("render", *common, "--frame", "3", "--out", tmp_path / "f3.png")
    assert bad.returncode == 2
    lines = [line for line in bad.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "frame 3 has no chosen patch" in lines[0] and "8, 9, 10, 31, 35" in lines[0]
    assert "Traceback" not in bad.stderr and not (tmp_path / "f3.png").exists()
    good = _run("render", *common, "--out", tmp_path / "f9.png", "--size", "480x270")
    assert good.returncode == 0, good.stderr
    assert "frame 9: chosen patch ★0 (track 1) is flagged" in good.stderr
    assert "FEngine" not in good.stderr + good.stdout  # Filament's start-up lines are captured
    import cv2

    from massviz.views.palette import FLAGGED_COLOUR, rgb255

    img = cv2.cvtColor(cv2.imread(str(tmp_path / "f9.png")), cv2.COLOR_BGR2RGB).astype(int)
    red = (np.abs(img - np.array(rgb255(FLAGGED_COLOUR))).sum(axis=-1) < 40).sum()
    assert red > 500, "the flagged pitcher is drawn in the flagged colour"
