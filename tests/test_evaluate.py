"""Scoring library, challenge CSV writer, baselines and the ``score`` / ``baseline`` commands.

Expected values are computed here from the definition (ε = |m̂ − m| / m, s = mean of 1[estimated]·exp(−ε) over all
annotated recordings) with ``math.exp`` on a few rows, never with the code under test.
"""
from __future__ import annotations

import csv
import json
import math
import os
import random
from pathlib import Path

import pytest

from massviz.cli import main
from massviz.errors import DataError
from massviz.evaluation.metrics import (
    default_class_of,
    parse_class_map,
    read_predictions,
    score,
    score_from_estimates,
)
from massviz.io.atomic import atomic_path
from massviz.io.ccm_annotations import read_annotations
from massviz.io.challenge_csv import write_challenge_csv

# The challenge CSV header, copied from /work/shared/ccm/README.md.
README_COLUMNS = (
    "Configuration ID,Container capacity,Container mass,Filling mass,None,Pasta,Rice,Water,Filling type,Empty,"
    "Half-full,Full,Filling level,Width at the top,Width at the bottom,Height,Object safety,Distance,"
    "Angle difference,Execution time"
).split(",")
ANN_HEADER = ("id,container id,scenario,background,illumination,width at the top,width at the bottom,height,depth,"
              "container capacity,container mass,filling type,filling level,filling density,filling mass,"
              "object mass,handover starting frame,handover start timestamp,handover hand")


def write_ann(path: Path, rows: list[tuple[int, int, float]]) -> Path:
    """An annotation CSV with the real header; rows are (id, container id, container mass)."""
    lines = [ANN_HEADER] + [f"{i},{c},0,0,0,69.0,42.0,72.0,-1.0,185.0,{m},1,1,0.34,66.0,69.0,-1,-1,-1"
                            for i, c, m in rows]
    path.write_text("\n".join(lines) + "\n")
    return path


def write_pred(path: Path, rows: list[tuple[int, float]]) -> Path:
    """A challenge CSV with all 20 columns; rows are (id, container mass)."""
    lines = [",".join(README_COLUMNS)] + [f"{i},-1,{m}" + ",-1" * 16 + ",1.5" for i, m in rows]
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture
def ann3(tmp_path) -> Path:
    # a cup (container 1, 10 g), a glass (container 4, 100 g) and a box (container 7, 50 g)
    return write_ann(tmp_path / "ann.csv", [(1, 1, 10.0), (2, 4, 100.0), (3, 7, 50.0)])


# ------------------------------------------------------------------------------------------------------ the score
def test_score_hand_computed(tmp_path, ann3):
    pred = write_pred(tmp_path / "pred.csv", [(1, 12), (2, 50), (3, 50)])
    report = score(read_predictions(pred), read_annotations(ann3))
    eps = {"cup": 2 / 10, "glass": 50 / 100, "box": 0 / 50}
    assert report.score == pytest.approx((math.exp(-0.2) + math.exp(-0.5) + math.exp(0)) / 3)
    assert report.score_pct == pytest.approx(100 * (math.exp(-0.2) + math.exp(-0.5) + 1) / 3)
    assert report.mean_eps == pytest.approx((0.2 + 0.5 + 0.0) / 3)
    assert list(report.per_class.index) == ["cup", "glass", "box"]
    for name, e in eps.items():
        assert report.per_class.loc[name, "score_pct"] == pytest.approx(100 * math.exp(-e))
        assert report.per_class.loc[name, "mean_eps"] == pytest.approx(e)
        assert report.per_class.loc[name, "recordings"] == 1
    assert report.per_container.loc[4, "class"] == "glass"
    assert report.per_recording.loc[1, "eps"] == pytest.approx(0.2)
    assert report.ignored_ids == ()


def test_missing_negative_zero_and_extra_predictions(tmp_path):
    ann = write_ann(tmp_path / "ann.csv", [(10, 1, 4.0), (11, 2, 8.0), (12, 3, 2.0), (13, 5, 20.0)])
    # 10: estimated 5 g (ε 0.25); 11: -1 (not estimated); 12: missing; 13: 0 g is an estimate (ε 1); 99, 7: not annotated
    pred = write_pred(tmp_path / "pred.csv", [(10, 5), (11, -1), (13, 0), (99, 30), (7, 1)])
    report = score(read_predictions(pred), read_annotations(ann))
    assert report.score == pytest.approx((math.exp(-0.25) + 0 + 0 + math.exp(-1)) / 4)
    assert report.mean_eps == pytest.approx((0.25 + 1.0) / 2)  # over the estimated recordings only
    assert (report.n_recordings, report.n_estimated) == (4, 2)
    assert report.ignored_ids == (7, 99)
    cup = report.per_class.loc["cup"]
    assert (cup["recordings"], cup["estimated"]) == (3, 1)
    assert cup["score_pct"] == pytest.approx(100 * math.exp(-0.25) / 3)
    assert cup["mean_eps"] == pytest.approx(0.25)
    assert math.isnan(report.per_recording.loc[11, "eps"]) and math.isnan(report.per_recording.loc[12, "pred_g"])
    assert report.per_recording.loc[12, "s"] == 0
    assert "ignored 2 predicted recordings not in the annotations: 7, 99" in report.format()


