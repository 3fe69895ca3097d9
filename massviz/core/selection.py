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
import math
import numbers
from dataclasses import dataclass, field

import numpy as np

from massviz.core.types import Detections
from massviz.errors import MassvizError


def _shown(value, n: int = 60) -> str:
    """``value`` in a message: 2.5, not np.float64(2.5); text quoted; at most ``n`` characters."""
    if isinstance(value, np.generic):
        value = value.item()
    text = repr(value)
    return text if len(text) <= n else text[:n] + "..."


@dataclass(frozen=True)
class Selection:
    """What the selection stage is asked for, one value from the CLI or a notebook to ``FramePipeline`` and the
    ``Trace``: the ``k`` nearest detections with score > ``threshold`` among every ``stride``-th frame, never the
    detections ``exclude`` (indices into the recording's detections).

    ``threshold`` None: the detector's own score cut. The edge that builds the pipeline (``massviz.app.Pipeline``)
    resolves it once (``at_cut``); ``cut`` then says for which cut, and the stages it is given use it as it is.
    """

    k: int = 5
    threshold: float | None = None
    stride: int = 1
    exclude: tuple = ()
    #: the detector's score cut this selection was resolved for (``at_cut``); None: not resolved. Not part of the
    #: value (equality, repr); a ``replace`` that changes the threshold drops it.
    cut: float | None = field(default=None, init=False, compare=False, repr=False)

    def __post_init__(self) -> None:
        k, stride = self.check("k", self.k), self.check("stride", self.stride)
        threshold = None if self.threshold is None else self.check("threshold", self.threshold)
        ex = np.asarray(self.exclude if self.exclude is not None else ())
        ex = np.flatnonzero(ex) if ex.dtype == bool else ex.astype(np.int64).reshape(-1)
        object.__setattr__(self, "k", k)
        object.__setattr__(self, "stride", stride)
        object.__setattr__(self, "threshold", threshold)
        object.__setattr__(self, "exclude", tuple(int(i) for i in ex))

    @staticmethod
    def check(name: str, value, label: str | None = None) -> int | float:
        """``value`` as the selection's ``name``: ``k`` and ``stride`` an integer >= 1 (returned as an int),
        ``threshold`` a number in [0, 1) (a float); else ``ValueError`` "<label> must be an integer" / "must be >= 1"
        / "must be a number" / "must be in [0, 1)", ", got <value>" (``label``: how the caller names it, ``--k`` or
        ``column 'k'``; default ``name``). The one check of K, stride and threshold: the options
        (``massviz.app.PipelineOptions``), ``massviz sweep``'s grid, a run folder's ``index.csv``, a trace file and
        the trace cache's index refuse a value with these words."""
        label = name if label is None else label
        if isinstance(value, np.generic):
            value = value.item()
        real = isinstance(value, numbers.Real) and not isinstance(value, bool)
        if name in ("k", "stride"):
            if not real or not (isinstance(value, numbers.Integral) or math.isfinite(value) and value == int(value)):
                raise ValueError(f"{label} must be an integer, got {_shown(value)}")
            if value < 1:
                raise ValueError(f"{label} must be >= 1, got {_shown(value)}")
            return int(value)
        if name == "threshold":
            if not real:
                raise ValueError(f"{label} must be a number, got {_shown(value)}")
            if not 0.0 <= float(value) < 1.0:
                raise ValueError(f"{label} must be in [0, 1), got {_shown(value)}")
            return float(value)
        raise KeyError(f"the selection has no checked value {name!r} (k, stride, threshold)")

    def replace(self, **changes) -> "Selection":
        """``dataclasses.replace``, keeping ``cut`` unless the threshold changes (K, stride and exclusions do not
        change what the detector's cut allows)."""
        out = dataclasses.replace(self, **changes)
        if "threshold" not in changes and self.cut is not None:
            object.__setattr__(out, "cut", self.cut)
        return out

    def at_cut(self, detect_threshold: float) -> "Selection":
        """This selection with its threshold resolved for a detector whose score cut is ``detect_threshold`` (and
        ``cut`` set): the cut itself when it names none; ``BelowCutError`` when it names one below the cut
        (``check_not_below_cut``). What the edge (``massviz.app.Pipeline``, ``massviz.app.process`` and
        ``FramePipeline`` given a selection not resolved for their detector) does once; every stage and sink after it
        reads the trace's (or the ``FrameResult``'s) values."""
        cut = float(detect_threshold)
        if self.threshold is None:
            out = dataclasses.replace(self, threshold=cut)
        else:
            check_not_below_cut(self.threshold, cut)
            out = dataclasses.replace(self)
        object.__setattr__(out, "cut", cut)
        return out

    def for_cut(self, detect_threshold: float) -> "Selection":
        """This selection when it was resolved for ``detect_threshold`` already (``cut``), else
        ``at_cut(detect_threshold)``: what a stage given a selection calls, so that one resolved at the edge is not
        resolved again."""
        return self if self.cut is not None and self.cut == float(detect_threshold) else self.at_cut(detect_threshold)


#: how far below a score cut a threshold may read and still be at it (a threshold that went through a float32 column
#: or a CSV round trip)
CUT_SLACK = 1e-9


class BelowCutError(MassvizError, ValueError):
    """A selection threshold below the score cut its detections were kept at (``check_not_below_cut``)."""


def serves(cut: float, threshold: float) -> bool:
    """Whether detections kept at score cut ``cut`` serve a selection at ``threshold``: the threshold is not below
    the cut (``CUT_SLACK`` aside). The one predicate of that rule: ``check_not_below_cut`` refuses what it does not
    serve, and the trace cache picks the entry that serves a threshold with it."""
    return float(threshold) >= float(cut) - CUT_SLACK


def check_not_below_cut(threshold: float, cut: float, kept_by: str = "the detector", path=None) -> None:
    """The one rule of a selection threshold against the score cut its detections were kept at (``cut``, by
    ``kept_by``: the detector, a trace, a cached trace, traces): it may be at or above it, never below (lower-scored
    detections were never kept; detections kept at t serve any threshold >= t). ``BelowCutError`` (a ``MassvizError``
    and a ``ValueError``) naming both and what to run. ``Selection.at_cut``, ``Trace.reselect``, the retuning
    sliders, the sweep table and a cached trace's index all refuse with it."""
    if not serves(cut, threshold):
        raise BelowCutError(f"threshold {threshold} is below the score cut {cut} of {kept_by} (lower-scored "
                            f"detections were never kept); run the detector again with --threshold {threshold} "
                            "or lower", path)


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
        return self.order[self.score > threshold][:Selection.check("k", k)]


def select_k_nearest(d: np.ndarray, score: np.ndarray, k: int, threshold: float,
                     exclude: np.ndarray | None = None) -> np.ndarray:
    """Indices of the ``k`` detections with the smallest ``d`` among those with score > threshold and a finite d,
    nearest first; ties go to the earliest detection. ``exclude`` (bool mask or indices) removes detections."""
    Selection.check("k", k)  # before the sort
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
