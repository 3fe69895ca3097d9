"""Two runs' estimates closer than the stated tolerance are a tie: neither run is declared better by rounding noise."""
from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from massviz.evaluation.runs import TIE_G, outcomes, run_scores
from support import run_massviz


def comparison(est_a, est_b, gt=10.0, in_runs="both") -> pd.DataFrame:
    """A compare_runs-like table, one recording per pair of estimates (-1 or NaN: not estimated)."""
    ea, eb = np.asarray(est_a, float), np.asarray(est_b, float)

    def err(e):
        return np.where(e >= 0, np.abs(e - gt) / gt, np.nan)

    def score(e):
        return np.where(e >= 0, np.exp(-np.abs(e - gt) / gt), 0.0)

    n = len(ea)
    return pd.DataFrame({"id": [f"r{i}" for i in range(n)], "container_class": ["cup"] * n, "gt_mass_g": [gt] * n,
                         "in_runs": [in_runs] * n, "estimate_g_a": ea, "estimate_g_b": eb,
                         "rel_error_a": err(ea), "rel_error_b": err(eb), "score_a": score(ea), "score_b": score(eb)})


def test_differences_below_the_tolerance_are_ties_whatever_the_scores_last_digits():
    t = comparison([57.388479, 20.260042, 12.0, 12.0, -1, -1, 12.0],
                   [57.388479 + 6e-6, 20.260042 - 1.3e-5, 12.0 + TIE_G * 1.5, 9.0, 12.0, -1, 12.0 + TIE_G * 0.9])
    assert list(outcomes(t)) == ["tie", "tie", "a better", "b better", "b better", "tie", "tie"]
    scores = run_scores(t)
    assert scores.loc["all", ["b better", "a better", "ties"]].tolist() == [2, 1, 4]


def test_recordings_without_ground_truth_or_in_one_run_are_not_counted():
    t = pd.concat([comparison([10.0], [11.0], gt=np.nan), comparison([10.0], [11.0], in_runs="A")])
    assert list(outcomes(t)) == ["", ""]


def test_compare_prints_numbers_as_the_estimate_is_and_the_tolerance():
    from massviz.commands._compare_runs import _fixed

    assert _fixed(4, sign=True)(-5.172e-08) == "0.0000" and _fixed(1, sign=True)(9.5e-7) == "0.0"
    assert _fixed(1, sign=True)(32.73) == "+32.7" and _fixed(4)(float("nan")) == "-"


@pytest.mark.slow  # a massviz subprocess over the samples
def test_the_same_patches_in_both_runs_are_ties_on_the_command_line(sample_cache, weights):
    run = run_massviz("compare", "data_samples", "--a", "detector=depth", "--b", "detector=depth,threshold=0.3",
                      "--cache", sample_cache, "--quiet", env={"MASSVIZ_WEIGHTS": weights})
    assert run.returncode == 0, run.stderr
    assert f"within {TIE_G:g} g" in run.stdout and "e-0" not in run.stdout
    all_row = next(ln for ln in run.stdout.splitlines() if ln.startswith("all "))
    assert all_row.split()[-3:] == ["0", "0", "3"]  # b better, a better, ties
