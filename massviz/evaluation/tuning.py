"""Re-estimation from cached traces for another threshold, K, frame stride or set of excluded detections.

Nothing here runs the detector or the model: every detection of a trace already carries its d and its prediction.

* ``subsample(trace, stride)``: the trace as if only every ``stride``-th frame had been processed (detections whose
  ``frame % stride == 0``), with its selection and estimate recomputed. Detection indices change (the kept ones are
  renumbered in order); ``kept_indices`` maps them back.
* ``retune(trace, k=, threshold=, stride=, exclude=)``: all four at once, in one ``reselect`` (one flags analysis);
  ``exclude`` are indices into *this* trace's detections, as for ``Trace.reselect``. For ``stride == 1`` it is
  exactly ``trace.reselect(k, threshold, exclude)``.
* ``retuned_selection`` / ``retuned_estimate``: the selection stage alone (indices into the trace's detections and
  their estimate), no trace made: of a ``Trace`` or a cached trace's selection index (``SelectionSource``).
* ``score_traces(traces, ann)``: the CORSMAL score (``massviz.evaluation.metrics.ScoreReport``) of the traces' estimates,
  against an annotation CSV frame or, by default, the ground truth in the recordings' ``meta.json``.
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Protocol, Sequence

import numpy as np
import pandas as pd

from massviz.core.detector import detector_info
from massviz.core.selection import Selection, check_not_below_cut, estimate_mass, select_k_nearest
from massviz.core.trace import Trace
from massviz.core.types import Detections
from massviz.evaluation.metrics import ScoreReport, default_class_of, score_from_estimates
from massviz.evaluation.sweep import annotations_from_meta, match_annotations


def kept_indices(trace: "Trace | SelectionSource", stride: int) -> np.ndarray:
    """Indices of the detections that ``subsample(trace, stride)`` keeps (frame % stride == 0), ascending."""
    return np.flatnonzero(trace.detections.frame % Selection.check("stride", stride) == 0)


def _renumbered(n: int, keep: np.ndarray) -> np.ndarray:
    """Old detection index -> its index among ``keep`` (-1: not kept)."""
    renumber = np.full(n, -1, dtype=np.int64)
    renumber[keep] = np.arange(len(keep))
    return renumber


def _restricted(trace: Trace, stride: int, excluded) -> Trace:
    """``trace``'s data restricted to the frames with ``frame % stride == 0`` (detections renumbered, ``excluded``
    and the measurements carried over renumbered), not yet selected: plain data for one ``reselect``."""
    keep = kept_indices(trace, stride)
    renumber = _renumbered(len(trace.detections), keep)
    ex = renumber[np.asarray(excluded, dtype=np.int64)]
    measurements = [dataclasses.replace(m, detection=int(renumber[int(m.detection)])) for m in trace.measurements
                    if renumber[int(m.detection)] >= 0]
    return dataclasses.replace(
        trace, detections=trace.detections[keep], frames=trace.frames[trace.frames % stride == 0],
        stride=math.lcm(int(trace.stride), stride), excluded=ex[ex >= 0], selection=np.zeros(0, dtype=np.int64),
        measurements=measurements, flags=None)


def _exclusions(exclude) -> np.ndarray:
    ex = np.asarray(exclude)
    return np.flatnonzero(ex) if ex.dtype == bool else ex.astype(np.int64).reshape(-1)


def subsample(trace: Trace, stride: int) -> Trace:
    """``trace`` restricted to the frames with ``frame % stride == 0``; selection and estimate recomputed with the
    trace's K and threshold, its exclusions and measurements carried over (renumbered). ``stride`` of the result is
    the least common multiple of the trace's stride and ``stride`` (the frames a run with that stride would have
    processed, when the trace's stride divides it)."""
    stride = int(stride)
    kept_indices(trace, stride)  # its check of stride
    if stride == 1:
        return trace
    return _restricted(trace, stride, trace.excluded).reselect()


def retune(trace: Trace, *, k: int | None = None, threshold: float | None = None, stride: int = 1,
           exclude=None) -> Trace:
    """The trace re-selected for ``k``/``threshold`` (None: keep the trace's), every ``stride``-th frame and the
    detections ``exclude`` (indices into ``trace.detections`` or a bool mask; None keeps the trace's exclusions):
    one ``reselect`` (one flags analysis)."""
    stride = int(stride)
    kept_indices(trace, stride)  # its check of stride
    if stride == 1:
        return trace.reselect(k=k, threshold=threshold, exclude=exclude)
    excluded = trace.excluded if exclude is None else _exclusions(exclude)
    return _restricted(trace, stride, excluded).reselect(k=k, threshold=threshold)


def original_selection(trace: Trace, retuned: Trace, stride: int) -> np.ndarray:
    """The selection of ``retuned`` (= ``retune(trace, stride=stride, ...)``) as indices into ``trace.detections``."""
    sel = np.asarray(retuned.selection, dtype=np.int64)
    return sel if int(stride) == 1 else kept_indices(trace, stride)[sel]


