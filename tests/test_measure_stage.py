"""The measure stage (``massviz.measure3d.stage.MeasureStage``): observing a run, it keeps the frames of the running K
nearest and measures the detections chosen at the end; the trace and its file carry the typed measurements,
re-selection keeps those still chosen, and the views only read them (Rerun's 3D boxes, the Open3D render): no view
measures. Each cloud is made once for the Rerun recording, the measurements and the .ply files, and neither
``import massviz`` nor ``massviz estimate`` loads Open3D."""
from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from fakes import DistanceModel
from massviz.core.measurement import Measurement
from massviz.core.pipeline import run
from massviz.detect import make_detector
from massviz.io.recording import open_recording
from massviz.io.trace_file import load_trace, save_trace
from massviz.measure3d import geometry as G
from massviz.measure3d.stage import MeasureStage

ROOT = Path(__file__).resolve().parents[1]
CUP = ROOT / "data_samples" / "cup_handover"


@pytest.fixture(scope="module")
def cup():
    return open_recording(CUP)


@pytest.fixture(scope="module")
def traced(cup):
    stage = MeasureStage(cup)
    return stage.finish(run(cup, make_detector("depth"), DistanceModel(), k=3, stride=3, on_frame=stage.on_frame))


def test_the_stage_measures_every_chosen_detection_as_a_fresh_measure_does(cup, traced):
    assert len(traced.selection) == 3
    stored = traced.measurements
    assert all(isinstance(m, Measurement) for m in stored)
    assert [m.detection for m in stored] == [int(i) for i in traced.selection]
    assert [m.rank for m in stored] == [0, 1, 2]
    # the same numbers as measuring afterwards from the frames read again (a stage that observed nothing)
    fresh = MeasureStage(cup).measurements(dataclasses.replace(traced, measurements=[]))
    assert [m.to_dict() for m in fresh] == [m.to_dict() for m in stored]
    assert all(0 < m.height_mm < 1000 and 0 < m.width_mm < 1000 for m in stored)
    # the stage is timed once, at the end, not per frame
    assert "measure3d" in traced.timings and "measure3d" not in traced.frame_timings


def test_only_the_detections_chosen_at_the_end_are_measured_and_at_most_k_frames_are_kept(cup, monkeypatch):
    from massviz.core.pipeline import FramePipeline

    measured, held = [], []
    real = G.measure_cloud_as
    monkeypatch.setattr(G, "measure_cloud_as", lambda pcd, **kw: measured.append(kw["detection"]) or real(pcd, **kw))
    fp = FramePipeline(make_detector("depth"), DistanceModel(), k=2, recording=cup.info())
    stage = MeasureStage(cup)
    entered, frame_of = set(), {}
    for frame in cup.frames():
        result = fp.step(frame)
        assert stage.on_frame(frame, result) == {}  # "chosen": no cloud while observing
        for g in result.selection[result.selection >= result.offset]:
            entered.add(int(g))
            frame_of[int(g)] = frame.index
        held.append(set(stage._kept))
        assert held[-1] == {frame_of[int(g)] for g in result.selection}  # the frames of the running K nearest
        assert len(held[-1]) <= 2
    trace = stage.finish(fp.finish())
    assert sorted(measured) == sorted(int(i) for i in trace.selection)
    assert len(entered) > len(trace.selection), "the sample should have detections overtaken later"
    assert [m.detection for m in trace.measurements] == [int(i) for i in trace.selection]


def test_active_clouds_are_those_of_the_steps_active_detections(cup):
    """In ``"active"`` mode the stage makes the clouds of ``FrameResult.active`` (the pipeline's decision), nothing
    else: it applies no score cut of its own."""
    from massviz.core.pipeline import FramePipeline

    fp = FramePipeline(make_detector("depth"), DistanceModel(), k=2, recording=cup.info())
    stage = MeasureStage(cup, clouds="active")
    frame, result = next((f, r) for f, r in ((f, fp.step(f)) for f in cup.frames()) if len(r.active))
    assert sorted(stage.on_frame(frame, result)) == [result.offset + int(j) for j in result.active]
    fewer = dataclasses.replace(result, active=result.active[1:])  # the same scores, one detection fewer active
    assert sorted(stage.on_frame(frame, fewer)) == [result.offset + int(j) for j in result.active[1:]]


def test_reselect_keeps_the_measurements_of_the_detections_still_chosen(traced):
    fewer = traced.reselect(k=1)
    assert [m.detection for m in fewer.measurements] == [int(traced.selection[0])]
    assert fewer.measurements[0].rank == 0
    excluded = traced.reselect(exclude=[int(traced.selection[0])])
    kept = [m.detection for m in excluded.measurements]
    assert int(traced.selection[0]) not in kept and kept == [int(i) for i in excluded.selection if int(i) in kept]
    assert [m.rank for m in excluded.measurements] == [list(excluded.selection).index(d) for d in kept]


def test_measurements_survive_the_trace_file(traced, tmp_path):
    save_trace(traced, tmp_path / "t.npz")
    assert load_trace(tmp_path / "t.npz").measurements == traced.measurements


@pytest.mark.parametrize("damage", [lambda m: m.pop("R"), lambda m: m.update(height_mm="tall"),
                                    lambda m: m.update(center=[0.0, 1.0]), lambda m: m.update(R=[["a"] * 3] * 3)])
