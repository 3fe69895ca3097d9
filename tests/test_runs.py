"""Two runs of the samples side by side (``massviz.evaluation.runs``): the table agrees with the per-recording
``compare``, patch changes are identified by frame and box, the scores of A, B and the pairwise best; a run
folder's recording sources are found where that is unambiguous."""
from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from massviz.errors import MassvizError
from massviz.evaluation.compare import compare_traces
from massviz.evaluation.runs import (
    compare_runs,
    filter_comparison,
    parse_settings,
    patch_changes,
    run_from_cache,
    run_from_traces,
    run_scores,
    write_table,
)


@pytest.fixture(scope="module")
def two_runs(sample_cache, weights, samples_dir):
    """The samples at the cache's settings (K 5) and at K 3, both from the trace cache (no detector runs)."""
    from massviz.app import PipelineOptions
    from massviz.io.recording import collect_recordings

    recs = collect_recordings([samples_dir])
    options = PipelineOptions(detector="depth", weights=str(weights), cache=str(sample_cache), threshold=0.4,
                              quiet=True)
    return run_from_cache(recs, options, label="K 5"), run_from_cache(recs, options, k=3, label="K 3")


def test_the_table_has_the_deltas_of_per_recording_compare(two_runs):
    a, b = two_runs
    for t in a.traces + b.traces:  # served by the cache: the detector did not run
        assert any(e.kind == "cache" for e in t.events), t.recording.id
    table = compare_runs(a, b)
    assert list(table.index) == list(table.sort_values("abs_delta_rel_error", ascending=False).index)
    assert set(table.index) == {"box_handover", "cup_handover", "glass_handover"}
    for ta, tb in zip(a.traces, b.traces, strict=False):
        c = compare_traces(ta, tb)
        row = table.loc[ta.recording.id]
        assert row["delta_estimate_g"] == pytest.approx(c.estimate_delta, abs=1e-9)
        assert row["estimate_g_a"] == pytest.approx(ta.estimate) and row["estimate_g_b"] == pytest.approx(tb.estimate)
        gt = ta.ground_truth_mass
        assert row["delta_rel_error"] == pytest.approx((abs(tb.estimate - gt) - abs(ta.estimate - gt)) / gt)
        # the ranks compare reports CHANGED are those of the dropped / added / re-ranked patches
        ch = patch_changes(a, b)
        mine = ch[(ch["recording"] == ta.recording.id) & (ch["change"] != "same")]
        ranks = set(mine.loc[mine["rank_a"] >= 0, "rank_a"]) | set(mine.loc[mine["rank_b"] >= 0, "rank_b"])
        assert ranks == {r.rank for r in c.chosen_changes} == {3, 4}
        dropped = table.loc[ta.recording.id, "patches_dropped"].split()
        d = ta.detections
        expect = [f"{int(d.frame[i])}:{','.join(str(int(v)) for v in d.xyxy[i])}" for i in ta.selection[3:]]
        assert dropped == expect and table.loc[ta.recording.id, "n_patches_changed"] == 2
    cup = table.loc["cup_handover"]  # K 3 keeps only the three pitcher patches: far worse
    assert cup["delta_rel_error"] > 3 and cup["n_flagged_a"] == cup["n_flagged_b"] == 3
    assert table.index[0] == "cup_handover"
    assert list(filter_comparison(table, worse_by=1.0).index) == ["cup_handover"]
    assert filter_comparison(table, flag_appeared=True).empty