def test_nothing_estimated_gives_zero_and_json_nulls(tmp_path, ann3):
    report = score_from_estimates({1: -1, 2: None}, read_annotations(ann3))
    assert report.score == 0 and math.isnan(report.mean_eps)
    doc = json.loads(json.dumps(report.to_dict()))  # must be JSON-serialisable
    assert doc["mean_eps"] is None and doc["score_pct"] == 0
    assert doc["per_class"][0]["mean_eps"] is None
    assert "score 0.00 %" in report.format()


def test_score_from_estimates_matches_definition(ann3):
    report = score_from_estimates({1: 9.0, 3: 75.0}, read_annotations(ann3))
    assert report.score == pytest.approx((math.exp(-0.1) + math.exp(-0.5)) / 3)
    assert report.per_class.loc["glass", "estimated"] == 0


def test_format_and_to_dict(tmp_path, ann3):
    report = score_from_estimates({1: 12, 2: 50, 3: 50}, read_annotations(ann3))
    expected = 100 * (math.exp(-0.2) + math.exp(-0.5) + 1) / 3
    text = report.format()
    assert text.splitlines()[0].startswith(f"score {expected:.2f} % over 3 recordings (3 estimated)")
    assert "per class:" in text and "per container:" in text and "0.200" in text  # ε with 3 decimals
    doc = report.to_dict()
    assert doc["score_pct"] == pytest.approx(expected)
    assert [row["class"] for row in doc["per_class"]] == ["cup", "glass", "box"]
    assert [row["container"] for row in doc["per_container"]] == [1, 4, 7]
    assert [row["id"] for row in doc["per_recording"]] == [1, 2, 3]


# ------------------------------------------------------------------------------------------------------ classes
def test_custom_class_mapping(ann3):
    ann = read_annotations(ann3)
    report = score_from_estimates({1: 12, 2: 50, 3: 50}, ann, class_of={1: "small", 4: "small", 7: "big"})
    assert sorted(report.per_class.index) == ["big", "small"]
    assert report.per_class.loc["small", "recordings"] == 2
    assert report.per_class.loc["small", "score_pct"] == pytest.approx(100 * (math.exp(-0.2) + math.exp(-0.5)) / 2)
    with pytest.raises(DataError, match="container 7 is not in the class mapping"):
        score_from_estimates({}, ann, class_of={1: "cup", 4: "glass"})


def test_default_classes_and_unknown_container():
    assert [default_class_of(c) for c in range(1, 10)] == ["cup"] * 3 + ["glass"] * 3 + ["box"] * 3
    with pytest.raises(DataError, match="container 10 has no class"):
        default_class_of(10)


def test_parse_class_map(tmp_path):
    assert parse_class_map("1=cup, 2=cup,4=glass") == {1: "cup", 2: "cup", 4: "glass"}
    spec = tmp_path / "classes.json"
    spec.write_text('{"1": "cup", "7": "box"}')
    assert parse_class_map(str(spec)) == {1: "cup", 7: "box"}
    for bad, message in [("one=cup", "'one' is not a container id"), ("1=", "container 1 has no class"),
                         (",", "empty"), (str(tmp_path / "missing.json"), "cannot read")]:
        with pytest.raises(DataError, match=message):
            parse_class_map(bad)


# ------------------------------------------------------------------------------------------------------ bad files
def test_duplicate_prediction_is_an_error(tmp_path, ann3):
    pred = write_pred(tmp_path / "pred.csv", [(1, 12), (2, 50), (1, 11)])
    with pytest.raises(DataError) as err:
        read_predictions(pred)
    message = str(err.value)
    assert str(pred) in message and "row 3 (line 4), column 'Configuration ID'" in message
    assert "already appears in row 1" in message
    # a hand-built frame with duplicates is refused by score() too
    frame = read_predictions(write_pred(tmp_path / "ok.csv", [(1, 12)]))
    with pytest.raises(DataError, match="recording 1 is predicted more than once"):
        score(frame.loc[[0, 0]], read_annotations(ann3))


