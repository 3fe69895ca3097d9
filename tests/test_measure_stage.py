"""The measure stage (issue 19, "sinks only read"): the pipeline measures each detection as it enters the running K
nearest, the trace and its file carry the measurements, re-selection keeps those still chosen, and the views only
read them (Rerun's 3D boxes, the Open3D render): no view measures, and ``import massviz`` does not load Open3D."""
from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from massviz.core import geometry as G
from massviz.core.pipeline import run
from massviz.detect import make_detector
from massviz.io.recording import open_recording
from massviz.io.trace_file import load_trace, save_trace
from test_selection import DistanceModel

ROOT = Path(__file__).resolve().parents[1]
CUP = ROOT / "data_samples" / "cup_handover"


@pytest.fixture(scope="module")
def cup():
    return open_recording(CUP)


@pytest.fixture(scope="module")
def traced(cup):
    return run(cup, make_detector("depth"), DistanceModel(), k=3, stride=3)


def test_the_pipeline_measures_every_chosen_detection_as_a_fresh_measure_does(cup, traced):
    assert len(traced.selection) == 3
    stored = G.measurements_of(traced)
    assert [m.detection for m in stored] == [int(i) for i in traced.selection]
    assert [m.rank for m in stored] == [0, 1, 2]
    # the same numbers as measuring afterwards from the frames (what views used to do)
    fresh = G.measure(dataclasses.replace(traced, measurements=[]), cup)
    assert [m.to_dict() for m in fresh] == [m.to_dict() for m in stored]
    assert all(0 < m.height_mm < 1000 and 0 < m.width_mm < 1000 for m in stored)
    # the stage is timed once, at the end (where it measures), not per frame
    assert "measure3d" in traced.timings and "measure3d" not in traced.frame_timings


def test_only_the_detections_chosen_at_the_end_are_measured_and_at_most_k_crops_are_kept(cup, monkeypatch):
    from massviz.core.pipeline import FramePipeline

    measured, held = [], []
    real = G.measure_crop
    monkeypatch.setattr(G, "measure_crop", lambda crop, *a, **kw: measured.append(kw["detection"]) or real(crop, *a, **kw))
    fp = FramePipeline(make_detector("depth"), DistanceModel(), k=2, recording=cup.info(), measure=True)
    entered = set()
    for frame in cup.frames():
        result = fp.step(frame)
        entered |= {int(g) for g in result.selection if g >= result.offset}
        held.append(set(fp._crops))
        assert held[-1] == {int(g) for g in result.selection}  # exactly the running K nearest
    trace = fp.finish()
    assert sorted(measured) == sorted(int(i) for i in trace.selection)
    assert len(entered) > len(trace.selection), "the sample should have detections overtaken later"
    assert [m["detection"] for m in trace.measurements] == [int(i) for i in trace.selection]


def test_reselect_keeps_the_measurements_of_the_detections_still_chosen(traced):
    fewer = traced.reselect(k=1)
    assert [m["detection"] for m in fewer.measurements] == [int(traced.selection[0])]
    assert fewer.measurements[0]["rank"] == 0
    excluded = traced.reselect(exclude=[int(traced.selection[0])])
    kept = [m["detection"] for m in excluded.measurements]
    assert int(traced.selection[0]) not in kept and kept == [int(i) for i in excluded.selection if int(i) in kept]
    assert [m["rank"] for m in excluded.measurements] == [list(excluded.selection).index(d) for d in kept]


def test_measurements_survive_the_trace_file(traced, tmp_path):
    save_trace(traced, tmp_path / "t.npz")
    assert load_trace(tmp_path / "t.npz").measurements == traced.measurements


def test_no_measurement_without_intrinsics_or_when_turned_off(cup):
    off = run(cup, make_detector("depth"), DistanceModel(), k=2, stride=6, measure=False)
    assert off.measurements == [] and "measure3d" not in off.timings


def test_views_never_measure(cup, traced, tmp_path, monkeypatch):
    from massviz.views.rerun import log_trace
    from massviz.views.rerun_log import rrd_contents

    def refuse(*args, **kwargs):
        raise AssertionError("a view measured")

    monkeypatch.setattr(G, "measure_cloud", refuse)
    monkeypatch.setattr(G, "measure_detection", refuse)
    log_trace(traced, cup, rrd=tmp_path / "a.rrd")
    boxes = {e for e in rrd_contents(tmp_path / "a.rrd") if e.endswith("/box")}
    assert boxes == {f"/world/detections/{int(i)}/box" for i in traced.selection}
    # a trace without measurements: clouds, but no box (the view does not make one up)
    bare = dataclasses.replace(traced, measurements=[])
    log_trace(bare, cup, rrd=tmp_path / "b.rrd")
    assert not any(e.endswith("/box") for e in rrd_contents(tmp_path / "b.rrd"))


def test_import_massviz_does_not_load_open3d():
    code = "import sys, massviz, massviz.core.pipeline, massviz.views.rerun; print('open3d' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})
    assert out.stdout.strip() == "False"
