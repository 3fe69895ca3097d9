"""Dataset scale: the selection index, recognition from file identities, the vectorised sweep, and the
warm commands (no frame file opened, no torch imported).

The dataset: the three samples and CCM recording 618 (../shared/ccm_real/618, as tests/test_dataset_catalog.py
builds it), processed once with the depth detector by the CLI (the slow path, which fills the cache, the indexes
and the remembered identities); every other test reads what that run left."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest

from massviz.core.selection import NearestOrder, estimate_mass
from massviz.evaluation.sweep import SweepTable, sweep
from massviz.evaluation.tuning import retune
from support import samples_and_618

ROOT = Path(__file__).resolve().parents[1]
WEIGHTS = "weights/corsmal_visual/Encoder_pool_aug_158.torch"
#: the frontal camera of CCM recording 618 (as tests/test_dataset_catalog.py)
INTR_618 = {"fx": 923.3, "fy": 923.3, "cx": 640.0, "cy": 360.0, "width": 1280, "height": 720}
THRESHOLDS = [0.4, 0.5, 0.6, 0.7, 0.8, 0.9]
KS = [1, 2, 3, 5, 8, 10, 12]
STRIDES = [1, 2, 3]


# -- the vectorised sweep against NearestOrder, on random detections ------------------------------------------------
def _random_traces(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        m = int(rng.integers(0, 40))
        d = np.round(rng.uniform(300, 2000, m), 0)
        d[rng.random(m) < 0.1] = np.nan  # masks without depth: never selected
        d[rng.random(m) < 0.2] = 800.0  # ties: the earliest first
        score = np.where(rng.random(m) < 0.3, np.float32(0.6), rng.random(m)).astype(np.float32)  # == threshold
        dets = types.SimpleNamespace(d=d, score=score, pred=rng.uniform(1, 300, m), frame=rng.integers(0, 30, m))
        out.append(types.SimpleNamespace(detections=dets, excluded=np.flatnonzero(rng.random(m) < 0.1),
                                         detect_threshold=0.0))
    return out


def _reference(trace, threshold, k, stride):
    """The estimate by the one definition: NearestOrder over the frames % stride == 0 (as tuning.subsample)."""
    dets = trace.detections
    keep = np.flatnonzero(dets.frame % stride == 0)
    renumber = np.full(len(dets.d), -1)
    renumber[keep] = np.arange(len(keep))
    ex = renumber[trace.excluded]
    sel = NearestOrder(dets.d[keep], dets.score[keep], ex[ex >= 0]).select(k, threshold)
    return estimate_mass(dets.pred[keep], sel)


def test_vectorised_sweep_is_identical_to_nearest_order_on_a_grid():
    traces = _random_traces(200)
    table = SweepTable(traces)
    for threshold in [0.0, 0.3, 0.6, float(np.float32(0.6)), 0.9]:
        for k in [1, 2, 7, 8, 9, 15, 40]:  # 8+ values: np.mean's pairwise summation
            for stride in STRIDES:
                got = table.estimates(threshold, k, stride)
                want = np.array([_reference(t, threshold, k, stride) for t in traces])
                assert np.array_equal(got, want), (threshold, k, stride)  # bit for bit, not close


def test_vectorised_sweep_refuses_a_threshold_below_the_traces():
    traces = _random_traces(3)
    for t in traces:
        t.detect_threshold = 0.5
    with pytest.raises(Exception, match="below the score cut 0.5 of the traces"):
        SweepTable(traces).estimates(0.4, 3)


# -- the dataset, processed once by the CLI -------------------------------------------------------------------------
@pytest.fixture(scope="module")
def env(shared_dir):
    return {**os.environ, "MASSVIZ_WEIGHTS": str(shared_dir / WEIGHTS), "PYTHONPATH": str(ROOT)}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory, shared_dir, samples_dir) -> Path:
    """The samples and CCM 618 as one folder of massviz recordings (frames linked, not copied)."""
    root = tmp_path_factory.mktemp("scale") / "ds"
    return samples_and_618(root, shared_dir, samples_dir, INTR_618)


def massviz(*args, env, check=True, timeout=900):
    run = subprocess.run([sys.executable, "-m", "massviz", *map(str, args)], capture_output=True, text=True,
                         env=env, timeout=timeout, cwd=ROOT)
    if check:
        assert run.returncode == 0, run.stderr[-3000:]
    return run


SWEEP = ("--threshold", "0.4:0.9:0.1", "--k", "1:10", "--detector", "depth", "--quiet")


@pytest.fixture(scope="module")
def cold(dataset, tmp_path_factory, env):
    """The first (cold) sweep: every recording opened and processed; (cache, its CSV table)."""
    cache = tmp_path_factory.mktemp("scale_cache")
    out = cache.parent / "cold.csv"
    massviz("sweep", dataset, *SWEEP, "--cache", cache, "--csv", out, env=env)
    return cache, out


def _pipeline_and_recordings(dataset, cache, env):
    from massviz.app import build_pipeline
    from massviz.io.recording import find_recordings, open_recording

    pipeline = build_pipeline(detector="depth", threshold=0.4, cache=str(cache), quiet=True,
                              weights=env["MASSVIZ_WEIGHTS"])
    return pipeline, [open_recording(p) for p in find_recordings(dataset)]


@pytest.fixture(scope="module")
def loaded(dataset, cold, env):
    """(full traces from the cache, their selection indexes), in the same order."""
    from massviz.commands._warm import cached_indexes

    cache, _ = cold
    pipeline, recordings = _pipeline_and_recordings(dataset, cache, env)
    traces = [pipeline.process(r, progress=False) for r in recordings]
    assert all("cache" in t.timings for t in traces)  # from the cache, made by the cold run
    indexes = cached_indexes(pipeline, recordings, 1, 0.4)
    assert indexes is not None and len(indexes) == 4
    return traces, indexes


def test_index_gives_the_full_traces_estimates_and_scores_on_a_grid(loaded):
    traces, indexes = loaded
    assert {i.trace_path.name[0] for i in indexes} == {"t"}  # the full trace stays where it is, lazily read
    table = SweepTable(indexes)
    estimated = 0
    for threshold in THRESHOLDS:
        for k in KS:
            for stride in STRIDES:
                got = table.estimates(threshold, k, stride)
                want = [retune(t, k=k, threshold=threshold, stride=stride).estimate for t in traces]
                assert got.tolist() == want, (threshold, k, stride)
                estimated += int((got >= 0).sum())
    assert estimated > 0  # the grid is not all "not estimated"
    full, indexed = sweep(traces, THRESHOLDS, KS), sweep(indexes, THRESHOLDS, KS)
    assert full.equals(indexed)
    assert full["score"].max() > 0


def test_an_index_is_kilobytes_and_not_used_for_another_trace_file(dataset, cold):
    from massviz.io.cache import index_path, load_index

    cache, _ = cold
    for trace_file in (Path(cache) / "traces").glob("*/t*.npz"):
        idx = index_path(trace_file)
        assert idx.is_file() and idx.stat().st_size < min(32_000, trace_file.stat().st_size)
        assert load_index(trace_file) is not None
    # a trace file replaced (another model's predictions...): its old index is ignored
    trace_file = next((Path(cache) / "traces").glob("*/t*.npz"))
    copy = trace_file.with_name("t0.99.npz")
    copy.write_bytes(trace_file.read_bytes())
    index_path(trace_file).rename(index_path(copy))
    assert load_index(copy) is None


def test_a_copied_cache_is_indexed_again(dataset, cold, env, tmp_path):
    import shutil

    from massviz.commands._warm import cached_indexes
    from massviz.io.cache import load_index

    copy = tmp_path / "copy"
    shutil.copytree(cold[0], copy)
    trace_files = sorted((copy / "traces").glob("*/t*.npz"))
    assert trace_files and all(load_index(f) is None for f in trace_files)  # another inode: not trusted
    pipeline, recordings = _pipeline_and_recordings(dataset, copy, env)
    indexes = cached_indexes(pipeline, recordings, 1, 0.4)
    assert indexes is not None and {i.trace_path.parent.parent.parent for i in indexes} == {copy}
    assert all(load_index(i.trace_path) is not None for i in indexes)


def test_the_tuner_on_indexes_is_the_tuner_on_full_traces(loaded):
    from massviz.views.widgets import Tuner

    traces, indexes = loaded
    full, light = Tuner(traces, k=5, threshold=0.4), Tuner(indexes, k=5, threshold=0.4)
    assert light._full == {}  # nothing shown yet: no full trace read
    for change in ({}, {"k": 1}, {"k": 10}, {"threshold": 0.7}, {"stride": 2}, {"stride": 3, "k": 4}):
        full.update(**change)
        light.update(**change)
        assert light.estimates() == full.estimates()
        assert light.report.score_pct == full.report.score_pct
        for i in range(len(traces)):
            assert np.array_equal(light.selection(i), full.selection(i))
            assert light.patch_table(i).equals(full.patch_table(i))
            assert light.current[i].flags == full.current[i].flags
    assert 0 < len(light._full) <= Tuner.KEEP_FULL
    cup = [t.recording.id for t in traces].index("cup_handover")
    chosen = int(full.selection(cup)[0])
    for tuner in (full, light):
        tuner.set_mode(cup, chosen, "exclude track")
        tuner.update(k=5)
    assert light.estimates() == full.estimates()
    assert light.estimates()["cup_handover"] != Tuner(indexes, k=5, threshold=0.4).estimates()["cup_handover"]
    assert light.exclusions() == full.exclusions()


def _warm_env(env, dataset, counts: Path):
    """Env for a subprocess that counts every Python 'open' of a file under the dataset (frames, meta...) and
    records whether torch was imported, written to ``counts`` at exit."""
    hook = counts.with_suffix(".py")
    hook.write_text(f"""
