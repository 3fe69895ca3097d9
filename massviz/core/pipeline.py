"""The paper's pipeline, one frame at a time, every stage timed into a ``Trace``.

Stages, per processed frame (every ``stride``-th): **read** the RGB-D frame, **detect** containers, compute the
**features** (d, a, b) of every detection, **predict** the mass of every detection's patch with the mass CNN, and
**select** the K nearest detections seen so far (the running estimate); each frame's detections are also linked to
the object tracks of the earlier frames (``massviz.core.tracks.Tracker``; ``detections.track``). After the last frame
the selection's **flags** are analysed (``massviz.core.flags``: chosen patches that are probably not the container).
``FramePipeline`` holds that running state:

    fp = FramePipeline(detector, model, selection=Selection(k=5, threshold=0.4))
    for frame in recording.frames():
        result = fp.step(frame)          # this frame's detections, the K nearest so far, the running estimate
    trace = fp.finish()                  # the whole recording's Trace

Every runner calls the same step: ``run`` (a loop over a recording, below), the dataset runners, the live camera,
batched detection (``step(frame, detections=...)`` when a batched detector already ran on the frame).

The selection's settings travel as one explicit ``massviz.core.selection.Selection`` (K, threshold, stride,
exclusions) into ``FramePipeline`` and the ``Trace``; the detector keeps only its own score cut (``detect_threshold``
in the trace). ``step`` never changes the detector's ``Detections``: features, tracks and predictions are new arrays.

Predicting every detection (not only the K chosen) costs little next to detection and makes re-selection for any
K, threshold or exclusion instant (notebook sliders, sweeps). Frames are streamed; only the ``keep_patches`` nearest
RGB patches are held, so memory does not grow with the recording's length beyond the small per-detection arrays.
"""
from __future__ import annotations

import dataclasses
import inspect
import math
import sys
import time
from collections import defaultdict

import numpy as np
from tqdm.auto import tqdm

from massviz.core.detector import Detector, detector_info
from massviz.core.frame_stage import FramePatches, FrameStage, StagedFrame, predictable
from massviz.core.prefetch import Prefetcher
from massviz.core.selection import REJECTED_PREFIX, Selection, estimate_mass, select_k_nearest
from massviz.core.trace import Event, FrameResult, Trace, analyse_trace, describe_detection, describe_selection
from massviz.core.tracks import Tracker
from massviz.core.types import Detections, Frame, RecordingInfo, Rejection

#: how many of the nearest detections keep their RGB patch in the trace (>= any K you will reselect with).
KEEP_PATCHES = 32


def predict_detections(model, rgb: np.ndarray, dets: Detections,
                       kernels: str = "exact") -> tuple[np.ndarray, FramePatches]:
    """Mass prediction (g) for every detection with a finite d and a non-empty box; NaN for the others.
    ``kernels``: ``exact`` (patches cut and resized on the host, ``model.predict``) or ``device`` (on the model's
    device, as ``FrameStage``'s device kernels: ``MassPredictor.predict_boxes``)."""
    from massviz.core.frame_stage import _check_finite

    pred = np.full(len(dets), np.nan, dtype=np.float32)
    patches = FramePatches(rgb, dets.xyxy)
    ok = predictable(dets)
    if len(ok):
        feats = np.stack([dets.a[ok], dets.b[ok], dets.d[ok]], axis=1)
        if kernels == "device":
            pred[ok] = model.predict_boxes(rgb, dets.xyxy[ok], feats)
        else:
            pred[ok] = model.predict([patches[i] for i in ok], feats)
        _check_finite(model, pred[ok])
    return pred, patches


class _NearestPatches:
    """Keeps the RGB patches of the ``n`` nearest detections seen so far (ties: the earliest wins)."""

    def __init__(self, n: int):
        self.n, self.patches = n, {}
        self._index, self._d = np.zeros(0, np.int64), np.zeros(0)

    def offer(self, offset: int, d: np.ndarray, patches) -> None:
        """A frame's detections, global indices ``offset + i`` at distances ``d`` (NaN: none), their patches
        ``patches[i]`` (read only for those kept)."""
        d = np.asarray(d, dtype=np.float64)
        local = np.flatnonzero(np.isfinite(d))
        if self.n <= 0 or not len(local):
            return
        index = np.concatenate([self._index, offset + local])
        dist = np.concatenate([self._d, d[local]])
        keep = np.sort(np.lexsort((index, dist))[:self.n])  # the n nearest, ties to the earliest; in index order
        self._index, self._d = index[keep], dist[keep]
        for gone in set(self.patches) - set(self._index.tolist()):
            del self.patches[gone]
        for i in self._index[self._index >= offset].tolist():
            self.patches[i] = patches[i - offset]


