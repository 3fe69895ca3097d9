"""``massviz compare``: two hand-made traces whose differences are known, reported exactly; the two-recording .rrd."""
from __future__ import annotations

import json

import numpy as np
import pytest

from massviz.cli import main
from massviz.core.trace import Trace
from massviz.core.types import COCO_KEEP, Detections
from massviz.evaluation.compare import box_iou, compare_traces, match_boxes
from massviz.io.trace_file import save_trace

CUP, BOTTLE = COCO_KEEP["cup"], COCO_KEEP["bottle"]



def make_trace(recording, rows, precision):
    """rows: (frame, class, score, box, d, pred); full-box masks; selection by the library (K 2, threshold 0.4)."""
    frame, cls, score, xyxy, d, pred = (list(c) for c in zip(*rows, strict=False))
    masks = [np.ones((y2 - y1, x2 - x1), bool) for x1, y1, x2, y2 in xyxy]
    dets = Detections(frame=frame, xyxy=xyxy, score=score, class_id=cls, masks=masks, d=d,
                      a=[0.1] * len(rows), b=[0.2] * len(rows), pred=pred)
    trace = Trace(recording=recording.info(), detector={"name": "maskrcnn", "weights": "random-init",
                                                        "precision": precision},
                  detect_threshold=0.4, threshold=0.4, k=2, stride=1, frames=np.array([0, 1, 2]), detections=dets,
                  selection=np.zeros(0, np.int64), estimate=-1.0, weights_id="abc")
    return trace.reselect()


A_ROWS = [
    (0, CUP, 0.90, [10, 10, 50, 60], 700.0, 100.0),
    (0, BOTTLE, 0.80, [100, 20, 140, 90], 900.0, 200.0),
    (1, CUP, 0.85, [12, 10, 52, 60], 710.0, 110.0),      # B has no box here
    (2, CUP, 0.70, [300, 100, 340, 150], 800.0, 150.0),
]
B_ROWS = [
    (0, CUP, 0.88, [10, 10, 50, 60], 703.5, 100.0),      # score -0.02, d +3.5
    (0, BOTTLE, 0.80, [100, 20, 140, 90], 900.0, 200.0),  # identical
    (1, CUP, 0.75, [200, 50, 240, 100], 720.0, 130.0),   # new: only in B, and chosen (rank 1)
    (2, CUP, 0.70, [302, 100, 342, 150], 800.0, 162.0),  # shifted 2 px (IoU 38/42), pred +12
]


@pytest.fixture(scope="module")
def traces(recording):
    return make_trace(recording, A_ROWS, "fp32"), make_trace(recording, B_ROWS, "bf16")


def test_iou_and_greedy_matching():
    a = np.array([[0, 0, 10, 10], [20, 0, 30, 10]])
    b = np.array([[21, 0, 31, 10], [0, 0, 10, 5], [0, 0, 10, 10]])
    np.testing.assert_allclose(box_iou(a, b), [[0, 0.5, 1.0], [9 / 11, 0, 0]])
    assert match_boxes(a, b) == [(0, 2, 1.0), (1, 0, pytest.approx(9 / 11))]  # best first, one to one
    assert match_boxes(a, b, iou=0.95) == [(0, 2, 1.0)]
    assert match_boxes(a[:0], b) == []


