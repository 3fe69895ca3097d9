"""Dataset scale in the views: the failure panel over selection indexes reads the full trace of the
recording on screen only, and shows what it shows over full traces.

The dataset: the bundled samples from the session's trace cache (``sample_cache``), as full traces
(``sample_traces``) and as selection indexes (``massviz.evaluation.tuning.index_recordings``)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from massviz.evaluation.failures import rank_by_error

pytest.importorskip("ipywidgets")


@pytest.fixture(scope="module")
def indexes(sample_cache, weights, samples_dir):
    from massviz.evaluation.tuning import index_recordings
    from massviz.io.recording import collect_recordings

    out = index_recordings(collect_recordings([samples_dir]), detector="depth", weights=str(weights),
                           cache=str(sample_cache), threshold=0.4, quiet=True)
    assert [type(i).__name__ for i in out] == ["TraceIndex"] * 3
    return out


@pytest.fixture
def loads(monkeypatch):
    """Every full trace file read (``massviz.io.cache.load_trace``, what ``TraceIndex.full_trace`` calls), in order."""
    import massviz.io.cache as cache

    seen: list[Path] = []
    real = cache.load_trace

    def counting(path, *args, **kwargs):
        seen.append(Path(path))
        return real(path, *args, **kwargs)

    monkeypatch.setattr(cache, "load_trace", counting)
    return seen


def _shown(panel) -> list:
    """What the failure panel shows: the ranking, the estimate, the score, and per row its text, image and toggle."""
    rows = [(r.children[0].value, r.children[0].layout.border, r.children[1].children[0].value,
             r.children[1].children[1].value) for r in panel.rows.children]
    return [panel.ranking_html.value, panel.estimate.value, panel.score.value, panel.recording.options,
            panel.recording.value, rows]


def test_the_failure_panel_on_indexes_reads_only_the_shown_recordings_full_trace(indexes, loads):
    from massviz.io.identity import capture_reads
    from massviz.views.widgets import FailurePanel, Tuner

    tuner = Tuner(indexes, k=5, stride=6)
    assert loads == []
    with capture_reads() as reads:
        panel = FailurePanel(tuner)
    shown = indexes[panel.i].trace_path
    assert loads == [shown]  # exactly one full trace read, once: the recording on screen
    npz = {f for f in reads["files"] if f.endswith(".npz")}
    assert npz == {str(shown)}, npz
    assert not [f for f in reads["files"] if "/rgb/" in f or "/depth/" in f]  # no frame of any recording
    assert len(panel.rows.children) == 5

    panel.set(k=3)  # a slider move: the shown recording's trace is kept
    assert loads == [shown] and len(panel.rows.children) == 3
    other = next(j for j in range(len(indexes)) if j != panel.i)
    panel.recording.value = other  # another recording on screen: its full trace, and only it
    assert loads == [shown, indexes[other].trace_path]
    det = int(panel.table()["detection"].iloc[0])
    panel.set_mode(det, "exclude track")
    assert loads == [shown, indexes[other].trace_path]


def test_the_failure_panel_on_indexes_shows_what_it_shows_on_full_traces(indexes, sample_traces):
    from massviz.views.widgets import FailurePanel, Tuner

    assert [i.recording.id for i in indexes] == [t.recording.id for t in sample_traces]
    full, light = Tuner(sample_traces, k=5, stride=6), Tuner(indexes, k=5, stride=6)
    a, b = FailurePanel(full), FailurePanel(light)
    assert _shown(a) == _shown(b)
    cup = [t.recording.id for t in sample_traces].index("cup_handover")
    for panel in (a, b):
        panel.recording.value = cup
    assert _shown(a) == _shown(b)
    pitcher = a.table().query("gt_overlaps == 'pitcher'")
    assert len(pitcher)  # the failure the panel is for (tests/test_widgets.py)
    det = int(pitcher["detection"].iloc[0])
    for panel in (a, b):
        panel.set_mode(det, "exclude track")
    assert _shown(a) == _shown(b) and "excluded by you" in str(_shown(b)[-1])
    for change in ({"k": 2}, {"threshold": 0.7}, {"stride": 1, "k": 9}):
        a.set(**change)
        b.set(**change)
        assert _shown(a) == _shown(b), change
        # the ranking from the estimates of an update is the ranking of every re-tuned trace (what it was before)
        want = rank_by_error(full.current)
        assert light.ranking().equals(want) and full.ranking().equals(want)
        assert want["estimate_g"].notna().any()
    assert light.exclusions() == full.exclusions() and light.exclusions()
    assert len(light._full) <= Tuner.KEEP_FULL


def test_the_chosen_counts_are_the_selections(sample_traces):
    from massviz.evaluation.sweep import SweepTable
    from massviz.evaluation.tuning import original_selection, retune, retuned_selection

    table = SweepTable(sample_traces)
    seen = set()
    for threshold in (0.4, 0.6, 0.9):
        for k in (1, 5, 40):
            for stride in (1, 4):
                got = table.chosen(threshold, k, stride)
                for t, n in zip(sample_traces, got, strict=False):
                    sel = retune(t, k=k, threshold=threshold, stride=stride)
                    assert n == len(sel.selection)
                    assert np.array_equal(retuned_selection(t, k=k, threshold=threshold, stride=stride),
                                          original_selection(t, sel, stride))
                    seen.add(int(n))
    assert len(seen) > 2  # not all zeros nor all K


def test_the_dataset_tables_numbers_are_the_vectorised_sweeps(indexes, sample_traces):
    """The dataset browser's per-recording columns (``tables_from_traces``: the trace's own selection, made by the
    pipeline) are the numbers the sweep, the tuner and the panels compute from the indexes, to the bit."""
    import math

    from massviz.evaluation.browser import tables_from_traces
    from massviz.evaluation.sweep import SweepTable

    recordings, _ = tables_from_traces(sample_traces)
    assert {(t.threshold, t.k, t.stride) for t in sample_traces} == {(0.4, 5, 1)}
    table = SweepTable(indexes)
    estimates, chosen = table.estimates(0.4, 5), table.chosen(0.4, 5)
    for t, est, n in zip(sample_traces, estimates, chosen, strict=False):
        row = recordings.loc[t.recording.id]
        assert row["estimate_g"] == est and row["k"] == n == len(t.selection) and est > 0
        true = t.ground_truth_mass
        assert row["rel_error"] == abs(est - true) / true and row["score"] == math.exp(-abs(est - true) / true)


def test_the_ranking_table_shows_the_worst_recordings_only(indexes, monkeypatch):
    """At 1,140 recordings the whole ranking is ~180 kB of HTML sent at every slider move: the worst rows only."""
    from massviz.views.widgets import FailurePanel, Tuner

    tuner = Tuner(indexes, k=5, stride=6)
    whole = FailurePanel(tuner).ranking_html.value
    assert whole.count("</tr>") == 1 + 3 and "more" not in whole  # header + every recording
    monkeypatch.setattr(FailurePanel, "RANKING_ROWS", 2)
    panel = FailurePanel(tuner)
    worst = tuner.ranking()["recording"].tolist()
    html = panel.ranking_html.value
    assert html.count("</tr>") == 1 + 2 and "… and 1 more" in html
    assert worst[0] in html and worst[1] in html and worst[2] not in html
    assert [label.split(". ", 1)[1] for label, _ in panel.recording.options] == worst
