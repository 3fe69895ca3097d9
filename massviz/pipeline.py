"""The paper's pipeline over one recording, every stage timed into a ``Trace``.

Stages, per processed frame (every ``stride``-th): **read** the RGB-D frame, **detect** containers, compute the
**features** (d, a, b) of every detection, **predict** the mass of every detection's patch with the mass CNN. Then,
over the whole recording: **select** the K nearest detections and average their predictions (the **estimate**).

Predicting every detection (not only the K chosen) costs little next to detection and makes re-selection for any
K, threshold or exclusion instant (notebook sliders, sweeps). Frames are streamed; only the ``keep_patches`` nearest
RGB patches are held, so memory does not grow with the recording's length beyond the small per-detection arrays.
"""
from __future__ import annotations

import dataclasses
import heapq
import math
import sys
import time
from collections import defaultdict

import numpy as np
from tqdm.auto import tqdm

from massviz.detect.base import Detector
from massviz.recording import Recording
from massviz.selection import compute_features, estimate_mass, select_k_nearest
from massviz.trace import Trace, describe_detection, describe_selection, is_selection_event
from massviz.types import Detections

#: how many of the nearest detections keep their RGB patch in the trace (>= any K you will reselect with).
KEEP_PATCHES = 32


def crop(rgb: np.ndarray, xyxy) -> np.ndarray:
    """The RGB patch of a box (x2/y2 exclusive), as the paper's code crops it."""
    x1, y1, x2, y2 = (int(v) for v in xyxy)
    return np.ascontiguousarray(rgb[y1:y2, x1:x2])


def predict_detections(model, rgb: np.ndarray, dets: Detections) -> tuple[np.ndarray, list]:
    """Mass prediction (g) for every detection with a finite d and a non-empty box; NaN for the others."""
    pred = np.full(len(dets), np.nan, dtype=np.float32)
    patches = [crop(rgb, box) for box in dets.xyxy]
    ok = [i for i in range(len(dets)) if np.isfinite(dets.d[i]) and patches[i].size]
    if ok:
        feats = np.stack([dets.a[ok], dets.b[ok], dets.d[ok]], axis=1)
        pred[ok] = model.predict([patches[i] for i in ok], feats)
    return pred, patches


class _NearestPatches:
    """Keeps the RGB patches of the ``n`` nearest detections seen so far (ties: the earliest wins)."""

    def __init__(self, n: int):
        self.n, self.heap, self.patches = n, [], {}

    def offer(self, index: int, d: float, patch: np.ndarray) -> None:
        if not np.isfinite(d) or self.n <= 0:
            return
        heapq.heappush(self.heap, (-d, -index))
        self.patches[index] = patch
        if len(self.heap) > self.n:
            _, neg = heapq.heappop(self.heap)
            self.patches.pop(-neg, None)