PRED_HEADER = ",".join(README_COLUMNS)


@pytest.mark.parametrize(
    "text, expected",
    [
        ("", "empty file"),
        ("Configuration ID,Execution time\n1,2.0\n", "header: missing column 'Container mass'"),
        (f"{PRED_HEADER}\n1,-1,12" + ",-1" * 17 + "\n2,-1,abc" + ",-1" * 17 + "\n",
         "row 2 (line 3), column 'Container mass': 'abc' is not a number"),
        (f"{PRED_HEADER}\n1,-1," + ",-1" * 17 + "\n", "row 1 (line 2), column 'Container mass': empty value"),
        (f"{PRED_HEADER}\n1,-1,nan" + ",-1" * 17 + "\n", "column 'Container mass': 'nan' is not a finite number"),
        (f"{PRED_HEADER}\n1.5,-1,3" + ",-1" * 17 + "\n", "row 1 (line 2), column 'Configuration ID': '1.5' is not an integer"),
        (f"{PRED_HEADER}\n1,-1,3\n", "row 1 (line 2), column 'Filling mass': missing"),
        (f"{PRED_HEADER}\n1,-1,3" + ",-1" * 18 + "\n", "row 1 (line 2): 21 fields, but the header has only 20"),
        (b"\x89PNG\r\n\x1a\n\x00\x00\xff\xfe", "not a CSV file"),
    ],
)
def test_malformed_predictions(tmp_path, text, expected):
    path = tmp_path / "bad.csv"
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    with pytest.raises(DataError) as err:
        read_predictions(path)
    message = str(err.value)
    assert message.startswith(f"{path}: ") and expected in message and "\n" not in message


@pytest.mark.parametrize(
    "rows, expected",
    [
        ([(1, 1, 10.0), (2, 4, 0.0)], "row 2 (line 3), column 'container mass': the true mass must be > 0 g"),
        ([(1, 1, -3.0)], "row 1 (line 2), column 'container mass': the true mass must be > 0 g"),
        ([(1, 1, 10.0), (1, 4, 5.0)], "row 2 (line 3), column 'id': recording 1 already appears in row 1"),
        ([], "no annotated recordings"),
    ],
)
def test_malformed_annotations(tmp_path, rows, expected):
    path = write_ann(tmp_path / "ann.csv", rows)
    with pytest.raises(DataError) as err:
        read_annotations(path)
    assert str(err.value).startswith(f"{path}: ") and expected in str(err.value)


def test_missing_file_is_a_data_error(tmp_path):
    with pytest.raises(DataError, match="cannot read the file"):
        read_annotations(tmp_path / "nope.csv")


# ------------------------------------------------------------------------------------------------------ challenge CSV
class _Estimate:
    def __init__(self, config_id, mass_g, exec_time_s):
        self.config_id, self.mass_g, self.exec_time_s = config_id, mass_g, exec_time_s


def test_write_challenge_csv_truncates_like_the_paper(tmp_path):
    path = tmp_path / "pred.csv"
    write_challenge_csv(path, [{"config_id": 5, "mass_g": 12.9, "exec_time_s": 3.14159},
                               _Estimate(6, -1, 0.5), _Estimate(7, None, 0), {"config_id": 8, "mass_g": 0.4,
                                                                              "exec_time_s": 1}])
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    assert rows[0] == README_COLUMNS
    assert [r[2] for r in rows[1:]] == ["12", "-1", "-1", "0"]
    assert [r[-1] for r in rows[1:]] == ["3.14", "0.50", "0.00", "1.00"]
    assert all(v == "-1" for r in rows[1:] for v in r[1:2] + r[3:-1])
    assert read_predictions(path)["Container mass"].tolist() == [12, -1, -1, 0]

    write_challenge_csv(path, [_Estimate(5, 12.956, 1)], exact=True)
    assert read_predictions(path)["Container mass"].tolist() == [12.96]


def test_write_challenge_csv_refuses_bad_rows(tmp_path):
    with pytest.raises(ValueError, match="recording 1 appears twice"):
        write_challenge_csv(tmp_path / "p.csv", [_Estimate(1, 2, 0), _Estimate(1, 3, 0)])
    with pytest.raises(ValueError, match="not a finite number"):
        write_challenge_csv(tmp_path / "p.csv", [_Estimate(1, float("nan"), 0)])
    assert not (tmp_path / "p.csv").exists()