def test_flags_that_appear_are_listed_and_the_pairwise_best_is_scored(two_runs):
    a, b = two_runs
    # B chooses the cup's two container patches only (the pitcher's excluded): A's three flags go, none appear
    cup = next(t for t in a.traces if t.recording.id == "cup_handover")
    pitcher = [int(p.detection) for p in cup.flags.flagged]
    b2 = run_from_traces([t if t is not cup else cup.reselect(exclude=pitcher) for t in a.traces], "no pitcher")
    table = compare_runs(a, b2)
    row = table.loc["cup_handover"]
    assert row["n_flags_gone"] == 3 and row["n_flags_appeared"] == 0 and "ground truth" in row["cues_gone"]
    assert row["delta_rel_error"] < -1 and row["n_patches_changed"] >= 3
    back = compare_runs(b2, a).loc["cup_handover"]
    assert back["n_flags_appeared"] == 3 and back["flags_appeared"] == row["flags_gone"]
    assert list(filter_comparison(compare_runs(b2, a), flag_appeared=True).index) == ["cup_handover"]
    scores = run_scores(table)
    assert list(scores.index) == ["box", "cup", "glass", "all"]
    s = table["score_a"], table["score_b"]
    assert scores.loc["all", "best %"] == pytest.approx(100 * np.maximum(*s).mean())
    assert scores.loc["all", "score_a %"] == pytest.approx(100 * s[0].mean())
    assert scores.loc["cup", "best %"] == pytest.approx(100 * row["score_b"])
    assert scores.loc["cup", "best %"] > scores.loc["cup", "score_a %"]


def test_settings_text_and_table_files(tmp_path, two_runs):
    assert parse_settings("detector=depth, threshold=0.3,K=3") == {"detector": "depth", "threshold": 0.3, "k": 3}
    for bad in ("threshold", "colour=red", "k=three"):
        with pytest.raises(MassvizError, match="NAME=VALUE|integer"):
            parse_settings(bad)
    table = compare_runs(*two_runs)
    back = pd.read_csv(write_table(table, tmp_path / "t.csv"))
    assert list(back["id"]) == list(table["id"])
    assert np.allclose(back["delta_estimate_g"], table["delta_estimate_g"])
    pq = pd.read_parquet(write_table(table, tmp_path / "t.parquet"))
    assert list(pq.columns) == list(table.columns)
    with pytest.raises(MassvizError, match=".csv or .parquet"):
        write_table(table, tmp_path / "t.txt")
    assert not (tmp_path / "t.txt").exists()


def test_a_run_from_the_cache_indexes_equals_the_run_from_full_traces(two_runs, sample_cache, weights, samples_dir):
    from massviz.evaluation.runs import run_from_indexes
    from massviz.evaluation.tuning import index_recordings
    from massviz.io.recording import collect_recordings

    a, b = two_runs
    indexes = index_recordings(collect_recordings([samples_dir]), detector="depth", weights=str(weights),
                               cache=str(sample_cache), threshold=0.4, quiet=True)
    ia, ib = run_from_indexes(indexes, k=5, threshold=0.4), run_from_indexes(indexes, k=3, threshold=0.4)
    for full, light in ((a, ia), (b, ib)):
        for tf, tl in zip(full.traces, light.traces, strict=False):
            assert list(tf.selection) == list(tl.selection) and tf.estimate == tl.estimate
            assert [(p.detection, p.flagged, p.ground_truth) for p in tf.flags.patches] == \
                [(p.detection, p.flagged, p.ground_truth) for p in tl.flags.patches]
    pd.testing.assert_frame_equal(compare_runs(a, b), compare_runs(ia, ib))
    with pytest.raises(MassvizError, match="below the score cut 0.4 of the cached trace"):
        run_from_indexes(indexes, k=5, threshold=0.3)


def test_a_run_folders_source_is_found_where_it_is_unambiguous(tmp_path, monkeypatch):
    """``locate_source``: absolute; relative from the current directory; else from the folder or a folder above it,
    every distinct place (two: ambiguous, for the caller to refuse)."""
    from massviz.io.run_folder import locate_source

    folder = tmp_path / "work" / "runs" / "k5"
    folder.mkdir(parents=True)
    (tmp_path / "work" / "recs" / "cup").mkdir(parents=True)
    (tmp_path / "elsewhere").mkdir()
    monkeypatch.chdir(tmp_path / "elsewhere")
    found = tmp_path.resolve() / "work" / "recs" / "cup"
    assert locate_source(str(found), folder) == [found]
    assert locate_source(str(tmp_path / "gone"), folder) == []
    assert locate_source("recs/cup", folder) == [found]  # from work/, the folder's grandparent
    assert locate_source("cup", folder) == []
    (tmp_path / "recs" / "cup").mkdir(parents=True)
    assert locate_source("recs/cup", folder) == [found, tmp_path.resolve() / "recs" / "cup"]
    monkeypatch.chdir(tmp_path / "work")
    assert locate_source("recs/cup", folder) == [found]  # the current directory first