def resolve_selection(selection: Selection | None, k: int | None, stride: int | None,
                      cut: float | None = None) -> Selection:
    """``selection``, or one made of the shorthand ``k``/``stride`` (not both); with ``cut`` (the detector's score
    cut) resolved for it (``Selection.for_cut``: a selection resolved for that cut at the edge is used as it is)."""
    if selection is None:
        selection = Selection(k=5 if k is None else k, stride=1 if stride is None else stride)
    elif k is not None or stride is not None:
        raise ValueError("pass either selection= or k=/stride=, not both")
    return selection if cut is None else selection.for_cut(cut)


class FramePipeline:
    """The per-frame step of the pipeline, holding the running nearest-K state of one recording.

    ``selection``: the K, threshold, stride and exclusions to select with (``Selection``; ``k=``/``stride=`` are a
    shorthand for ``Selection(k, stride=stride)``), resolved for the detector's score cut unless the edge did
    (``Selection.for_cut``): a selection without a threshold selects at the cut; one below it is refused (those
    detections were never kept).

    Measured sizes (point clouds, Open3D) are not a step of this pipeline: the optional measure stage
    (``massviz.measure3d.stage.MeasureStage``) observes the steps' results and fills ``Trace.measurements``.
    """

    def __init__(self, detector: Detector, model, *, selection: Selection | None = None, k: int | None = None,
                 stride: int | None = None, recording: RecordingInfo | None = None,
                 keep_patches: int = KEEP_PATCHES, stage: FrameStage | None = None):
        self.detect_threshold = float(detector.threshold)  # the detector's own cut, recorded in the trace
        self.selection = selection = resolve_selection(selection, k, stride, self.detect_threshold)
        self.detector, self.model = detector, model
        self.stage = stage if stage is not None else FrameStage(detector, model)
        self.k, self.stride = selection.k, selection.stride
        self._exclude = np.asarray(selection.exclude, dtype=np.int64)
        self.recording = recording
        self.timings: dict[str, float] = defaultdict(float)
        self.events: list[Event] = []
        self._parts: list[Detections] = []
        self._frames: list[int] = []
        self._nearest = _NearestPatches(max(keep_patches, self.k))
        self._offset = 0
        self._frame_timings: dict[str, list[float]] = defaultdict(list)
        # the running selection: the K nearest so far (global indices, their d and predictions). The K nearest of
        # the recording so far are the K nearest of (the previous K nearest + this frame's detections), ties to the
        # earliest: a frame's detections come after every earlier one, so a stable merge keeps the paper's order.
        self._sel = np.zeros(0, dtype=np.int64)
        self._sel_d = np.zeros(0)
        self._sel_pred = np.zeros(0)
        self._start = time.perf_counter()
        self._tracker = Tracker(recording.fps if recording is not None else None)

    @property
    def frames_done(self) -> int:
        return len(self._frames)

    def step(self, frame: Frame, *, staged: StagedFrame | None = None, read_seconds: float = 0.0) -> FrameResult:
        """Run detect, features and predict on one frame (``self.stage``), unless ``staged`` holds what a
        ``FrameStage`` already computed for it (a batch of frames, possibly on a GPU), then the tracks and the
        running selection."""
        if staged is None:
            staged = self.stage.process([frame], [read_seconds])[0]
        dets = staged.detections
        t3 = time.perf_counter()
        dets.track = self._tracker.update(frame.index, dets)
        t_track = time.perf_counter() - t3
        patches = staged.patches
        events = [Event(frame.index, f"{REJECTED_PREFIX}{note}", "skipped", "info",
                        reason=note.reason if isinstance(note, Rejection) else str(note))
                  for note in staged.notes]
        offset = self._offset
        for i in np.flatnonzero(~np.isfinite(dets.d)):
            events.append(Event(frame.index, f"skipped {describe_detection(dets, int(i))}: its mask has no depth",
                                "skipped", "warn", offset + int(i)))
        self._nearest.offer(offset, dets.d, patches)
        self._frames.append(frame.index)
        self._parts.append(dets)
        self._offset += len(dets)
        t4 = time.perf_counter()
        selection, running = self._update_selection(dets, offset)
        t5 = time.perf_counter()
        timings = {"read": staged.timings.get("read", read_seconds), "detect": staged.timings.get("detect", 0.0),
                   "features": staged.timings.get("features", 0.0) + t_track,
                   "predict": staged.timings.get("predict", 0.0), "select": t5 - t4}
        for name, seconds in timings.items():
            self._frame_timings[name].append(seconds)
            if name != "select":  # the whole recording's selection is timed in finish()
                self.timings[name] += seconds
        self.events.extend(events)
        return FrameResult(frame=frame, detections=dets, patches=patches, offset=offset, selection=selection,
                           running_estimate=running, timings=timings, events=events,
                           active=np.flatnonzero(dets.score > self.selection.threshold))

    def _update_selection(self, dets: Detections, offset: int) -> tuple[np.ndarray, float]:
        local = self._exclude[(self._exclude >= offset) & (self._exclude < offset + len(dets))] - offset
        new = select_k_nearest(dets.d, dets.score, self.k, self.selection.threshold, local)
        idx = np.concatenate([self._sel, offset + new])
        d = np.concatenate([self._sel_d, dets.d[new]])
        pred = np.concatenate([self._sel_pred, dets.pred[new].astype(np.float64)])
        keep = select_k_nearest(d, np.ones(len(d)), self.k, 0.0)  # already above the threshold, finite d
        self._sel, self._sel_d, self._sel_pred = idx[keep], d[keep], pred[keep]
        return self._sel.copy(), estimate_mass(self._sel_pred, np.arange(len(keep)))

    def finish(self, analyse: bool = True) -> Trace:
        """The recording's ``Trace``: every detection (tracked as the frames were processed), the K nearest, the
        estimate, the decisions, stage times and, with ``analyse``, the flags of the selection
        (``massviz.core.trace.analyse_trace``; off for a caller that adds the ground truth's overlaps first and then
        analyses once)."""
        detections = Detections.concat(self._parts)
        for i, patch in self._nearest.patches.items():
            detections.patches[i] = patch
        t5 = time.perf_counter()
        excluded = self._exclude[self._exclude < len(detections)]
        selection = select_k_nearest(detections.d, detections.score, self.k, self.selection.threshold, excluded)
        estimate = estimate_mass(detections.pred, selection)
        timings = dict(self.timings)
        timings["select"] = time.perf_counter() - t5
        timings["total"] = time.perf_counter() - self._start
        events = [*self.events, *describe_selection(detections, selection, estimate, self.k, self.events,
                                                    threshold=self.selection.threshold, detector=self.detector.name)]
        info = self.recording if self.recording is not None else RecordingInfo(id="live")
        trace = Trace(recording=info, detector=detector_info(self.detector),
                     detect_threshold=self.detect_threshold, threshold=self.selection.threshold,
                     k=self.k, stride=self.stride, frames=np.asarray(self._frames, dtype=np.int32),
                     detections=detections, selection=selection, estimate=estimate, excluded=excluded,
                     weights_id=getattr(self.model, "weights_id", ""), timings=timings, events=events,
                     frame_timings={n: np.asarray(v) for n, v in self._frame_timings.items()},
                     compute=self.stage.describe())
        return analyse_trace(trace) if analyse else trace