def test_atomic_path_keeps_the_old_file_on_failure(tmp_path):
    path = tmp_path / "out.json"
    path.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_path(path) as tmp:
            tmp.write_text("half")
            raise RuntimeError("interrupted")
    assert path.read_text() == "old" and os.listdir(tmp_path) == ["out.json"]


# ------------------------------------------------------------------------------------------------------ CLI
def test_cli_score_prints_and_writes_json(tmp_path, ann3, capsys):
    pred = write_pred(tmp_path / "pred.csv", [(1, 12), (2, 50), (3, 50), (42, 1)])
    out = tmp_path / "score.json"
    assert main(["score", str(pred), "--annotations", str(ann3), "--json", str(out)]) == 0
    expected = 100 * (math.exp(-0.2) + math.exp(-0.5) + 1) / 3
    stdout = capsys.readouterr().out
    assert stdout.startswith(f"score {expected:.2f} %")
    assert "per class:" in stdout and "per container:" in stdout and ": 42" in stdout
    doc = json.loads(out.read_text())
    assert doc["score_pct"] == pytest.approx(expected) and doc["ignored_ids"] == [42]
    assert doc["predictions"] == str(pred) and doc["label"] == "pred"


def test_cli_score_custom_classes(tmp_path, ann3, capsys):
    pred = write_pred(tmp_path / "pred.csv", [(1, 12), (2, 50), (3, 50)])
    assert main(["score", str(pred), "--annotations", str(ann3), "--classes", "1=light,4=light,7=heavy"]) == 0
    stdout = capsys.readouterr().out
    assert "light" in stdout and "heavy" in stdout and "glass" not in stdout


@pytest.mark.parametrize("make_args, expected", [
    (lambda p, a, t: ["score", str(t / "bad.csv"), "--annotations", str(a)], "row 1 (line 2), column 'Container mass'"),
    (lambda p, a, t: ["score", str(p), str(p), "--annotations", str(a), str(a), str(a)],
     "2 prediction files but 3 annotation files"),
    (lambda p, a, t: ["score", str(p), "--annotations", str(a), "--labels", "x", "y"], "1 prediction files but 2 labels"),
    (lambda p, a, t: ["score", str(p), "--annotations", str(a), "--classes", "1=cup"], "container 4 is not in"),
    (lambda p, a, t: ["score", str(p), "--annotations", str(a), "--plot", str(t / "fig.xyz")], "cannot write a figure"),
    (lambda p, a, t: ["score", str(p), "--annotations", str(a), "--json", str(t / "no" / "x.json")], "does not exist"),
])
def test_cli_score_bad_input_exits_2_without_traceback(tmp_path, ann3, capsys, make_args, expected):
    pred = write_pred(tmp_path / "pred.csv", [(1, 12)])
    (tmp_path / "bad.csv").write_text(f"{PRED_HEADER}\n1,-1,twelve" + ",-1" * 17 + "\n")
    assert main(make_args(pred, ann3, tmp_path)) == 2
    captured = capsys.readouterr()
    assert expected in captured.err and "Traceback" not in captured.err
    assert len(captured.err.strip().splitlines()) == 1


def test_cli_score_plot_several_splits(tmp_path, ann3, capsys):
    first = write_pred(tmp_path / "a.csv", [(1, 12), (2, 50), (3, 50)])
    second = write_pred(tmp_path / "b.csv", [(1, 300), (2, -1)])  # ε 29 for the cup: clipped bar
    plot, out = tmp_path / "fig4.png", tmp_path / "all.json"
    assert main(["score", str(first), str(second), "--annotations", str(ann3), "--labels", "A", "B",
                 "--plot", str(plot), "--json", str(out)]) == 0
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and plot.stat().st_size > 1000
    assert [d["label"] for d in json.loads(out.read_text())] == ["A", "B"]
    stdout = capsys.readouterr().out
    assert f"== A: {first} vs {ann3}" in stdout and f"== B: {second} vs {ann3}" in stdout
    assert sorted(os.listdir(tmp_path)) == ["a.csv", "all.json", "ann.csv", "b.csv", "fig4.png"]  # no temp left


# ------------------------------------------------------------------------------------------------------ baselines
def _read_csv(path: Path) -> list[list[str]]:
    with open(path, newline="") as f:
        return list(csv.reader(f))


