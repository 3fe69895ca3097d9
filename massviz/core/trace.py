"""The trace: everything one pipeline run computed, with each stage's wall time.

Every consumer (Rerun logger, Open3D sink, notebooks, evaluation, training extraction) only *reads* a ``Trace``.
``reselect`` recomputes the selection, the estimate and their events for another K, threshold or set of excluded detections
without running the detector or the model again (every detection already carries its prediction).

A trace saves to a single ``.npz`` (no pickle; ``massviz.io.trace_file.save_trace`` / ``load_trace``): JSON header +
parallel arrays + packed masks + PNG-encoded patches. This module reads and writes no file.

A ``Trace`` is plain data: constructing it or ``dataclasses.replace`` computes nothing. Its **tracks**
(``detections.track``, ``massviz.core.tracks``) and the **flags** of its selection (``flags``,
``massviz.core.flags.analyse``: which chosen patches are probably not the container, and the estimate without them) are
computed by explicit stages: the pipeline's ``FramePipeline.finish`` (tracks as frames are processed, flags once at the
end), ``Trace.reselect`` (flags of the new selection) and ``analyse_trace`` (for a trace whose recording, detections or
ground-truth overlaps were replaced, or a file written before tracks and flags were saved: what is missing or no longer
describes the trace). They are saved with the trace (array ``det_track``, header ``flags``). Computing them opens no
file (the ground truth's masks are read by io, ``massviz.io.ground_truth.with_ground_truth``, into per-detection
overlaps the flags read).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from massviz.core.detector import describe_cut
from massviz.core.flags import Flags, analyse
from massviz.core.frame_stage import FramePatches
from massviz.core.measurement import Measurement, ranked_measurements
from massviz.core.selection import (
    NearestOrder,
    Selection,
    check_not_below_cut,
    estimate_mass,
    not_estimated_reason,
    select_k_nearest,
)
from massviz.core.tracks import assign_tracks
from massviz.core.types import Detections, Frame, GroundTruth, RecordingInfo, class_name


@dataclass
class FrameResult:
    """What the pipeline computed for one frame (``massviz.core.pipeline.FramePipeline.step``), or what a finished
    trace holds of it (``frame_results``): what a sink is given for each frame.

    - ``frame``: the frame; ``detections``: its detections with d, a, b and ``pred`` (their indices in the trace are
      ``offset + i``); ``patches``: their RGB crops (``massviz.core.frame_stage.FramePatches``, cut when read).
    - ``selection``: the K nearest detections *so far* (indices into the trace's detections, nearest first) and
      ``running_estimate`` the mean of their predictions (-1 while nothing is selected).
    - ``active``: indices into ``detections`` of those above the selection's score threshold.
    - ``timings``: this frame's seconds per stage (read, detect, features, predict, select); ``events`` its decisions
      (both empty for a frame of a finished trace).
    """

    frame: Frame
    detections: Detections
    patches: list
    offset: int
    selection: np.ndarray
    running_estimate: float
    timings: dict = field(default_factory=dict)
    events: list = field(default_factory=list)
    active: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))


class Event(NamedTuple):
    """One decision worth reading, at a frame (-1: not tied to a frame).

    ``kind`` is one of ``EVENT_KINDS``: ``chosen`` (a patch was selected), ``estimate`` (the estimate was made),
    ``not_estimated``, ``skipped`` (a detection that cannot be used, e.g. its mask has no depth), ``cache`` (detections
    reused from the trace cache), ``measured`` (the 3D stage's size of a chosen patch), ``warning`` and ``info``.
    ``level`` is ``debug``, ``info`` or ``warn`` (the Rerun ``/log`` level). ``detection`` is the index into the
    trace's detections the event is about (-1: none). ``reason``: what a ``skipped`` event of an object the detector
    did not take as a container rejected it for (``massviz.core.types.Rejection.reason``, e.g. ``border-cut object``;
    "" for every other event): what ``massviz.core.selection.why_not_estimated`` counts, never the message.
    """

    frame: int
    message: str
    kind: str = "info"
    level: str = "info"
    detection: int = -1
    reason: str = ""

    @property
    def is_selection(self) -> bool:
        """Events that belong to one selection (replaced when the trace is re-selected)."""
        return self.kind in SELECTION_KINDS

    def to_list(self) -> list:
        out = [int(self.frame), str(self.message), self.kind, self.level, int(self.detection)]
        return [*out, str(self.reason)] if self.reason else out


EVENT_KINDS = ("chosen", "estimate", "not_estimated", "skipped", "cache", "measured", "warning", "info")
SELECTION_KINDS = frozenset({"chosen", "estimate", "not_estimated"})
LEVELS = ("debug", "info", "warn")


@dataclass
class Trace:
    """Output of ``massviz.core.pipeline.run`` for one recording.

    - ``recording``: ``RecordingInfo`` (id, path, size, frame count, intrinsics, meta; ``.ground_truth``).
    - ``detector``: the detector's name and settings; ``detect_threshold`` the score threshold it ran at.
    - ``threshold``, ``k``, ``stride``: the selection settings this trace's ``selection``/``estimate`` use.
    - ``frames``: indices of the processed frames.
    - ``detections``: every detection (score > detect_threshold) with d, a, b, the model's ``pred`` and, for the
      ``keep_patches`` nearest ones, the RGB patch.
    - ``selection``: indices into ``detections`` of the chosen patches, nearest first.
    - ``estimate``: mean of the chosen predictions in grams; -1 when nothing was selected (not estimated).
    - ``excluded``: detection indices the user excluded (never selected).
    - ``timings``: wall time per stage in seconds; ``events``: typed ``Event`` decisions worth reading.
    - ``measurements``: the measured size of each chosen detection (``massviz.core.measurement.Measurement``),
      filled by the measure stage (``massviz.measure3d``, recordings with intrinsics; empty when it did not run);
      views only read them. ``reselect`` keeps those of the detections still chosen, re-ranked.
    - ``frame_timings``: seconds per stage for each processed frame (stage -> array aligned with ``frames``; empty
      for traces made before massviz recorded them).
    - ``flags``: ``massviz.core.flags.Flags`` of the selection, made by the stages that make or change the selection
      (module docstring); None on a trace no stage has analysed yet (``analyse_trace``).
    - ``compute``: where and how the detections and predictions were computed (``FrameStage.describe``: device,
      kernels, precision, batch, mode ``faithful``/``fast``); after ``massviz.core.pipeline.repredict`` also
      ``predict_device``/``predict_kernels``/``predict_precision``/``predict_mode`` of the new predictions, ``mode``
      then ``faithful`` only when both were; empty for traces made before massviz recorded it.
    - ``ground_truth_source``: what the detections' ground-truth overlaps (``Detections.gt_iou`` ...) were computed
      from (``massviz.core.flags.ground_truth_source``; "" none): the flags use them only while it matches the
      recording's ground truth (``massviz.io.ground_truth.with_ground_truth`` fills them).
    """

    recording: RecordingInfo
    detector: dict
    detect_threshold: float
    threshold: float
    k: int
    stride: int
    frames: np.ndarray
    detections: Detections
    selection: np.ndarray
    estimate: float
    weights_id: str = ""
    timings: dict = field(default_factory=dict)
    events: list = field(default_factory=list)
    excluded: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    measurements: list[Measurement] = field(default_factory=list)
    frame_timings: dict = field(default_factory=dict)
    flags: Flags | None = None
    ground_truth_source: str = ""
    compute: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        # only the plain forms of the typed fields are converted (a dict, a list); nothing is computed
        if isinstance(self.recording, dict):
            self.recording = RecordingInfo.from_dict(self.recording)
        self.events = [e if isinstance(e, Event) else Event(*e) for e in self.events]
        if isinstance(self.flags, dict):
            self.flags = Flags.from_dict(self.flags)

    # -- views -----------------------------------------------------------------------------------------------------
    @property
    def selection_params(self) -> Selection:
        """The ``Selection`` (K, threshold, stride, exclusions) this trace's ``selection`` and ``estimate`` use."""
        return Selection(k=self.k, threshold=self.threshold, stride=self.stride, exclude=self.excluded)

    @property
    def selected(self) -> Detections:
        return self.detections[self.selection]

    @property
    def ground_truth(self) -> GroundTruth | None:
        """The recording's ground truth (``meta.json``), None when it has none."""
        return self.recording.ground_truth

    @property
    def ground_truth_mass(self) -> float | None:
        gt = self.ground_truth
        return None if gt is None else gt.mass_g

    def active(self) -> np.ndarray:
        """Boolean mask of detections above the current threshold."""
        return self.detections.score > self.threshold

    def table(self):
        """One row per detection (pandas DataFrame): frame, class, score, box, d, a, b, pred, selected rank."""
        import pandas as pd

        dets = self.detections
        rank = np.full(len(dets), -1)
        rank[self.selection] = np.arange(len(self.selection))
        return pd.DataFrame({
            "frame": dets.frame, "class": dets.class_names(), "score": dets.score,
            "x1": dets.xyxy[:, 0], "y1": dets.xyxy[:, 1], "x2": dets.xyxy[:, 2], "y2": dets.xyxy[:, 3],
            "d_mm": dets.d, "a": dets.a, "b": dets.b, "pred_g": dets.pred,
            "active": self.active(), "rank": rank,
        })

    def running_selections(self) -> list[np.ndarray]:
        """The K nearest detections as they stood after each processed frame (aligned with ``frames``; indices into
        ``detections``, nearest first), with this trace's K, threshold and exclusions: what the running selection of
        ``massviz.core.pipeline.FramePipeline`` held. The last one is ``selection``."""
        dets = self.detections
        nearest = NearestOrder(dets.d, dets.score, self.excluded)  # finite d, not excluded, sorted by d (ties: first)
        order = nearest.order[nearest.score > self.threshold]
        position = {int(f): j for j, f in enumerate(self.frames)}
        processed_at = np.array([position.get(int(f), len(self.frames)) for f in dets.frame[order]], dtype=np.int64)
        return [order[processed_at <= j][: self.k] for j in range(len(self.frames))]

    def running_estimate(self) -> np.ndarray:
        """The estimate as it stood after each processed frame (aligned with ``frames``): the mean prediction of the
        K nearest detections among those of the frames processed so far (``running_selections``; what ``massviz
        live`` shows as ``/predictions/running_estimate``); -1 while none is selected. Its last value is
        ``estimate``."""
        return np.array([estimate_mass(self.detections.pred, sel) for sel in self.running_selections()],
                        dtype=np.float64).reshape(-1)

    def settled_after(self, tolerance: float = 0.10) -> int | None:
        """How many processed frames it took the running estimate to settle: from then on it stays within
        ``tolerance`` (relative) of the final estimate. None when not estimated."""
        if self.estimate < 0 or len(self.frames) == 0:
            return None
        running = self.running_estimate()
        outside = np.flatnonzero((running < 0) | (np.abs(running - self.estimate) > tolerance * abs(self.estimate)))
        return int(outside[-1]) + 2 if len(outside) else 1

    # -- reselection -----------------------------------------------------------------------------------------------
    def reselect(self, k: int | None = None, threshold: float | None = None, exclude=None) -> "Trace":
        """A new trace with the selection and estimate recomputed for another ``k``/``threshold``/exclusion.

        ``threshold`` must be >= the threshold the detector ran at (lower-scored boxes were never kept).
        ``exclude``: detection indices (or a bool mask) never to select; ``None`` keeps the current exclusions.
        """
        k = self.k if k is None else int(k)
        threshold = self.threshold if threshold is None else float(threshold)
        check_not_below_cut(threshold, self.detect_threshold, "this trace")
        if exclude is None:
            excluded = self.excluded
        else:
            ex = np.asarray(exclude)
            excluded = np.flatnonzero(ex) if ex.dtype == bool else ex.astype(np.int64).reshape(-1)
        selection = select_k_nearest(self.detections.d, self.detections.score, k, threshold, excluded)
        estimate = estimate_mass(self.detections.pred, selection)
        events = [e for e in self.events if not e.is_selection]
        events.extend(describe_selection(self.detections, selection, estimate, k, events, threshold=threshold,
                                         detector=str(self.detector.get("name", ""))))
        out = dataclasses.replace(self, k=k, threshold=threshold, selection=selection, estimate=estimate,
                                  excluded=excluded, events=events,
                                  measurements=ranked_measurements(self.measurements, selection), flags=None)
        return analyse_trace(out)


def analyse_trace(trace: Trace) -> Trace:
    """The analysis stages of ``trace``: track ids for detections that have none (``massviz.core.tracks``), then the
    flags of its selection (``massviz.core.flags.analyse``) unless its ``flags`` already describe it
    (``Flags.describes``: the same selection, detections, tracks, threshold, estimate and ground truth). ``trace``
    itself when nothing is missing; else a new trace (``trace`` is not changed)."""
    dets = trace.detections
    if len(dets) and (dets.track <= 0).any():
        dets = dataclasses.replace(dets, track=assign_tracks(dets, trace.recording.fps))
        trace = dataclasses.replace(trace, detections=dets, flags=None)
    if trace.flags is not None and trace.flags.describes(trace):
        return trace
    return dataclasses.replace(trace, flags=analyse(trace))


def frame_results(trace: Trace, frames):
    """The ``FrameResult`` of each of ``frames`` (the trace's processed frames, in order, as a reader yields them),
    made from what ``trace`` holds: its detections of the frame, their patches cut from the frame, the running
    selection and estimate after it and the detections above its threshold. Yields (frame, result): what a sink
    is given for a trace that did not come from a run it observed (a trace from the cache)."""
    dets = trace.detections
    groups = dets.indices_by_frame()
    selections = trace.running_selections()
    estimates = trace.running_estimate()
    position = {int(f): j for j, f in enumerate(trace.frames)}
    active = trace.active()
    for frame in frames:
        j = position[int(frame.index)]
        idx = groups.get(int(frame.index), np.zeros(0, dtype=np.int64))
        offset = int(idx[0]) if len(idx) else int(np.searchsorted(dets.frame, frame.index))
        if len(idx) and not np.array_equal(idx, np.arange(offset, offset + len(idx))):
            raise ValueError("frame_results needs a trace whose detections are in frame order (as the pipeline "
                             "makes them)")
        local = dets[idx]
        yield frame, FrameResult(frame=frame, detections=local, patches=FramePatches(frame.rgb, local.xyxy),
                                 offset=offset, selection=selections[j], running_estimate=float(estimates[j]),
                                 active=np.flatnonzero(active[idx]))


def describe_detection(dets: Detections, i: int) -> str:
    """One detection in a line: class, score, box, d and prediction."""
    return (f"{class_name(dets.class_id[i])} {dets.score[i]:.2f} box {dets.xyxy[i].tolist()} "
            f"d={dets.d[i]:.0f}mm pred={dets.pred[i]:.1f}g")


def describe_selection(dets: Detections, selection: np.ndarray, estimate: float, k: int, events=(), *,
                       threshold: float | None = None, detector: str = "") -> list[Event]:
    """The selection stage's decisions: one ``chosen`` event per patch, then ``estimate`` or ``not_estimated`` (its
    reason from ``massviz.core.selection.not_estimated_reason``, given the recording's other ``events``); the
    estimate's names the score cut used (``threshold``, and whether it is ``detector``'s default)."""
    out = [Event(int(dets.frame[i]), f"chose patch {r} (of K={k}): {describe_detection(dets, i)}", "chosen",
                 "info", int(i)) for r, i in enumerate(selection)]
    last = int(dets.frame.max()) if len(dets) else 0
    if len(selection):
        cut = "" if threshold is None else f" (K={k}, {describe_cut(detector, threshold)})"
        out.append(Event(last, f"estimate {estimate:.1f} g = mean of {len(selection)} patch predictions{cut}",
                         "estimate"))
    else:
        out.append(Event(last, not_estimated_reason(dets, events), "not_estimated", "warn"))
    return out
