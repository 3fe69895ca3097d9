"""The ``massviz`` command line, run as a user runs it (a subprocess): malformed recordings give exit code 2, one
line on stderr naming the file, no traceback and no output file; ``estimate`` writes a valid challenge CSV.

The subprocesses of a test group are started together (two at a time) so the module stays quick on 2 cores.
"""
from __future__ import annotations

import csv
import json
import re
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
import pytest

from fakes import OPEN_ERRORS, corrupt_middle_depth
from support import run_massviz as massviz

pytestmark = pytest.mark.slow  # every test runs massviz as subprocesses (dozens of recordings)

CCM_VIDEO = Path("ccm_real/view1/rgb/000000.mp4")
HELD_BOX = [672, 262, 776, 408]  # the box held in frame index 1 of the CCM sample (shared/ccm_real/README.md)


def run_many(calls: dict) -> dict:
    with ThreadPoolExecutor(max_workers=2) as pool:
        futures = {name: pool.submit(massviz, *args) for name, args in calls.items()}
    return {name: f.result() for name, f in futures.items()}


def visible_lines(stderr: str) -> list[str]:
    """What a terminal shows: progress bars redraw with carriage returns, so each line is its last segment."""
    lines = [line.split("\r")[-1] for line in stderr.split("\n")]
    return [line for line in lines if line.strip()]


@pytest.fixture(scope="module")
def bad_runs(tmp_path_factory, weights):
    """Every malformed recording through `estimate` and `log`: {(command, case): (result, culprit, output, what)}."""
    base = tmp_path_factory.mktemp("cli_bad")
    replay = base / "none.json"
    replay.write_text(json.dumps({"detections": []}))
    calls, expect = {}, {}
    for build in [*OPEN_ERRORS, corrupt_middle_depth]:
        for command in ("estimate", "log"):
            case = build.__name__
            if (command, case) not in CASES:
                continue
            work = base / command / case
            work.mkdir(parents=True)
            path, culprit, what = build(work / "rec")
            if command == "estimate" and case == "bad_empty_folder":
                what = "no recordings found"  # estimate also takes dataset roots: an empty one holds none
            out = work / ("preds.csv" if command == "estimate" else "out.rrd")
            args = [command, path, "--out" if command == "estimate" else "--rrd", out, "--detector", "replay",
                    "--replay", replay, "--weights", weights, "--cache", work / "cache"]
            calls[command, case] = args
            expect[command, case] = (culprit, out, what)
    results = run_many(calls)
    return {key: (results[key], *expect[key]) for key in calls}


#: every malformed recording through both commands, except that 'log' runs on a recording without depth (RGB only:
#: detections and tracks, test_real_ccm's test_rgb_only_recording_...)
CASES = [(command, build.__name__) for build in [*OPEN_ERRORS, corrupt_middle_depth] for command in ("estimate", "log")
         if (command, build.__name__) != ("log", "bad_missing_depth")]


@pytest.mark.parametrize("command,case", CASES, ids=[f"{c}-{b}" for c, b in CASES])
def test_bad_recording_one_line_exit_2(bad_runs, command, case):
    result, culprit, out, what = bad_runs[command, case]
    assert "Traceback" not in result.stderr + result.stdout
    assert result.returncode == 2, result.stderr
    lines = visible_lines(result.stderr)
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith(f"massviz {command}: error: {culprit}: "), lines[0]
    assert re.search(what, lines[0]), lines[0]
    assert not out.exists()
    assert not [p.name for p in out.parent.iterdir() if p.name.startswith(("." + out.name, out.name))]


def test_help_mentions_the_options():
    results = run_many({"top": ["--help"], "estimate": ["estimate", "--help"], "log": ["log", "--help"]})
    assert all(r.returncode == 0 for r in results.values())
    top = results["top"].stdout
    assert "estimate" in top and "log" in top
    for name in ("estimate", "log"):
        text = results[name].stdout
        for option in ("--detector", "--threshold", "--k", "--stride", "--weights", "--detector-weights",
                       "--replay", "--cache", "--no-cache", "--quiet"):
            assert re.search(rf"{option}\b", text), (name, option)
        for detector in ("auto", "maskrcnn", "depth", "replay"):
            assert detector in text
    assert all(o in results["estimate"].stdout for o in ("--out", "--view", "--exact"))
    assert all(o in results["log"].stdout for o in ("--rrd", "--spawn"))