def test_baseline_random_is_seeded_mersenne_twister(tmp_path, ann3, capsys):
    paths = [tmp_path / name for name in ("a.csv", "b.csv", "c.csv")]
    for path, seed in zip(paths, ("7", "7", "8"), strict=False):
        assert main(["baseline", "random", "--annotations", str(ann3), "--out", str(path), "--seed", seed]) == 0
    assert paths[0].read_bytes() == paths[1].read_bytes() != paths[2].read_bytes()
    rows = _read_csv(paths[0])
    assert rows[0] == README_COLUMNS
    rng = random.Random(7)
    assert [r[:3] for r in rows[1:]] == [[str(i), "-1", str(int(rng.uniform(1, 351)))] for i in (1, 2, 3)]
    assert all(v == "-1" for r in rows[1:] for v in r[3:-1])
    assert "wrote 3 random predictions" in capsys.readouterr().out


def test_baseline_average_uses_training_masses(tmp_path, ann3):
    train = write_ann(tmp_path / "train.csv", [(100, 1, 10.0), (101, 2, 20.0), (102, 8, 45.5)])
    out = tmp_path / "m5.csv"
    assert main(["baseline", "average", "--annotations", str(ann3), "--train", str(train), "--out", str(out)]) == 0
    rows = _read_csv(out)
    assert rows[0] == README_COLUMNS
    assert [(r[0], r[2]) for r in rows[1:]] == [("1", "25"), ("2", "25"), ("3", "25")]  # int(75.5 / 3 = 25.17)

    # --train defaults to --annotations; --exact keeps the decimals
    assert main(["baseline", "average", "--annotations", str(ann3), "--out", str(out), "--exact"]) == 0
    assert {r[2] for r in _read_csv(out)[1:]} == {f"{(10 + 100 + 50) / 3:.2f}"}


def test_baseline_bad_annotations_exit_2(tmp_path, capsys):
    bad = write_ann(tmp_path / "ann.csv", [(1, 1, 0.0)])
    assert main(["baseline", "average", "--annotations", str(bad), "--out", str(tmp_path / "o.csv")]) == 2
    err = capsys.readouterr().err
    assert "column 'container mass'" in err and "Traceback" not in err
    assert not (tmp_path / "o.csv").exists()


# ------------------------------------------------------------------------------------------------------ the paper
PAPER = os.environ.get("MASSVIZ_PAPER_PREDICTIONS")


@pytest.mark.skipif(not PAPER, reason="opt-in: set MASSVIZ_PAPER_PREDICTIONS to the folder of the authors' "
                    "Visual_*.csv prediction files")
@pytest.mark.parametrize("pred, ann, total, per_class, cup_eps", [
    ("Visual_val_pool_aug.csv", "Val_annotations.csv", 71.08, {"cup": 49.86, "glass": 83.41, "box": 86.72}, 2.091),
    ("Visual_pool_aug_fold0.csv", "test_annotations_fold0.csv", 9.62, None, 22.952),
    ("Visual_pool_aug_fold1.csv", "test_annotations_fold1.csv", 37.42, None, None),
    ("Visual_pool_aug_fold2.csv", "test_annotations_fold2.csv", 44.54, None, None),
])
def test_paper_figure_4(shared_dir, pred, ann, total, per_class, cup_eps):
    report = score(read_predictions(Path(PAPER) / pred), read_annotations(shared_dir / "ccm" / "annotations" / ann))
    assert round(report.score_pct, 2) == total
    for name, value in (per_class or {}).items():
        assert round(report.per_class.loc[name, "score_pct"], 2) == value
    if cup_eps is not None:
        assert round(report.per_class.loc["cup", "mean_eps"], 3) == cup_eps


@pytest.mark.parametrize("n", [1, 3, 40])
def test_summary_table_equals_pandas_named_aggregation(n):
    """``_summary`` (one reduction per column, for slider speed) gives the frame pandas' named aggregation gives:
    values, dtypes, index name and order, with recordings not estimated (NaN ε) and one-recording groups."""
    import numpy as np
    import pandas as pd

    from massviz.evaluation.metrics import _summary

    rng = np.random.default_rng(n)
    frame = pd.DataFrame({"class": rng.choice(["cup", "glass", "box"], n), "container": rng.integers(1, 9, n),
                          "s": rng.random(n), "estimated": rng.random(n) > 0.3,
                          "eps": np.where(rng.random(n) > 0.3, rng.random(n), np.nan)})
    for by in ("class", "container"):
        want = frame.groupby(by).agg(recordings=("s", "size"), estimated=("estimated", "sum"),
                                     score_pct=("s", "mean"), mean_eps=("eps", "mean"))
        want["score_pct"] *= 100
        pd.testing.assert_frame_equal(_summary(frame, by), want)
