"""``massviz compare`` on datasets: DATASET --a/--b from the trace cache and two ``--rrd-dir`` run folders give the
same table, whose deltas are those of per-recording ``compare``; ``--rrd-dir`` recordings hold both runs (A at the
light recording's paths, B under /b, one timeline) and the catalog's segment table both runs' columns; two run
folders write the same recordings as the settings they record, or one line when a folder's source, settings,
weights or estimate cannot be reproduced."""
from __future__ import annotations

import json

import pandas as pd
import pytest

from massviz.cli import main

pytestmark = pytest.mark.slow  # the samples' pipeline from the cache, a catalog server, rrd files

SAMPLES = ("box_handover", "cup_handover", "glass_handover")


@pytest.fixture(scope="module")
def compared(sample_cache, weights, samples_dir, tmp_path_factory):
    """``massviz compare data_samples --a k=5 --b k=3 --out --rrd-dir`` (the samples' cache: no detector runs)."""
    out = tmp_path_factory.mktemp("runs")
    code = main(["compare", str(samples_dir), "--detector", "depth", "--weights", str(weights), "--cache",
                 str(sample_cache), "--a", "k=5", "--b", "k=3", "--out", str(out / "table.csv"), "--rrd-dir",
                 str(out / "both"), "--quiet"])
    assert code == 0
    return out


def test_dataset_table_has_the_deltas_of_per_recording_compare(compared, sample_cache, weights, samples_dir, capsys):
    table = pd.read_csv(compared / "table.csv", dtype={"id": str}).set_index("id")
    assert sorted(table.index) == list(SAMPLES)
    assert table.index[0] == "cup_handover"  # the largest change of the error first
    for rid in SAMPLES:
        js = compared / f"{rid}.json"
        assert main(["compare", str(samples_dir / rid), "--detector", "depth", "--weights", str(weights), "--cache",
                     str(sample_cache), "--quiet", "--b-k", "3", "--json", str(js)]) == 0
        one = json.loads(js.read_text())
        row = table.loc[rid]
        assert row["delta_estimate_g"] == pytest.approx(one["estimate_delta_g"], abs=1e-6)
        assert [row["estimate_g_a"], row["estimate_g_b"]] == pytest.approx(one["estimate"], abs=1e-6)
        # compare's CHANGED ranks (3 and 4: K 3 drops them) are the dropped patches
        assert one["chosen_changed"] == [3, 4] and len(row["patches_dropped"].split()) == 2
        assert row["n_patches_changed"] == 2 and pd.isna(row["patches_added"])
    capsys.readouterr()


@pytest.fixture(scope="module")
def folders(sample_cache, weights, samples_dir, tmp_path_factory):
    """``massviz log data_samples --k 5 --rrd-dir k5/`` and ``--k 3 --rrd-dir k3/`` (the samples' cache)."""
    out = tmp_path_factory.mktemp("folders")
    for k in (5, 3):
        assert main(["log", str(samples_dir), "--detector", "depth", "--weights", str(weights), "--cache",
                     str(sample_cache), "--k", str(k), "--rrd-dir", str(out / f"k{k}"), "--quiet"]) == 0
    return out


def _compare_folders(a, b, out, sample_cache, weights, *extra):
    return main(["compare", str(a), str(b), "--weights", str(weights), "--cache", str(sample_cache), "--rrd-dir",
                 str(out), "--quiet", *extra])


@pytest.fixture(scope="module")
def folders_compared(folders, sample_cache, weights):
    """``massviz compare k5/ k3/ --rrd-dir both/``: the two-run recordings from two run folders."""
    assert _compare_folders(folders / "k5", folders / "k3", folders / "both", sample_cache, weights) == 0
    return folders / "both"


def test_two_run_folders_give_the_same_table(compared, folders, tmp_path, capsys):
    capsys.readouterr()
    assert main(["compare", str(folders / "k5"), str(folders / "k3"), "--out", str(tmp_path / "t.parquet")]) == 0
    printed = capsys.readouterr().out
    assert "A: k5\nB: k3\n" in printed and "score per class" in printed
    folder_table = pd.read_parquet(tmp_path / "t.parquet").set_index("id")
    table = pd.read_csv(compared / "table.csv", dtype={"id": str}).set_index("id")
    assert list(folder_table.index) == list(table.index)
    for col in ("delta_estimate_g", "delta_rel_error", "n_patches_changed"):
        assert folder_table[col].to_numpy() == pytest.approx(table[col].to_numpy(), abs=1e-6), col
    assert list(folder_table["patches_dropped"]) == list(table["patches_dropped"])