def run(recording, detector: Detector, model, *, selection: Selection | None = None, k: int | None = None,
        stride: int | None = None, keep_patches: int = KEEP_PATCHES, progress: bool = False, batch: int = 1,
        prefetch: int = 2, on_frame=None, kernels: str = "auto",
        overlap: bool | None = None, analyse: bool = True) -> Trace:
    """Run the pipeline over ``recording`` (a loop over ``FramePipeline.step``) and select as ``selection`` says
    (``k=``/``stride=``: shorthand, see ``FramePipeline``).

    ``batch``: frames per detector call, their patches predicted by the mass CNN together
    (``massviz.core.frame_stage.FrameStage``); ``kernels``: the stage's kernels (``auto``: ``device`` when the mass CNN is
    on a CUDA GPU, else ``exact``). ``prefetch``: frames read ahead in a background thread
    (``massviz.core.prefetch.Prefetcher``, at least ``batch``; 0 reads in this thread); it never changes the result;
    the ``read`` timing is then the time spent waiting for frames. ``overlap``: the stage in a thread of its own, a
    batch ahead of the selection (default: on CUDA).

    ``on_frame(frame, result)``: a read-only observer called after each frame's step with the ``Frame`` (its arrays
    and, when the format has them, the bytes the reader read) and the ``FrameResult``, e.g. a sink logging each frame
    as it is processed so that no frame is read twice (``massviz log``). It must not change either; its time is not
    charged to any stage (the measure stage, ``massviz.measure3d.stage.MeasureStage``, is such an observer).
    ``analyse``: the flags (``FramePipeline.finish``).
    """
    stage = FrameStage(detector, model, batch=batch, kernels=kernels, overlap=overlap)
    fp = FramePipeline(detector, model, selection=selection, k=k, stride=stride, recording=recording.info(),
                       keep_patches=keep_patches, stage=stage)
    stride = fp.stride
    total = math.ceil(recording.num_frames / stride)
    bar = tqdm(total=total, desc=f"{recording.id}", unit="frame", file=sys.stderr, disable=not progress,
               leave=False)
    workers = stage.read_workers if "workers" in inspect.signature(recording.frames).parameters else 1
    frames = recording.frames(stride=stride, **({"workers": workers} if workers > 1 else {}))
    if prefetch > 0:
        frames = Prefetcher(frames, size=max(int(prefetch), int(batch)), prepare=stage.prepare)
    staged = stage.stream(frames)
    if stage.overlap:
        staged = Prefetcher(staged, size=2 * batch)
    # the faithful settings once for the whole run, the stage's thread included (closed before they are left)
    with stage.faithful():
        try:  # the bar is cleared before any error is reported, so the error line stands alone
            for item in staged:
                result = fp.step(item.frame, staged=item)
                if on_frame is not None:
                    on_frame(item.frame, result)
                bar.update(1)
        finally:
            bar.close()
            for it in (staged, frames):
                if isinstance(it, Prefetcher):
                    it.close()
    fp.events.extend(Event(-1, note, "warning", "warn") for note in getattr(recording, "notes", ()))
    return fp.finish(analyse=analyse)


