"""The K-nearest patch selection, as the paper's published code makes it: the ``Selection`` asked for (K, threshold,
stride, exclusions), the K detections with the smallest distance d (``massviz.core.features``) among those scored
above the threshold, the mass estimate (the mean of their predictions) and why nothing was selected.

Deliberate difference from the original code (CORSMAL/Visual, demo/generate_video_inference.py): the original's
selection looks every sorted distance up with ``np.where(d == value)[0][0]``, so two detections at exactly the same
distance both resolved to the *first* one (the same patch chosen twice). massviz uses a stable sort: ties go to the
earliest detection, and each detection is chosen at most once; a detection without a finite d is never selected.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from massviz.core.types import Detections


@dataclass(frozen=True)
class Selection:
    """What the selection stage is asked for, one value from the CLI or a notebook to ``FramePipeline`` and the
    ``Trace``: the ``k`` nearest detections with score > ``threshold`` among every ``stride``-th frame, never the
    detections ``exclude`` (indices into the recording's detections).

    ``threshold`` None: the detector's own score cut (what ``FramePipeline`` resolves it to when the caller names
    none; the CLI and ``massviz.app`` always name it).
    """

    k: int = 5
    threshold: float | None = None
    stride: int = 1
    exclude: tuple = ()

    def __post_init__(self) -> None:
        if isinstance(self.k, bool) or int(self.k) != self.k or self.k < 1:
            raise ValueError(f"k must be an integer >= 1, got {self.k!r}")
        if isinstance(self.stride, bool) or int(self.stride) != self.stride or self.stride < 1:
            raise ValueError(f"stride must be an integer >= 1, got {self.stride!r}")
        if self.threshold is not None and not 0.0 <= float(self.threshold) < 1.0:
            raise ValueError(f"threshold must be in [0, 1), got {self.threshold!r}")
        ex = np.asarray(self.exclude if self.exclude is not None else ())
        ex = np.flatnonzero(ex) if ex.dtype == bool else ex.astype(np.int64).reshape(-1)
        object.__setattr__(self, "k", int(self.k))
        object.__setattr__(self, "stride", int(self.stride))
        object.__setattr__(self, "threshold", None if self.threshold is None else float(self.threshold))
        object.__setattr__(self, "exclude", tuple(int(i) for i in ex))

    def replace(self, **changes) -> "Selection":
        return dataclasses.replace(self, **changes)

    def at_cut(self, detect_threshold: float) -> "Selection":
        """This selection with its threshold resolved for a detector whose score cut is ``detect_threshold``: the
        cut itself when it names none; ``ValueError`` when it names one below the cut (those detections were never
        kept). What the edge (``massviz.app.Pipeline``, ``massviz.app.process``, ``FramePipeline``'s shorthand)
        resolves once; every stage and sink after it reads the trace's (or the ``FrameResult``'s) values."""
        if self.threshold is None:
            return self.replace(threshold=float(detect_threshold))
        if self.threshold < float(detect_threshold) - 1e-9:
            raise ValueError(f"selection threshold {self.threshold} is below the detector's score cut "
                             f"{float(detect_threshold)} (lower-scored detections are never kept)")
        return self


class NearestOrder:
    """The re-selection engine: detections sorted by d once (finite d only, ties: the earliest first, excluded ones
    left out), so that the K nearest above any threshold is one boolean filter. ``select_k_nearest``, every
    ``Trace.reselect`` and the sweeps go through it."""

    def __init__(self, d: np.ndarray, score: np.ndarray, exclude: np.ndarray | None = None):
        d = np.asarray(d, dtype=np.float64)
        ok = np.isfinite(d)
        if exclude is not None and len(exclude):
            ex = np.asarray(exclude)
            ok[ex if ex.dtype != bool else np.flatnonzero(ex)] = False
        candidates = np.flatnonzero(ok)
        self.order = candidates[np.argsort(d[candidates], kind="stable")]
        self.score = np.asarray(score)[self.order]

    def select(self, k: int, threshold: float) -> np.ndarray:
        """Indices of the ``k`` nearest detections with score > ``threshold``, nearest first."""
        if k < 1:
            raise ValueError("k must be >= 1")
        return self.order[self.score > threshold][:k]


def select_k_nearest(d: np.ndarray, score: np.ndarray, k: int, threshold: float,
                     exclude: np.ndarray | None = None) -> np.ndarray:
    """Indices of the ``k`` detections with the smallest ``d`` among those with score > threshold and a finite d,
    nearest first; ties go to the earliest detection. ``exclude`` (bool mask or indices) removes detections."""
    if k < 1:
        raise ValueError("k must be >= 1")
    return NearestOrder(d, score, exclude).select(k, threshold)


#: the prefix of the events that name an object a detector did not take as a container (``FramePipeline``).
REJECTED_PREFIX = "not a container candidate: "


@dataclass(frozen=True)
class NotEstimated:
    """Why nothing was selected: ``rejected`` the objects the detector did not take as container candidates, as
    (reason, frames) in order of first appearance (a frame once per object: ``Event.reason`` of the ``skipped``
    events), and ``usable`` how many detections have depth (none of them chosen: score <= threshold or excluded)."""

    rejected: tuple = ()
    usable: int = 0

    def _summary(self) -> str:
        parts = []
        for what, frames in self.rejected:
            fr = sorted(set(frames))
            span = f"frame {fr[0]}" if len(fr) == 1 else f"frames {fr[0]}–{fr[-1]}"
            parts.append(f"{len(frames)} × {what} ({span})")
        rest = (f"; {self.usable} other detection(s) with depth not chosen (score <= threshold or excluded)"
                if self.usable else "")
        return f"only border-cut / implausibly sized objects: {', '.join(parts)}{rest}"

    def message(self) -> str:
        """The ``not_estimated`` event's line: "only border-cut / implausibly sized objects: 14 × border-cut object
        (frames 0–7), ...: mass not estimated (-1)" when the detector rejected objects, else "no detection with
        depth: mass not estimated (-1)"."""
        if not self.rejected:
            return "no detection with depth: mass not estimated (-1)"
        return f"{self._summary()}: mass not estimated (-1)"

    def warning(self) -> str | None:
        """The line a command warns with ("not estimated: only border-cut / implausibly sized objects: ..."); None
        when the detector rejected nothing (nothing more to say than the estimate of -1)."""
        return f"not estimated: {self._summary()}" if self.rejected else None


def why_not_estimated(dets: Detections, events=()) -> NotEstimated:
    """The ``NotEstimated`` of a recording whose selection is empty, from its ``skipped`` events' reasons
    (``Event.reason``: objects the detector rejected) and its detections."""
    rejected: dict[str, list[int]] = {}
    for e in events:
        if e.kind == "skipped" and e.reason:
            rejected.setdefault(e.reason, []).append(int(e.frame))
    if not rejected:
        return NotEstimated()
    usable = int(np.isfinite(np.asarray(dets.d, dtype=np.float64)).sum()) if len(dets) else 0
    return NotEstimated(rejected=tuple((what, tuple(frames)) for what, frames in rejected.items()), usable=usable)


def not_estimated_reason(dets: Detections, events=()) -> str:
    """Why nothing was selected, in one line (``why_not_estimated(dets, events).message()``)."""
    return why_not_estimated(dets, events).message()


def estimate_mass(pred: np.ndarray, selection: np.ndarray) -> float:
    """Mean of the selected predictions (grams); -1 when nothing is selected (not estimated)."""
    if len(selection) == 0:
        return -1.0
    return float(np.mean(np.asarray(pred, dtype=np.float64)[selection]))