def _properties(rrd) -> dict:
    from rrd_reader import rrd_rows

    (row,) = rrd_rows(rrd, "/__properties/massviz")
    return {k: v for k, v in row.items() if k not in ("time", "row_id")}


def test_two_run_folders_write_the_recordings_of_dataset_settings(compared, folders_compared):
    """``compare k5/ k3/ --rrd-dir`` writes what ``compare DATASET --a k=5 --b k=3 --rrd-dir`` does: the same
    comparison.csv, and per recording the same entities and properties (the labels aside: the folders' names)."""
    from rrd_reader import rrd_entities

    settings = compared / "both"
    assert sorted(p.name for p in folders_compared.iterdir()) == sorted(p.name for p in settings.iterdir())
    assert (folders_compared / "comparison.csv").read_text() == (settings / "comparison.csv").read_text()
    for rid in SAMPLES:
        got, want = _properties(folders_compared / f"{rid}.rrd"), _properties(settings / f"{rid}.rrd")
        assert (got.pop("label_a"), got.pop("label_b")) == (["k5"], ["k3"])
        assert (want.pop("label_a"), want.pop("label_b")) == (["k=5"], ["k=3"])
        assert got == want and got["k_a"] == [5] and got["k_b"] == [3], rid
        entities = rrd_entities(folders_compared / f"{rid}.rrd")
        assert entities == rrd_entities(settings / f"{rid}.rrd"), rid
        assert {"/camera/detections", "/b/camera/detections", "/compare"} <= entities


def _edited(folder, to, rid: str | None, column: str, value):
    """A copy of run folder ``folder`` at ``to`` whose index.csv has ``value`` in row ``rid`` (None: every row,
    ``value`` a function of the column's values) of ``column``."""
    import shutil

    shutil.copytree(folder, to)
    index = pd.read_csv(to / "index.csv", dtype=str, keep_default_na=False)
    if rid is None:
        index[column] = value(index[column])
    else:
        index.loc[index["id"] == rid, column] = value
    index.to_csv(to / "index.csv", index=False)
    return to


def test_two_run_folders_find_a_source_relative_to_a_folder_above(folders, folders_compared, sample_cache, weights,
                                                                   tmp_path, monkeypatch):
    """A source written relative to where ``log`` ran (here: the folder's parent) is found from elsewhere."""
    import os

    moved = tmp_path / "runs" / "k3"
    _edited(folders / "k3", moved, None, "source", lambda s: [os.path.relpath(p, moved.parent) for p in s])
    assert not any(os.path.isabs(p) for p in pd.read_csv(moved / "index.csv")["source"])
    elsewhere = tmp_path / "elsewhere" / "deeper"  # deeper than the folder's parent: the sources are not found here
    elsewhere.mkdir(parents=True)
    monkeypatch.chdir(elsewhere)
    assert _compare_folders(folders / "k5", moved, tmp_path / "out", sample_cache, weights) == 0
    assert (tmp_path / "out" / "comparison.csv").read_text() == (folders_compared / "comparison.csv").read_text()


