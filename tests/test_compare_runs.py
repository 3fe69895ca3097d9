"""``massviz compare`` on datasets: DATASET --a/--b from the trace cache and two ``--rrd-dir`` run folders give the
same table, whose deltas are those of per-recording ``compare``; ``--rrd-dir`` recordings hold both runs (A at the
light recording's paths, B under /b, one timeline) and the catalog's segment table both runs' columns."""
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


def test_two_run_folders_give_the_same_table(compared, sample_cache, weights, samples_dir, tmp_path, capsys):
    for k in (5, 3):
        assert main(["log", str(samples_dir), "--detector", "depth", "--weights", str(weights), "--cache",
                     str(sample_cache), "--k", str(k), "--rrd-dir", str(tmp_path / f"k{k}"), "--quiet"]) == 0
    assert main(["compare", str(tmp_path / "k5"), str(tmp_path / "k3"), "--out", str(tmp_path / "t.parquet")]) == 0
    printed = capsys.readouterr().out
    assert "A: k5\nB: k3\n" in printed and "score per class" in printed
    folders = pd.read_parquet(tmp_path / "t.parquet").set_index("id")
    table = pd.read_csv(compared / "table.csv", dtype={"id": str}).set_index("id")
    assert list(folders.index) == list(table.index)
    for col in ("delta_estimate_g", "delta_rel_error", "n_patches_changed"):
        assert folders[col].to_numpy() == pytest.approx(table[col].to_numpy(), abs=1e-6), col
    assert list(folders["patches_dropped"]) == list(table["patches_dropped"])
    # --rrd-dir needs traces
    assert main(["compare", str(tmp_path / "k5"), str(tmp_path / "k3"), "--rrd-dir", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--rrd-dir needs the runs' traces" in err[0] and not (tmp_path / "x").exists()


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
