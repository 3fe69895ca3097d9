"""The tracker's matching as arrays (``massviz.core.tracks``): the greedy matching in rounds and the tracks' median
sizes equal their one-at-a-time definitions (the whole tracker against a plain one: tests/test_flags.py)."""
from __future__ import annotations

import numpy as np

from massviz.core.tracks import SIZE_HISTORY, Tracker, _median_of_filled, greedy_pairs
from massviz.core.types import Detections


def greedy_one_at_a_time(rows, cols):
    used_rows, used_cols, kept = set(), set(), []
    for r, c in zip(rows.tolist(), cols.tolist()):
        if r in used_rows or c in used_cols:
            continue
        used_rows.add(r)
        used_cols.add(c)
        kept.append((r, c))
    return kept


def test_greedy_pairs_equal_the_one_at_a_time_greedy_on_random_candidates():
    rng = np.random.default_rng(0)
    for _ in range(2000):
        n = int(rng.integers(0, 60))
        rows, cols = rng.integers(0, int(rng.integers(1, 12)), n), rng.integers(0, int(rng.integers(1, 12)), n)
        got_rows, got_cols = greedy_pairs(rows, cols)
        got = sorted(zip(got_rows.tolist(), got_cols.tolist()))
        assert got == sorted(greedy_one_at_a_time(rows, cols)), (rows, cols)
    empty = greedy_pairs(np.zeros(0, np.int64), np.zeros(0, np.int64))
    assert [len(a) for a in empty] == [0, 0]


def test_the_median_of_the_filled_sizes_is_numpys_median_bit_for_bit():
    rng = np.random.default_rng(1)
    values = np.full((500, SIZE_HISTORY, 2), np.nan)
    counts = rng.integers(0, SIZE_HISTORY + 1, 500)
    for i, n in enumerate(counts):
        values[i, :n] = rng.uniform(1e3, 1e5, (n, 2)) * rng.choice([1, 1 / 3, 7.1], (n, 2))
        values[i] = values[i][rng.permutation(SIZE_HISTORY)]  # a ring: filled places anywhere
    got = _median_of_filled(values, counts)
    for i, n in enumerate(counts):
        filled = values[i][~np.isnan(values[i, :, 0])]
        want = np.median(filled, axis=0) if n else np.full(2, np.nan)
        assert np.array_equal(got[i], want, equal_nan=True), (i, values[i], got[i], want)


def test_a_track_keeps_the_median_of_its_last_sizes():
    tr = Tracker(fps=30)
    sizes = []
    for f, w in enumerate([10, 12, 11, 15, 13, 12, 14, 16]):  # one object, one detection a frame
        d = 500.0 + f
        tr.update(f, Detections(frame=[f], xyxy=[[100, 100, 100 + w, 130]], score=[1], class_id=[0], d=[d]))
        sizes.append((w * d, 30 * d))
        assert np.array_equal(tr.size[0], np.median(np.asarray(sizes[-SIZE_HISTORY:]), axis=0))
    assert list(tr.ids) == [1] and tr.seen[0] == 8
    # no depth: matched by overlap, its size is not recorded
    tr.update(8, Detections(frame=[8], xyxy=[[100, 100, 116, 130]], score=[1], class_id=[0], d=[np.nan]))
    assert list(tr.ids) == [1] and tr.seen[0] == 8
    assert np.array_equal(tr.size[0], np.median(np.asarray(sizes[-SIZE_HISTORY:]), axis=0))
