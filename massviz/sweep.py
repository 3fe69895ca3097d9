"""Threshold × K sweeps over cached traces: the CORSMAL score of every pair, without running any detector.

Every detection in a trace already carries its d and its mass prediction, so the estimate for any detection
threshold t (>= the threshold the trace was made at) and any K is the mean prediction of the K smallest-d detections
with score > t. ``SweepTable`` sorts each recording's detections by d once; a pair then costs one boolean filter per
recording.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import pandas as pd

from massviz.errors import MassvizError
from massviz.evaluate import ANN_CONTAINER, ANN_ID, ANN_MASS, default_class_of
from massviz.trace import Trace


def parse_range(spec: str, kind=float) -> list:
    """``"0.3:0.9:0.05"`` (start:stop:step, stop included), ``"1:10"`` (step 1), ``"0.4"`` or ``"1,3,5"``."""
    try:
        if ":" in spec:
            parts = [kind(p) for p in spec.split(":")]
            if len(parts) not in (2, 3):
                raise ValueError
            start, stop = parts[0], parts[1]
            step = parts[2] if len(parts) == 3 else kind(1)
            if step <= 0 or stop < start:
                raise ValueError
            n = int(math.floor((stop - start) / step + 1e-9)) + 1
            values = [start + i * step for i in range(n)]
            return [round(v, 10) for v in values] if kind is float else [int(v) for v in values]
        return [kind(p) for p in spec.split(",")]
    except ValueError:
        raise MassvizError(f"bad range {spec!r}: use start:stop[:step], a list a,b,c or one value") from None


@dataclass
class _Sorted:
    score: np.ndarray  # scores in increasing-d order (finite d only)
    pred: np.ndarray


class SweepTable:
    """Detections of many traces, prepared for fast (threshold, K) re-estimation."""

    def __init__(self, traces: Sequence[Trace]):
        self.traces = list(traces)
        self.min_threshold = max((t.detect_threshold for t in self.traces), default=0.0)
        self._sorted = []
        for t in self.traces:
            d = t.detections.d
            ok = np.flatnonzero(np.isfinite(d) & np.ones(len(d), bool))
            excluded = np.zeros(len(d), bool)
            excluded[t.excluded] = True
            ok = ok[~excluded[ok]]
            order = ok[np.argsort(d[ok], kind="stable")]
            self._sorted.append(_Sorted(t.detections.score[order], t.detections.pred[order].astype(np.float64)))

    def estimates(self, threshold: float, k: int) -> np.ndarray:
        """Estimate per trace (grams, -1 when not estimated) — equal to ``trace.reselect(k, threshold).estimate``."""
        if threshold < self.min_threshold - 1e-9:
            raise MassvizError(f"threshold {threshold} is below {self.min_threshold}, the threshold the traces were "
                               "made at; run again with a lower --threshold first")
        out = np.full(len(self._sorted), -1.0)
        for j, s in enumerate(self._sorted):
            chosen = s.pred[s.score > threshold][:k]
            if len(chosen):
                out[j] = chosen.mean()
        return out


def corsmal_scores(estimates: np.ndarray, true_mass: np.ndarray) -> np.ndarray:
    """Per-recording exp(-|m̂-m|/m), 0 where not estimated (m̂ < 0)."""
    est = np.asarray(estimates, dtype=np.float64)
    s = np.exp(-np.abs(est - true_mass) / true_mass)
    return np.where(est >= 0, s, 0.0)


def annotations_from_meta(traces: Sequence[Trace]) -> tuple[pd.DataFrame, dict]:
    """An annotation frame (``massviz.evaluate`` columns) and container→class map from the recordings' meta.json
    (``container.mass_g`` and ``container.class``), for massviz recordings that carry their ground truth.
    Ids are the traces' positions; container ids are positions + 1."""
    rows, classes = [], {}
    for i, t in enumerate(traces):
        c = (t.recording.get("meta") or {}).get("container") or {}
        if "mass_g" not in c:
            raise MassvizError(f"recording {t.recording.get('id')} has no container.mass_g in its meta.json; "
                               "pass --annotations ANN.csv", t.recording.get("path"))
        rows.append({ANN_ID: i, ANN_CONTAINER: i + 1, ANN_MASS: float(c["mass_g"])})
        classes[i + 1] = str(c.get("class", "object"))
    return pd.DataFrame(rows), classes


def match_annotations(traces: Sequence[Trace], ann: pd.DataFrame) -> np.ndarray:
    """For each annotated recording, the index of its trace (-1 when the dataset lacks it)."""
    by_id = {}
    for i, t in enumerate(traces):
        cid = str(t.recording.get("config_id", t.recording.get("id")))
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
            s = corsmal_scores(per_rec, true)
            rows.append({"threshold": float(t), "k": int(k), "score": 100 * float(s.mean()),
                         "estimated": int((per_rec >= 0).sum()), "recordings": len(true)})
    return pd.DataFrame(rows)


def best_pair(table: pd.DataFrame) -> pd.Series:
    """The best row (highest score; ties: lowest threshold, then smallest K)."""
    return table.sort_values(["score", "threshold", "k"], ascending=[False, True, True]).iloc[0]


def plot_heatmap(table: pd.DataFrame, path: str | Path, title: str = "CORSMAL score (%)") -> Path:
    """Heatmap of score over threshold (rows) × K (columns), best pair outlined; written atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from massviz.atomic import atomic_path

    grid = table.pivot(index="threshold", columns="k", values="score")
    fig, ax = plt.subplots(figsize=(1.0 + 0.55 * grid.shape[1], 1.0 + 0.35 * grid.shape[0]))
    im = ax.imshow(grid.to_numpy(), aspect="auto", cmap="viridis", origin="lower")
    ax.set_xticks(range(grid.shape[1]), [str(k) for k in grid.columns])
    ax.set_yticks(range(grid.shape[0]), [f"{t:.2f}" for t in grid.index])
    ax.set_xlabel("K (nearest patches averaged)")
    ax.set_ylabel("detection threshold")
    best = best_pair(table)
    bi, bj = list(grid.index).index(best["threshold"]), list(grid.columns).index(best["k"])
    ax.add_patch(plt.Rectangle((bj - 0.5, bi - 0.5), 1, 1, fill=False, edgecolor="red", linewidth=2))
    ax.set_title(f"{title}; best {best['score']:.2f}% at t={best['threshold']:.2f}, K={int(best['k'])}", fontsize=9)
    fig.colorbar(im, ax=ax, label="score (%)")
    fig.tight_layout()
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format=path.suffix.lstrip(".") or "png", dpi=120)
    plt.close(fig)
    return path