def test_two_run_folders_bad_inputs_are_one_line(folders, sample_cache, weights, tmp_path, capsys):
    k5, k3 = folders / "k5", folders / "k3"
    (weights_id,) = set(pd.read_csv(k3 / "index.csv", dtype=str)["weights_id"])
    lost = _edited(k3, tmp_path / "lost", "glass_handover", "source", "nowhere/glass_handover")
    other = _edited(k3, tmp_path / "other_weights", "box_handover", "weights_id", "000000000123")
    estimate = _edited(k3, tmp_path / "estimate", "cup_handover", "estimate_g", "12.5")
    detector = _edited(k3, tmp_path / "detector", "box_handover", "detector", "yolo")
    precision = _edited(k3, tmp_path / "precision", "box_handover", "detector", "depth bf16")
    twice = _edited(k3, tmp_path / "twice", None, "id", lambda ids: ["box_handover"] * len(ids))
    k_half = _edited(k3, tmp_path / "k_half", "box_handover", "k", "2.5")
    threshold = _edited(k3, tmp_path / "threshold", "box_handover", "threshold", "1.2")
    out = tmp_path / "out"
    for b, extra, says in (
            (detector, (), [f"{detector / 'index.csv'}:", "'box_handover'", "'yolo'"]),
            (precision, (), [f"{precision / 'index.csv'}:", "'box_handover'", "--precision bf16"]),
            (twice, (), [f"{twice / 'index.csv'}:", "'box_handover' is there twice"]),
            (k_half, (), [f"{k_half / 'index.csv'}:", "'box_handover': column 'k' must be an integer, got 2.5"]),
            (threshold, (), [f"{threshold / 'index.csv'}:", "column 'threshold' must be in [0, 1), got 1.2"]),
            (lost, (), [f"{lost / 'index.csv'}:", "'glass_handover'", "'nowhere/glass_handover'", "not found"]),
            (other, (), [f"{other}:", "'box_handover'", "'000000000123'", repr(weights_id)]),
            (estimate, (), [f"{estimate / 'index.csv'}:", "'cup_handover'", "12.5 g", "does not reproduce"]),
            (k3, ("--b-k", "2"), ["--b-k: two run folders record their settings"])):
        capsys.readouterr()
        assert _compare_folders(k5, b, out, sample_cache, weights, "--out", str(tmp_path / "t.csv"), *extra) == 2, b
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and all(s in err[0] for s in says), err
        assert not out.exists() and not (tmp_path / "t.csv").exists()


def test_catalog_segment_table_holds_both_runs(compared):
    from rerun.chunk import RrdReader

    from massviz.views.rerun_serve import catalog

    table = pd.read_csv(compared / "table.csv", dtype={"id": str}).set_index("id")
    both = compared / "both"
    assert sorted(p.name for p in both.glob("*.rrd")) == [f"{r}.rrd" for r in SAMPLES]
    cols = ("estimate_g_a", "estimate_g_b", "delta_estimate_g", "rel_error_a", "rel_error_b", "delta_rel_error",
            "k_a", "k_b", "n_patches_changed")
    with catalog(both) as cat:
        got = cat.sql("SELECT rerun_segment_id AS id, " + ", ".join(f'"property:massviz:{c}"[1] AS {c}'
                                                                    for c in cols) + " FROM segments")
    got = got.set_index("id").sort_index()
    assert list(got.index) == list(SAMPLES)
    for c in cols:
        digits = 2 if "_g" in c else 4
        assert got[c].astype(float).to_numpy() == pytest.approx(table.loc[got.index, c].round(digits), abs=1e-9), c
    assert list(got["k_a"]) == [5, 5, 5] and list(got["k_b"]) == [3, 3, 3]
    reader = RrdReader(both / "cup_handover.rrd")  # both runs in one recording
    (entry,) = reader.recordings()
    assert entry.recording_id == "cup_handover"
    contents = {col.entity_path for col in reader.stream(store=entry).collect().schema().component_columns()}
    assert {"/camera/detections", "/patches/4", "/b/camera/detections", "/b/patches/2", "/compare",
            "/predictions/running_estimate", "/b/predictions/running_estimate"} <= set(contents)
    assert "/b/patches/3" not in contents


def test_dataset_compare_errors_are_one_line(samples_dir, tmp_path, capsys):
    for args, says in ((["--a", "k=5", "--b", "colour=red"], "NAME=VALUE"),
                       (["--a", "k=5", "--b", "k=3", "--rrd", str(tmp_path / "x.rrd")], "--rrd compares one"),
                       (["--a", "k=5", "--b", "k=3", "--out", str(tmp_path / "t.txt")], ".csv or .parquet"),
                       (["--out", str(tmp_path / "t.csv")], "--out is for two runs")):
        extra = ["--b-k", "3"] if "--a" not in args else []
        assert main(["compare", str(samples_dir / "cup_handover"), *args, *extra]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and says in err[0], err
    assert not list(tmp_path.iterdir())