def test_reports_exactly_the_differences_put_in(traces):
    a, b = traces
    assert a.selection.tolist() == [0, 2] and a.estimate == pytest.approx(105.0)
    assert b.selection.tolist() == [0, 2] and b.estimate == pytest.approx(115.0)
    c = compare_traces(a, b)
    assert c.settings == [("precision", "fp32", "bf16")]
    assert c.frames_only_a == [] and c.frames_only_b == []
    assert sorted(zip(c.match_a.tolist(), c.match_b.tolist(), strict=False)) == [(0, 0), (1, 1), (3, 3)]
    assert c.unmatched_a.tolist() == [2] and c.unmatched_b.tolist() == [2]
    order = np.argsort(c.match_a)
    np.testing.assert_allclose(c.match_iou[order], [1.0, 1.0, 38 / 42])
    np.testing.assert_allclose(c.d_score[order], [-0.02, 0.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(c.d_d[order], [3.5, 0.0, 0.0])
    np.testing.assert_allclose(c.d_pred[order], [0.0, 0.0, 12.0])
    assert len(c.class_changes) == 0
    assert [(r.rank, r.a, r.b, r.same) for r in c.chosen] == [(0, 0, 0, True), (1, 2, 2, False)]
    assert c.estimate_delta == pytest.approx(10.0)
    s = c.summary()
    assert (s["matched"], s["unmatched_a"], s["unmatched_b"], s["chosen_changed"]) == (3, 1, 1, [1])
    assert s["max_abs_d_d_mm"] == pytest.approx(3.5) and s["max_abs_d_pred_g"] == pytest.approx(12.0)
    text = c.table()
    assert "precision fp32 -> bf16" in text and "3 matched" in text and "1 only in A, 1 only in B" in text
    assert "delta +10.00 g" in text and "CHANGED" in text


def test_identical_traces_have_no_differences(traces):
    a, _ = traces
    c = compare_traces(a, a)
    s = c.summary()
    assert s["settings"] == [] and s["matched"] == len(a.detections) and s["unmatched_a"] == s["unmatched_b"] == 0
    assert s["max_abs_d_score"] == s["max_abs_d_d_mm"] == s["max_abs_d_pred_g"] == 0.0
    assert s["chosen_changed"] == [] and s["estimate_delta_g"] == 0.0


def test_a_class_change_and_frames_of_one_side(recording, traces):
    a, _ = traces
    rows = [list(r) for r in A_ROWS]
    rows[1][1] = CUP  # the bottle became a cup
    b = make_trace(recording, [tuple(r) for r in rows], "fp32")
    b.frames = np.array([0, 1, 2, 3])
    c = compare_traces(a, b)
    assert c.class_changes.tolist() == [1] and c.frames_only_b == [3] and c.settings == []


@pytest.mark.slow
def test_cli_on_two_saved_traces_table_json_and_two_recording_rrd(traces, tmp_path, capsys):
    from rerun.chunk import RrdReader

    a, b = traces
    save_trace(a, tmp_path / "a.npz")
    save_trace(b, tmp_path / "b.npz")
    out, js = tmp_path / "both.rrd", tmp_path / "diff.json"
    code = main(["compare", str(tmp_path / "a.npz"), str(tmp_path / "b.npz"), "--rrd", str(out), "--json", str(js),
                 "--quiet"])
    printed = capsys.readouterr().out
    assert code == 0
    assert "3 matched" in printed and "1 only in A, 1 only in B" in printed
    summary = json.loads(js.read_text())
    assert summary["matched"] == 3 and summary["estimate_delta_g"] == pytest.approx(10.0)
    reader = RrdReader(out)
    recordings = reader.recordings()
    assert len(recordings) == 2 and len({r.recording_id for r in recordings}) == 2
    assert {r.application_id for r in recordings} == {"massviz"}
    for entry in recordings:
        entities = {col.entity_path for col in reader.stream(store=entry).collect().schema().component_columns()}
        assert {"/compare", "/camera/detections", "/summary"} <= entities


def test_cli_errors_are_one_line(traces, tmp_path, capsys):
    a, _ = traces
    save_trace(a, tmp_path / "a.npz")
    assert main(["compare", str(tmp_path / "a.npz")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nothing to compare" in err[0]
    assert main(["compare", str(tmp_path / "a.npz"), str(tmp_path / "missing.npz")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no such trace file" in err[0]


@pytest.mark.slow
def test_cli_two_runs_of_one_recording(weights, samples_dir, tmp_path, capsys):
    code = main(["compare", str(samples_dir / "cup_handover"), "--detector", "depth", "--stride", "12",
                 "--weights", str(weights), "--cache", str(tmp_path / "cache"), "--quiet", "--b-k", "2"])
    printed = capsys.readouterr().out
    assert code == 0
    assert "settings that differ: k 5 -> 2" in printed and "0 only in A, 0 only in B" in printed