def run(recording: Recording, detector: Detector, model, *, k: int = 5, stride: int = 1,
        keep_patches: int = KEEP_PATCHES, progress: bool = False) -> Trace:
    """Run detection, features and prediction over ``recording`` and select the ``k`` nearest patches."""
    timings: dict[str, float] = defaultdict(float)
    events: list[tuple[int, str]] = []
    parts: list[Detections] = []
    frames: list[int] = []
    nearest = _NearestPatches(max(keep_patches, k))
    offset = 0
    total = math.ceil(recording.num_frames / stride)
    bar = tqdm(total=total, desc=f"{recording.id}", unit="frame", file=sys.stderr, disable=not progress,
               leave=False)
    t_start = time.perf_counter()
    t0 = time.perf_counter()
    try:  # the bar is cleared before any error is reported, so the error line stands alone
        for frame in recording.frames(stride=stride):
            t1 = time.perf_counter()
            timings["read"] += t1 - t0
            dets = detector.detect(frame)
            t2 = time.perf_counter()
            compute_features(dets, frame.depth)
            t3 = time.perf_counter()
            dets.pred, patches = predict_detections(model, frame.rgb, dets)
            t4 = time.perf_counter()
            timings["detect"] += t2 - t1
            timings["features"] += t3 - t2
            timings["predict"] += t4 - t3
            for i in range(len(dets)):
                if not np.isfinite(dets.d[i]):
                    events.append((frame.index, f"skipped {describe_detection(dets, i)}: its mask has no depth"))
                nearest.offer(offset + i, float(dets.d[i]), patches[i])
            frames.append(frame.index)
            parts.append(dets)
            offset += len(dets)
            bar.update(1)
            t0 = time.perf_counter()
    finally:
        bar.close()
    detections = Detections.concat(parts)
    for i, patch in nearest.patches.items():
        detections.patches[i] = patch

    t5 = time.perf_counter()
    selection = select_k_nearest(detections.d, detections.score, k, detector.threshold)
    estimate = estimate_mass(detections.pred, selection)
    timings["select"] = time.perf_counter() - t5
    timings["total"] = time.perf_counter() - t_start
    events.extend(describe_selection(detections, selection, estimate, k))
    return Trace(recording=recording.info(), detector={"name": detector.name, **detector.settings()},
                 detect_threshold=float(detector.threshold), threshold=float(detector.threshold), k=k,
                 stride=stride, frames=np.asarray(frames, dtype=np.int32), detections=detections,
                 selection=selection, estimate=estimate, weights_id=getattr(model, "weights_id", ""),
                 timings=dict(timings), events=events)


def repredict(trace: Trace, recording: Recording, model, progress: bool = False) -> Trace:
    """Recompute every detection's prediction with another model (re-reads the frames that have detections)."""
    dets = trace.detections
    pred = np.full(len(dets), np.nan, dtype=np.float32)
    by_frame = defaultdict(list)
    for i, f in enumerate(dets.frame):
        by_frame[int(f)].append(i)
    for frame in tqdm(recording.frames(indices=list(by_frame)), total=len(by_frame), disable=not progress,
                      file=sys.stderr, desc=f"{recording.id} re-predict", leave=False):
        idx = by_frame[frame.index]
        pred[idx], _ = predict_detections(model, frame.rgb, dets[idx])
    new = Detections(**{n: getattr(dets, n) for n in Detections._ARRAYS if n != "pred"}, pred=pred,
                     masks=dets.masks, patches=dets.patches)
    out = dataclasses.replace(trace, detections=new, weights_id=getattr(model, "weights_id", ""))
    return out.reselect()


def process(recording: Recording, detector: Detector, model, *, k: int = 5, stride: int = 1, cache=None,
            progress: bool = False, exclude=None) -> Trace:
    """``run`` with the trace cache: reuse cached detections when the recording, detector settings and stride match
    and the cached threshold is <= this one; re-predict only when the model differs. ``cache`` is a
    ``massviz.cache.TraceCache`` or None (no caching)."""
    info = {"name": detector.name, **detector.settings()}
    trace = cache.load(recording, info, stride, detector.threshold) if cache is not None else None
    if trace is not None:
        t0 = time.perf_counter()
        note = (f"reused cached detections (made at threshold {trace.detect_threshold}); the detector did not run")
        if trace.weights_id != getattr(model, "weights_id", ""):
            trace = repredict(trace, recording, model, progress=progress)
            cache.save(trace, recording, info)
            note += "; predictions recomputed for this model"
        trace = trace.reselect(k=k, threshold=detector.threshold, exclude=exclude)
        events = [e for e in trace.events if not is_selection_event(e)]
        events.append((-1, note))
        events.extend(e for e in trace.events if is_selection_event(e))
        timings = {"cache": time.perf_counter() - t0}
        return dataclasses.replace(trace, events=events, timings={**trace.timings, **timings})
    trace = run(recording, detector, model, k=k, stride=stride, progress=progress)
    if cache is not None:
        cache.save(trace, recording, info)
    if exclude is not None:
        trace = trace.reselect(exclude=exclude)
    return trace