def test_a_trace_file_with_damaged_measurements_is_one_error_line(traced, tmp_path, damage):
    import json

    from massviz.errors import MassvizError

    save_trace(traced, tmp_path / "t.npz")
    data = dict(np.load(tmp_path / "t.npz"))
    header = json.loads(data["header"].tobytes())
    damage(header["measurements"][0])
    data["header"] = np.frombuffer(json.dumps(header).encode(), dtype=np.uint8)
    np.savez_compressed(tmp_path / "bad.npz", **data)
    with pytest.raises(MassvizError, match="measurements") as err:
        load_trace(tmp_path / "bad.npz")
    assert "\n" not in str(err.value) and "bad.npz" in str(err.value)


def test_no_measurement_without_intrinsics_or_without_the_stage(cup):
    off = run(cup, make_detector("depth"), DistanceModel(), k=2, stride=6)
    assert off.measurements == [] and "measure3d" not in off.timings
    blind = dataclasses.replace(cup, intrinsics=None)
    stage = MeasureStage(blind, clouds="active")
    assert not stage.enabled and "no camera intrinsics" in stage.skip
    assert stage.finish(off) is off and stage.ply_clouds(off) is None


def test_views_never_measure(cup, traced, tmp_path, monkeypatch):
    from massviz.views.rerun import log_trace_with_clouds
    from rrd_reader import rrd_contents

    def refuse(*args, **kwargs):
        raise AssertionError("a view measured")

    monkeypatch.setattr(G, "measure_cloud", refuse)
    monkeypatch.setattr(G, "measure_detection", refuse)
    monkeypatch.setattr(G, "measure_cloud_as", refuse)
    log_trace_with_clouds(traced, cup, rrd=tmp_path / "a.rrd",
                          frames=MeasureStage(cup, clouds="active").replay_frames(traced))
    boxes = {e for e in rrd_contents(tmp_path / "a.rrd") if e.endswith("/box")}
    assert boxes == {f"/world/detections/{int(i)}/box" for i in traced.selection}
    # a trace without measurements: clouds, but no box (the view does not make one up)
    bare = dataclasses.replace(traced, measurements=[])
    log_trace_with_clouds(bare, cup, rrd=tmp_path / "b.rrd",
                          frames=MeasureStage(cup, clouds="active").replay_frames(bare))
    contents = rrd_contents(tmp_path / "b.rrd")
    assert any(e.startswith("/world/detections/") for e in contents)
    assert not any(e.endswith("/box") for e in contents)
    # without the stage's clouds the view makes none
    log_trace_with_clouds(traced, cup, rrd=tmp_path / "c.rrd")
    assert not any(e.startswith("/world/detections/") for e in rrd_contents(tmp_path / "c.rrd"))


def test_log_with_ply_makes_each_cloud_once(samples_dir, weights, tmp_path, monkeypatch):
    # an uncached `massviz log --ply` of a sample with intrinsics: the Rerun recording's clouds, the measurements and
    # the .ply files all come from one cloud per detection, the chosen ones included
    from massviz.cli import main
    from rrd_reader import rrd_entities

    made = []
    real = G.Crop.cloud
    monkeypatch.setattr(G.Crop, "cloud", lambda crop, *a, **kw: made.append((crop.frame, crop.xyxy)) or
                        real(crop, *a, **kw))
    rec = samples_dir / "cup_handover"
    assert open_recording(rec).intrinsics is not None
    assert main(["log", str(rec), "--detector", "depth", "--no-cache", "--quiet", "--weights", str(weights),
                 "--rrd", str(tmp_path / "c.rrd"), "--ply", str(tmp_path / "ply")]) == 0
    chosen = sorted(p.name for p in (tmp_path / "ply").iterdir() if p.name.startswith("chosen_"))
    assert chosen == [f"chosen_{r}.ply" for r in range(5)]
    entities = rrd_entities(tmp_path / "c.rrd")
    clouds = {e for e in entities if e.count("/") == 3 and e.startswith("/world/detections/")}
    assert len({e for e in entities if e.endswith("/measurement")}) == 5
    # every detection shown got exactly one cloud, and the chosen ones (measured, written) none more
    assert len(made) == len(set(made)) and len(made) >= len(clouds) > 5


def test_import_massviz_does_not_load_open3d():
    code = "import sys, massviz, massviz.core.pipeline, massviz.views.rerun; print('open3d' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})
    assert out.stdout.strip() == "False"


@pytest.mark.slow  # a fresh interpreter runs massviz estimate (what it imports is the point)
@pytest.mark.parametrize("recording", ["../shared/ccm_real/618", "data_samples/cup_handover"])
def test_estimate_of_a_recording_never_loads_open3d(recording, shared_dir, weights, tmp_path):
    # uncached; cup_handover has intrinsics (the recordings the measure stage would measure)
    code = ("import sys\nfrom massviz.cli import main\n"
            f"rc = main(['estimate', {recording!r}, '--detector', 'depth', '--no-cache', '--quiet', "
            f"'--weights', {str(weights)!r}, '--out', {str(tmp_path / 'e.csv')!r}])\n"
            "print(rc, 'open3d' in sys.modules, any(m.startswith('massviz.measure3d') for m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT,
                         env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin", "HOME": str(tmp_path)})
    assert out.stdout.strip().splitlines()[-1:] == ["0 False False"], out.stderr
    assert (tmp_path / "e.csv").read_text().count("\n") == 2
