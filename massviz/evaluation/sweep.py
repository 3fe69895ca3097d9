"""Threshold × K sweeps over cached traces: the CORSMAL score of every pair, without running any detector.

Every detection in a trace already carries its d and its mass prediction, so the estimate for any detection
threshold t (>= the threshold the trace was made at) and any K is the mean prediction of the K smallest-d detections
with score > t. ``SweepTable`` sorts each recording's detections by d once; a pair then costs one boolean filter per
recording.
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import pandas as pd

from massviz.core.selection import NearestOrder, Selection, check_not_below_cut
from massviz.core.trace import Trace
from massviz.errors import MassvizError
from massviz.evaluation.metrics import default_class_of, recording_scores
from massviz.io.ccm_annotations import ANN_CONTAINER, ANN_ID, ANN_MASS

#: most values a range may expand to (a step of 1e-9 would otherwise ask for a billion).
MAX_RANGE_VALUES = 10_000
#: most (threshold, K) pairs one sweep scores (each costs one pass over every recording's detections).
MAX_SWEEP_PAIRS = 100_000


def parse_range(spec: str, kind=float, option: str = "range") -> list:
    """``"0.3:0.9:0.05"`` (start:stop:step, stop included), ``"1:10"`` (step 1), ``"0.4"`` or ``"1,3,5"``.

    Every value must be finite and the range at most :data:`MAX_RANGE_VALUES` long (counted before anything is
    allocated); ``MassvizError`` starting with ``option`` otherwise."""
    usage = f"{option} {spec!r}: use start:stop[:step], a list a,b,c or one value"
    try:
        parts = [kind(p) for p in spec.split(":" if ":" in spec else ",")]
    except (ValueError, OverflowError):
        raise MassvizError(f"{usage} (of {'integers' if kind is int else 'numbers'})") from None
    if not all(math.isfinite(v) for v in parts):
        raise MassvizError(f"{option} {spec!r}: every value must be a finite number")
    if ":" not in spec:
        if len(parts) > MAX_RANGE_VALUES:
            raise MassvizError(f"{option} {spec!r}: {len(parts)} values (at most {MAX_RANGE_VALUES})")
        return parts
    if len(parts) not in (2, 3):
        raise MassvizError(usage)
    start, stop = parts[0], parts[1]
    step = parts[2] if len(parts) == 3 else kind(1)
    if step <= 0 or stop < start:
        raise MassvizError(f"{usage} (step > 0, stop >= start)")
    count = math.floor((stop - start) / step + 1e-9) + 1
    if count > MAX_RANGE_VALUES:
        raise MassvizError(f"{option} {spec!r} would give {count} values (at most {MAX_RANGE_VALUES}); use a larger "
                           "step")
    values = [start + i * step for i in range(count)]
    return [round(v, 10) for v in values] if kind is float else [int(v) for v in values]


class SweepTable:
    """Detections of many traces (or ``massviz.io.cache.TraceIndex`` values: anything with ``detections``,
    ``excluded``, ``detect_threshold``), prepared for fast (threshold, K, stride) re-estimation of all of them at once.

    Each recording's detections are put in ``NearestOrder`` (the one definition of the selection's order: finite d,
    not excluded, by d, ties the earliest first) once; the orders are concatenated, so that a (threshold, K) pair is a
    handful of array operations over every recording together instead of a Python loop over recordings. The mean
    of each recording's chosen predictions is taken by ``np.mean`` over the same values in the same order as
    ``estimate_mass`` does, so the estimates are identical (not just close) to ``trace.reselect(k, threshold)`` (and
    with ``stride``, to ``massviz.evaluation.tuning.retune``)."""

    def __init__(self, traces: Sequence[Trace], excluded: Sequence | None = None):
        """``excluded``: detection indices never selected, one array per trace (default: each trace's own)."""
        self.traces = list(traces)
        self.min_threshold = max((t.detect_threshold for t in self.traces), default=0.0)
        excluded = [t.excluded for t in self.traces] if excluded is None else list(excluded)
        orders = [NearestOrder(t.detections.d, t.detections.score, ex) for t, ex in zip(self.traces, excluded)]
        n = np.array([len(o.order) for o in orders], dtype=np.int64)
        self._trace_of = np.repeat(np.arange(len(orders), dtype=np.int64), n)
        self._start = np.concatenate([[0], np.cumsum(n)])[:-1]
        cat = (lambda parts, dtype: np.concatenate(parts).astype(dtype, copy=False) if len(parts) else
               np.zeros(0, dtype))
        # scores keep their dtype (float32): compared with the threshold exactly as NearestOrder.select compares them
        self._score = np.concatenate([o.score for o in orders]) if orders else np.zeros(0, np.float32)
        self._pred = cat([np.asarray(t.detections.pred, dtype=np.float64)[o.order]
                          for t, o in zip(self.traces, orders)], np.float64)
        self._frame = cat([np.asarray(t.detections.frame, dtype=np.int64)[o.order]
                           for t, o in zip(self.traces, orders)], np.int64)
        self._by_threshold: dict = {}

    def _check(self, threshold: float) -> None:
        check_not_below_cut(threshold, self.min_threshold, "the traces")

    def _ranked(self, threshold: float, stride: int):
        """(recording, rank, prediction) of the detections above ``threshold`` on frames ``% stride == 0``, in each
        recording's nearest-first order; rank 0 is the nearest."""
        key = (float(threshold), int(stride))
        if key not in self._by_threshold:
            keep = self._score > threshold
            if stride != 1:
                keep &= self._frame % int(stride) == 0
            trace_of = self._trace_of[keep]
            counts = np.bincount(trace_of, minlength=len(self.traces))
            first = np.concatenate([[0], np.cumsum(counts)])[:-1]
            rank = np.arange(len(trace_of), dtype=np.int64) - first[trace_of]
            if len(self._by_threshold) > 64:
                self._by_threshold.clear()
            self._by_threshold[key] = (trace_of, rank, self._pred[keep])
        return self._by_threshold[key]

    def chosen(self, threshold: float, k: int, stride: int = 1) -> np.ndarray:
        """Number of patches chosen per trace (0 when not estimated): ``len(retune(trace, k=, threshold=,
        stride=).selection)``."""
        self._check(threshold)
        k = Selection.check("k", k)
        trace_of, _, _ = self._ranked(threshold, stride)
        return np.minimum(np.bincount(trace_of, minlength=len(self.traces)), k)

    def estimates(self, threshold: float, k: int, stride: int = 1) -> np.ndarray:
        """Estimate per trace (grams, -1 when not estimated) — equal to ``trace.reselect(k, threshold).estimate``
        (``stride`` > 1: to ``retune(trace, k=, threshold=, stride=).estimate``)."""
        self._check(threshold)
        k = Selection.check("k", k)
        trace_of, rank, pred = self._ranked(threshold, stride)
        chosen = rank < k
        trace_of, rank, pred = trace_of[chosen], rank[chosen], pred[chosen]
        counts = np.bincount(trace_of, minlength=len(self.traces))
        out = np.full(len(self.traces), -1.0)
        if not len(trace_of):
            return out
        width = int(counts.max())
        table = np.zeros((len(self.traces), width))
        table[trace_of, rank] = pred
        for c in np.unique(counts[counts > 0]):  # rows of c values: np.mean over exactly those, as estimate_mass
            rows = np.flatnonzero(counts == c)
            out[rows] = table[rows, :c].mean(axis=1)
        return out


def annotations_from_meta(traces: Sequence[Trace]) -> tuple[pd.DataFrame, dict]:
    """An annotation frame (``massviz.evaluation.metrics`` columns) and container→class map from the recordings' meta.json
    (``container.mass_g`` and ``container.class``), for massviz recordings that carry their ground truth.
    Ids are the traces' positions; container ids are positions + 1."""
    rows, classes = [], {}
    for i, t in enumerate(traces):
        gt = t.ground_truth
        if gt is None or gt.mass_g is None:
            raise MassvizError(f"recording {t.recording.id} has no container.mass_g in its meta.json; "
                               "pass --annotations ANN.csv", t.recording.path)
        rows.append({ANN_ID: i, ANN_CONTAINER: i + 1, ANN_MASS: gt.mass_g})
        classes[i + 1] = gt.cls or "object"
    return pd.DataFrame(rows), classes


def match_annotations(traces: Sequence[Trace], ann: pd.DataFrame) -> np.ndarray:
    """For each annotated recording, the index of its trace (-1 when the dataset lacks it)."""
    by_id = {}
    for i, t in enumerate(traces):
        cid = t.recording.config_id
        if cid.lstrip("-").isdigit():
            by_id[int(cid)] = i
    return np.array([by_id.get(int(a), -1) for a in ann[ANN_ID]], dtype=np.int64)


def sweep(traces: Sequence[Trace], thresholds: Sequence[float], ks: Sequence[int], ann: pd.DataFrame | None = None,
          class_of=default_class_of) -> pd.DataFrame:
    """Score of every (threshold, K) pair. ``ann`` None → ground truth from the recordings' meta.json.

    Returns a frame with columns threshold, k, score (%), estimated (count), recordings.
    """
    if ann is None:
        ann, _ = annotations_from_meta(traces)
        index = np.arange(len(traces))
    else:
        index = match_annotations(traces, ann)
    true = ann[ANN_MASS].to_numpy(dtype=np.float64)
    table = SweepTable(traces)
    rows = []
    for t in thresholds:
        for k in ks:
            est = table.estimates(float(t), int(k)) if len(traces) else np.zeros(0)
            per_rec = np.where(index >= 0, est[np.clip(index, 0, None)] if len(est) else -1.0, -1.0)
            s = recording_scores(per_rec, true)
            rows.append({"threshold": float(t), "k": int(k), "score": 100 * float(s.mean()),
                         "estimated": int((per_rec >= 0).sum()), "recordings": len(true)})
    return pd.DataFrame(rows)


def best_pair(table: pd.DataFrame) -> pd.Series:
    """The best row (highest score; ties: lowest threshold, then smallest K)."""
    return table.sort_values(["score", "threshold", "k"], ascending=[False, True, True]).iloc[0]