import atexit, json, os, sys
_opened = []
_root = {str(Path(dataset).resolve())!r}
_shared = {str(Path(dataset).parent)!r}
def _hook(event, args):
    if event == "open" and isinstance(args[0], (str, bytes, os.PathLike)):
        p = os.path.realpath(os.fsdecode(args[0]))
        if any(part in p for part in ("/rgb/", "/depth/", ".mp4")) or p.startswith(_root):
            _opened.append(p)
sys.addaudithook(_hook)
atexit.register(lambda: open({str(counts)!r}, "w").write(json.dumps(
    {{"opened": _opened, "torch": "torch" in sys.modules}})))
""")
    (counts.parent / "sitecustomize.py").write_text(hook.read_text())
    return {**env, "PYTHONPATH": f"{counts.parent}{os.pathsep}{env['PYTHONPATH']}"}


def test_a_cached_rerun_opens_no_frame_file_and_imports_no_torch(dataset, cold, tmp_path, env):
    cache, cold_csv = cold
    counts = tmp_path / "counts.json"
    warm_env = _warm_env(env, dataset, counts)
    warm_csv = tmp_path / "warm.csv"
    massviz("sweep", dataset, *SWEEP, "--cache", cache, "--csv", warm_csv, "--cached-only", env=warm_env)
    seen = json.loads(counts.read_text())
    assert seen["opened"] == [] and seen["torch"] is False, seen
    assert warm_csv.read_text() == Path(cold_csv).read_text()  # the same table from the indexes

    out = tmp_path / "est.csv"
    run = massviz("estimate", dataset / "cup_handover", "--detector", "depth", "--cache", cache, "--out", out,
                  "--quiet", "--exec-time", "none", env=warm_env)
    seen = json.loads(counts.read_text())
    assert [p for p in seen["opened"] if "/rgb/" in p or "/depth/" in p] == [] and seen["torch"] is False, seen
    assert "cup_handover: 57.4 g" in run.stderr

    # the hook does see frames: a cold estimate (another cache) opens them and imports torch
    massviz("estimate", dataset / "cup_handover", "--detector", "depth", "--cache", tmp_path / "c2", "--out",
            tmp_path / "cold.csv", "--quiet", "--exec-time", "none", env=warm_env)
    seen = json.loads(counts.read_text())
    assert any("/depth/" in p for p in seen["opened"]) and seen["torch"] is True
    assert (tmp_path / "cold.csv").read_bytes() == out.read_bytes()


# -- recognition from file identities -------------------------------------------------------------------------------
def test_a_recording_is_recognised_only_while_its_files_are_unchanged(tmp_path, samples_dir):
    import shutil

    from massviz.io.identity import LocatedRecording, locate, open_remembered
    from massviz.io.recording import Recording

    rec = tmp_path / "rec"
    shutil.copytree(samples_dir / "cup_handover", rec)
    cache = tmp_path / "cache"
    assert locate(rec, cache) is None
    first = open_remembered(rec, cache)
    assert isinstance(first, Recording)
    again = locate(rec, cache)
    assert isinstance(again, LocatedRecording)
    assert (again.id, again.config_id, again.num_frames, again.fingerprint()) == (
        first.id, first.config_id, first.num_frames, first.fingerprint())
    assert again.info() == first.info()

    depth = sorted((rec / "depth").glob("*.png"))
    data = depth[3].read_bytes()
    stat = depth[3].stat()
    depth[3].write_bytes(data)  # same bytes, same size, mtime set back: ctime still moved
    os.utime(depth[3], ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert locate(rec, cache) is None
    open_remembered(rec, cache)
    assert locate(rec, cache) is not None

    meta = json.loads((rec / "meta.json").read_text())  # meta.json is read when opened: a dependency
    meta["container"]["mass_g"] = 1.0
    (rec / "meta.json").write_text(json.dumps(meta))
    assert locate(rec, cache) is None
    assert open_remembered(rec, cache).info().ground_truth.mass_g == 1.0
    assert locate(rec, cache).info().ground_truth.mass_g == 1.0

    shutil.copyfile(depth[0], rec / "depth" / "999999.png")  # a new frame: its folder changed
    assert locate(rec, cache) is None


def test_a_garbage_memo_is_ignored(tmp_path, samples_dir):
    from massviz.io.identity import _memo_path, locate, open_remembered

    cache = tmp_path / "cache"
    rec = samples_dir / "box_handover"
    open_remembered(rec, cache)
    memo = _memo_path(cache, rec, False)
    for garbage in ("", "[1, 2]", '{"format": 1, "path": "x"}', "{" * 10_000, json.dumps(
            {**json.loads(memo.read_text()), "depends": {"files": {"/nonexistent": [1]}, "dirs": {}}})):
        memo.write_text(garbage)
        assert locate(rec, cache) is None


def test_the_panel_keeps_its_tiles_across_slider_moves(loaded):
    pytest.importorskip("ipywidgets")
    from massviz.views.widgets import Tuner, TuningPanel

    _, indexes = loaded
    panel = TuningPanel(Tuner(indexes, k=5, threshold=0.4))
    before = panel.shown_tiles()
    panel.set(k=6)
    after = panel.shown_tiles()
    assert len(before) == 5 and len(after) == 6 and after[:5] == before  # the same widgets, new values
    fresh = TuningPanel(Tuner(indexes, k=6, threshold=0.4))  # what a panel made at K=6 shows
    show = lambda p: [(t.children[0].value, t.children[1].value, t.layout.border) for t in p.shown_tiles()]  # noqa: E731
    assert show(panel) == show(fresh)
    panel.set(k=2, threshold=0.7)
    fresh = TuningPanel(Tuner(indexes, k=2, threshold=0.7))
    assert show(panel) == show(fresh) and len(panel.shown_tiles()) <= 2


def test_a_damaged_or_vanished_cached_trace_is_computed_again_or_one_line(samples_dir, weights, tmp_path, capsys,
                                                                        monkeypatch):
    """A damaged trace file (its index beside it no longer matches it) is dropped and computed again in the same run;
    one removed after the warm path found it (another process cleaning the cache) fails that recording with one line
    saying to run again, and the next run computes it: the same CSV every time."""
    from massviz.cli import main
    from massviz.io.cache import TraceCache

    args = ["estimate", str(samples_dir / "box_handover"), "--detector", "depth", "--weights", str(weights),
            "--cache", str(tmp_path / "cache"), "--stride", "12", "--quiet", "--exec-time", "none", "--out"]
    assert main([*args, str(tmp_path / "first.csv")]) == 0
    [npz] = (tmp_path / "cache").rglob("*.npz")
    npz.write_bytes(npz.read_bytes()[:200])
    assert main([*args, str(tmp_path / "damaged.csv")]) == 0, capsys.readouterr().err
    assert (tmp_path / "damaged.csv").read_bytes() == (tmp_path / "first.csv").read_bytes()

    load = TraceCache.load

    def vanishing(self, recording, *a):  # the entry goes after the warm path saw its index
        for p in Path(self.root).rglob("*.npz"):
            p.unlink()
        return load(self, recording, *a)

    monkeypatch.setattr(TraceCache, "load", vanishing)
    capsys.readouterr()
    assert main([*args, str(tmp_path / "vanished.csv")]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "box_handover" in err[0] and "run the command again" in err[0], err
    assert not (tmp_path / "vanished.csv").exists()
    monkeypatch.setattr(TraceCache, "load", load)
    assert main([*args, str(tmp_path / "again.csv")]) == 0, capsys.readouterr().err
    assert (tmp_path / "again.csv").read_bytes() == (tmp_path / "first.csv").read_bytes()