def score_traces(traces: Sequence[Trace], ann: pd.DataFrame | None = None, class_of=None) -> ScoreReport:
    """CORSMAL score of the traces' estimates.

    ``ann`` None: the ground truth of the recordings' ``meta.json`` (``massviz.evaluation.sweep.annotations_from_meta``; ids are
    the traces' positions, one container per recording, its class from ``container.class``). Otherwise an annotation
    frame (``massviz.io.ccm_annotations.read_annotations``) matched by the recordings' configuration ids, with ``class_of``
    (default: the CCM classes).
    """
    return score_estimates(traces, [float(t.estimate) for t in traces], ann, class_of)


def score_estimates(traces: Sequence[Trace], estimates: Sequence[float], ann: pd.DataFrame | None = None,
                    class_of=None) -> ScoreReport:
    """``score_traces`` with the estimates given (``estimates[j]`` for ``traces[j]``): the traces only name the
    recordings and carry their ground truth."""
    if ann is None:
        ann, classes = annotations_from_meta(traces)
        return score_from_estimates(dict(enumerate(estimates)), ann, class_of or classes)
    index = match_annotations(traces, ann)
    values = {int(a): (float(estimates[j]) if j >= 0 else None) for a, j in zip(ann["id"], index)}
    return score_from_estimates(values, ann, class_of or default_class_of)


class SelectionSource(Protocol):
    """What the selection stage reads: a ``Trace``, or a cached trace's selection index
    (``massviz.io.cache.TraceIndex``, its detections' columns without masks or patches)."""

    detections: Detections
    detect_threshold: float


def retuned_selection(source: SelectionSource, *, k: int, threshold: float, stride: int = 1,
                      exclude=()) -> np.ndarray:
    """The selection stage alone: what ``retune(source, k=, threshold=, stride=, exclude=)`` selects, as indices
    into ``source.detections`` (nearest first; ``original_selection`` of the retuned trace), with no trace made and
    so no flags analysis: what a slider needs for every recording but the one shown."""
    check_not_below_cut(float(threshold), source.detect_threshold, "these detections")
    dets = source.detections
    excluded = _exclusions(exclude)
    if int(stride) == 1:
        return select_k_nearest(dets.d, dets.score, int(k), float(threshold), excluded)
    keep = kept_indices(source, stride)
    ex = _renumbered(len(dets), keep)[excluded]
    return keep[select_k_nearest(dets.d[keep], dets.score[keep], int(k), float(threshold), ex[ex >= 0])]


def retuned_estimate(source: SelectionSource, *, k: int, threshold: float, stride: int = 1, exclude=()) -> float:
    """The estimate of ``retuned_selection`` (``retune(...).estimate``: the same predictions in the same order, so
    the same value to the bit)."""
    return estimate_mass(source.detections.pred,
                         retuned_selection(source, k=k, threshold=threshold, stride=stride, exclude=exclude))


def index_recordings(recordings, options=None, *, progress: bool = False, **kwargs) -> list:
    """The selection index (``massviz.io.cache.TraceIndex``, a few kB) of each recording's cached trace, processing
    the recordings not in the cache first: what a ``massviz.views.widgets.Tuner`` over a whole dataset is given
    (``Tuner(index_recordings(paths, detector="depth"))``). Options as ``massviz.app.build_pipeline``; recordings
    unchanged since they were last opened are recognised from their file identities (``massviz.io.identity``)."""
    import dataclasses

    from massviz.app import build_pipeline
    from massviz.io.identity import LocatedRecording, open_remembered

    pipeline = build_pipeline(options, **kwargs)
    if pipeline.cache is None:
        raise ValueError("index_recordings needs the trace cache (no_cache=False)")
    o, selection = pipeline.options, pipeline.selection
    info = detector_info(pipeline.detector)
    out = []
    for r in recordings:
        rec = r if not isinstance(r, (str, Path)) else open_remembered(r, pipeline.cache.root,
                                                                       allow_partial=o.allow_partial)
        index = pipeline.cache.load_index(rec, info, selection.stride, selection.threshold)
        if index is None or index.weights_id != getattr(pipeline.model, "weights_id", ""):
            if isinstance(rec, LocatedRecording):  # recognised, not opened: open it to process it
                from massviz.io.recording import open_recording

                rec = open_recording(r, allow_partial=o.allow_partial)
            pipeline.process(rec, progress=progress)
            index = pipeline.cache.load_index(rec, info, selection.stride, selection.threshold)
        out.append(dataclasses.replace(index, recording=rec.info()))
    return out


__all__ = ["index_recordings", "kept_indices", "subsample", "retune", "retuned_estimate", "retuned_selection",
           "original_selection", "score_traces", "SelectionSource",
           "score_estimates"]