def repredict(trace: Trace, recording, model, progress: bool = False, *, detector: Detector | None = None,
              kernels: str = "auto") -> Trace:
    """Recompute every detection's prediction with another model (re-reads the frames that have detections), in
    the settings a run of that model computes in (a ``FrameStage`` of ``detector`` and ``model``, which detects
    nothing here): its kernels (``auto``: ``device`` when the model is on a CUDA GPU) inside the run's faithful
    settings (``FrameStage.faithful``: the run's ``--precision`` is the detector's, without a detector the
    model's). ``compute`` records it: ``predict_device``, ``predict_kernels``, ``predict_precision`` and
    ``predict_mode`` say where and how the predictions were recomputed, and ``mode`` is ``faithful`` only when both
    the detections and the predictions are."""
    stage = FrameStage(detector, model, kernels=kernels)
    dets = trace.detections
    pred = np.full(len(dets), np.nan, dtype=np.float32)
    by_frame = dets.indices_by_frame()
    with stage.faithful():
        for frame in tqdm(recording.frames(indices=list(by_frame)), total=len(by_frame), disable=not progress,
                          file=sys.stderr, desc=f"{recording.id} re-predict", leave=False):
            idx = by_frame[frame.index]
            pred[idx], _ = predict_detections(model, frame.rgb, dets[idx], stage.kernels)
    new = Detections(**{n: getattr(dets, n) for n in Detections._ARRAYS if n != "pred"}, pred=pred,
                     masks=dets.masks, patches=dets.patches)
    predicted = stage.describe()
    compute = {**trace.compute, **{f"predict_{k}": predicted[k] for k in ("device", "kernels", "precision", "mode")}}
    if "mode" in trace.compute:
        both = trace.compute["mode"] == predicted["mode"] == "faithful"
        compute["mode"] = "faithful" if both else "fast"
    out = dataclasses.replace(trace, detections=new, weights_id=getattr(model, "weights_id", ""), compute=compute)
    return out.reselect()


__all__ = ["FramePipeline", "FrameResult", "KEEP_PATCHES", "predict_detections", "run", "repredict",
           "resolve_selection"]