def readme_columns(shared_dir: Path) -> list[str]:
    lines = (shared_dir / "ccm" / "README.md").read_text().splitlines()
    at = next(i for i, line in enumerate(lines) if line.startswith("Challenge prediction CSV columns"))
    return [c.strip() for c in " ".join(lines[at + 1:at + 3]).split(",")]


def held_box_prediction(shared_dir: Path, weights: Path) -> float:
    """The mass CNN's prediction for the held box, with d, a, b computed here from the frame and its depth."""
    from massviz.io.checkpoint import load_checkpoint

    cap = cv2.VideoCapture(str(shared_dir / CCM_VIDEO))
    for _ in range(2):
        ok, bgr = cap.read()
        assert ok
    cap.release()
    rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    depth = cv2.imread(str(shared_dir / "ccm_real/view1/depth/000000/0001.png"), cv2.IMREAD_UNCHANGED)
    x1, y1, x2, y2 = HELD_BOX
    values = depth[y1:y2, x1:x2].astype(np.float64)
    d = round(float(values[values > 0].mean()), 2)
    feats = [[round((x2 - x1) / 1280, 2), round((y2 - y1) / 720, 2), d]]
    return float(load_checkpoint(weights).predict([rgb[y1:y2, x1:x2]], np.array(feats))[0])


@pytest.fixture(scope="module")
def ccm_runs(shared_dir, weights, tmp_path_factory):
    base = tmp_path_factory.mktemp("cli_ccm")
    replay = base / "held.json"
    replay.write_text(json.dumps({"detections": [{"frame": 1, "box": HELD_BOX, "score": 0.9, "class": "book"}]}))
    video = shared_dir / CCM_VIDEO
    calls = {"replay": ["estimate", video, "--out", base / "replay.csv", "--detector", "replay", "--replay", replay,
                        "--weights", weights, "--cache", base / "cache", "--quiet"],
             "exact": ["estimate", video, "--out", base / "exact.csv", "--detector", "replay", "--replay", replay,
                       "--weights", weights, "--no-cache", "--exact", "--quiet"]}
    try:
        import massviz.detect.depth  # noqa: F401 - written concurrently; tested when present
        calls["depth"] = ["estimate", video, "--out", base / "depth.csv", "--detector", "depth", "--weights",
                          weights, "--cache", base / "cache", "--quiet"]
    except ImportError:
        pass
    return base, run_many(calls)


def read_csv(path: Path) -> list[list[str]]:
    with open(path, newline="") as f:
        return list(csv.reader(f))


def test_estimate_ccm_writes_the_challenge_csv(ccm_runs, shared_dir, weights):
    base, results = ccm_runs
    for name in ("replay", "exact"):
        assert results[name].returncode == 0, results[name].stderr
    pred = held_box_prediction(shared_dir, weights)
    for name, mass in (("replay", str(int(pred))), ("exact", f"{pred:.2f}")):
        header, *rows = read_csv(base / f"{name}.csv")
        assert header == readme_columns(shared_dir) and len(header) == 20
        assert len(rows) == 1 and len(rows[0]) == 20
        row = dict(zip(header, rows[0], strict=False))
        assert row["Configuration ID"] == "0"
        assert row["Container mass"] == mass
        assert float(row["Execution time"]) > 0
        assert all(v == "-1" for k, v in row.items() if k not in ("Configuration ID", "Container mass",
                                                                    "Execution time"))


def test_estimate_ccm_with_the_depth_detector(ccm_runs, shared_dir):
    base, results = ccm_runs
    if "depth" not in results:
        pytest.skip("massviz.detect.depth is not importable yet")
    assert results["depth"].returncode == 0, results["depth"].stderr
    header, *rows = read_csv(base / "depth.csv")
    assert header == readme_columns(shared_dir) and [len(r) for r in rows] == [20]
    assert rows[0][0] == "0" and (rows[0][2] == "-1" or int(rows[0][2]) >= 0)
