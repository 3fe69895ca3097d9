"""The measure stage: each detection's cleaned cloud (``massviz.measure3d.geometry``), computed once, and the measured
size of every chosen detection (``massviz.core.measurement.Measurement``), for a recording with intrinsics.

The stage observes a run of the pipeline (``on_frame(frame, result)``, the read-only per-frame observer of
``massviz.core.pipeline.run``) or the replay of a finished trace's frames (``replay``), and keeps, for each frame that
holds a detection of the running K nearest, a copy of the frame's RGB and depth and the clouds it already made there
(so at most K frames are held; a frame is dropped when none of its detections is among the K nearest any more).
``finish(trace)`` then measures the chosen detections from those clouds, and ``ply_clouds(trace)`` gives the
clouds ``massviz cloud`` and ``massviz log --ply`` write, making only those not made yet: no cloud is made twice and
no frame is read again. A trace from the cache, whose run was not observed, has its chosen frames read once.

Which clouds a frame gets while it is observed is resolved when the stage is made (``clouds``):

* ``"chosen"``: none until the end (``finish`` and ``ply_clouds`` make the chosen frames' clouds from the kept
  arrays);
* ``"active"``: every detection above the selection's threshold in every frame (a run's ``FrameResult.active``, a
  replayed trace's ``active()``), returned by ``on_frame`` / ``replay`` for a sink that shows them (``massviz log``'s
  Rerun recording).
"""
from __future__ import annotations

import dataclasses
import time
from typing import Iterator

import numpy as np

from massviz.core.measurement import Measurement, ranked_measurements
from massviz.core.trace import Event
from massviz.core.types import Detections, Frame
from massviz.measure3d.settings import BAND_M, DEPTH_TRUNC_M, skip_reason

CLOUDS = ("chosen", "active")


def by_frame(indices, dets: Detections) -> dict[int, list[int]]:
    """{frame: the detection indices of ``indices`` in that frame}, in the order given."""
    out: dict[int, list[int]] = {}
    for i in indices:
        out.setdefault(int(dets.frame[i]), []).append(int(i))
    return out


@dataclasses.dataclass
class _Kept:
    """A frame holding a detection of the running K nearest: its arrays (copies) and the clouds made there."""

    frame: Frame
    clouds: dict = dataclasses.field(default_factory=dict)  # detection index in the trace -> PointCloud


class MeasureStage:
    """The measure stage of one recording (module docstring). ``recording``: what ``massviz.io.recording`` opens
    (its ``intrinsics``; a recording without them gets no cloud and no measurement, ``skip_reason`` says why).
    ``clouds``: ``"chosen"`` or ``"active"``."""

    def __init__(self, recording, *, clouds: str = "chosen", depth_trunc: float = DEPTH_TRUNC_M,
                 band_m: float | None = BAND_M):
        if clouds not in CLOUDS:
            raise ValueError(f"clouds must be one of {', '.join(CLOUDS)}, got {clouds!r}")
        self.recording = recording
        self.skip = skip_reason(recording)
        self.intr = None if self.skip else recording.intrinsics
        self.mode = clouds
        self.depth_trunc, self.band_m = depth_trunc, band_m
        self.frames_seen = 0
        self.seconds = 0.0
        self._kept: dict[int, _Kept] = {}
        self._running: dict[int, int] = {}  # detection of the running K nearest -> its frame

    @property
    def enabled(self) -> bool:
        return self.intr is not None

    def _cloud(self, frame: Frame, dets: Detections, j: int):
        from massviz.measure3d.geometry import detection_cloud

        return detection_cloud(frame, dets, j, self.intr, depth_trunc=self.depth_trunc, band_m=self.band_m)

    def _keep(self, frame: Frame, keep: bool) -> _Kept | None:
        if not keep:
            return None
        arrays = dataclasses.replace(frame, rgb=np.array(frame.rgb, copy=True), depth=np.array(frame.depth, copy=True),
                                     rgb_encoded=None, depth_encoded=None)
        return self._kept.setdefault(frame.index, _Kept(arrays))

    # ------------------------------------------------------------------------------------------------ per frame
    def on_frame(self, frame: Frame, result) -> dict:
        """Observe one step of a run (``result``: its ``FrameResult``); returns {detection index in the trace: cloud}
        of this frame's active detections (``result.active``: above the selection's threshold) in ``"active"`` mode;
        empty for ``"chosen"``."""
        if not self.enabled:
            return {}
        t0 = time.perf_counter()
        self.frames_seen += 1
        dets, offset = result.detections, result.offset
        self._running = {int(g): (frame.index if g >= offset else self._running[int(g)]) for g in result.selection}
        frames_held = set(self._running.values())
        for f in [f for f in self._kept if f not in frames_held]:
            del self._kept[f]
        kept = self._keep(frame, frame.index in frames_held)
        out = {}
        if self.mode == "active":
            for j in result.active:
                out[offset + int(j)] = self._cloud(frame, dets, int(j))
            if kept is not None:
                kept.clouds.update(out)
        self.seconds += time.perf_counter() - t0
        return out

    def replay(self, trace, frame: Frame) -> dict:
        """Observe one processed frame of a finished ``trace`` (its run was not observed, e.g. a trace from the
        cache); returns {detection index: cloud} of its detections above the trace's threshold (``"active"``)."""
        if not self.enabled:
            return {}
        t0 = time.perf_counter()
        self.frames_seen += 1
        dets = trace.detections
        chosen_frames = {int(dets.frame[i]) for i in trace.selection}
        kept = self._keep(frame, frame.index in chosen_frames)
        out = {}
        if self.mode == "active":
            made = self._kept[frame.index].clouds if frame.index in self._kept else {}
            for i in np.flatnonzero((dets.frame == frame.index) & trace.active()):
                out[int(i)] = made[int(i)] if int(i) in made else self._cloud(frame, dets, int(i))
            if kept is not None:
                kept.clouds.update(out)
        self.seconds += time.perf_counter() - t0
        return out

    def replay_frames(self, trace, *, frames=None) -> Iterator[tuple[Frame, dict]]:
        """(frame, its clouds as ``replay`` returns them) for each processed frame of ``trace`` (or ``frames``), each
        read from the recording once."""
        indices = [int(f) for f in (trace.frames if frames is None else frames)]
        for frame in self.recording.frames(indices=indices):
            yield frame, self.replay(trace, frame)

    # ------------------------------------------------------------------------------------------------------ end
    def _frames(self, indices) -> Iterator[_Kept]:
        """The kept frames of ``indices`` (sorted), the others read from the recording once and held from now on."""
        indices = sorted({int(f) for f in indices})
        missing = iter(self.recording.frames(indices=[f for f in indices if f not in self._kept])
                       if any(f not in self._kept for f in indices) else ())
        for f in indices:
            if f not in self._kept:
                self._keep(next(missing), True)
            yield self._kept[f]

    def clouds_of(self, trace, indices) -> dict:
        """{detection: cleaned cloud} of the detections ``indices`` of ``trace``, made only where not made yet."""
        dets = trace.detections
        out = {}
        groups = by_frame(indices, dets)
        for kept in self._frames(groups):
            for i in groups[kept.frame.index]:
                if i not in kept.clouds:
                    kept.clouds[i] = self._cloud(kept.frame, dets, i)
                out[i] = kept.clouds[i]
        return out

    def measurements(self, trace) -> list[Measurement]:
        """The measured size of each chosen detection of ``trace`` (``trace.selection``, nearest first), those the
        trace already holds reused; detections whose cloud has fewer than 10 points have none."""
        if not self.enabled:
            return []
        rank_of = {int(i): r for r, i in enumerate(trace.selection)}
        default = self.depth_trunc == DEPTH_TRUNC_M and self.band_m == BAND_M
        have = ranked_measurements(trace.measurements, trace.selection) if default else []
        done = {m.detection for m in have}
        clouds = self.clouds_of(trace, [int(i) for i in trace.selection if int(i) not in done])
        if clouds:
            from massviz.measure3d.geometry import measure_cloud_as
        out = list(have)
        for i, pcd in clouds.items():
            m = measure_cloud_as(pcd, rank=rank_of[i], detection=i, frame=int(trace.detections.frame[i]))
            if m is not None:
                out.append(m)
        return sorted(out, key=lambda m: m.rank)

    def finish(self, trace):
        """``trace`` with ``measurements`` and the stage's wall time (``timings["measure3d"]``: the clouds made while
        observing and the measuring); ``trace`` itself for a recording without intrinsics."""
        t0 = time.perf_counter()
        if not self.enabled:
            return trace
        ms = self.measurements(trace)
        seconds = self.seconds + time.perf_counter() - t0
        return dataclasses.replace(trace, measurements=ms, timings={**trace.timings, "measure3d": seconds})

    def ply_clouds(self, trace, *, frames=None) -> Iterator[tuple[str, object]] | None:
        """(file name, cloud) of what ``massviz cloud`` writes: for each frame of ``frames`` (default: the frames of
        the chosen detections) ``scene_<frame>.ply`` (the whole frame), ``detection_<id>.ply`` for each of its
        detections above the trace's threshold and ``chosen_<rank>.ply`` for the chosen ones; None for a recording
        without intrinsics."""
        return self._ply_clouds(trace, frames) if self.enabled else None

    def _ply_clouds(self, trace, frames) -> Iterator[tuple[str, object]]:
        dets = trace.detections
        rank_of = {int(i): r for r, i in enumerate(trace.selection)}
        from massviz.measure3d.geometry import scene_cloud

        if frames is None:
            frames = sorted({int(dets.frame[i]) for i in trace.selection})
        wanted = {int(f) for f in frames}
        groups = by_frame([i for i in np.flatnonzero(trace.active()) if int(dets.frame[i]) in wanted], dets)
        for kept in self._frames(wanted):
            f = kept.frame.index
            yield f"scene_{f:06d}.ply", scene_cloud(kept.frame, self.intr, depth_trunc=self.depth_trunc)
            for i in groups.get(f, []):
                if i not in kept.clouds:
                    kept.clouds[i] = self._cloud(kept.frame, dets, i)
                yield f"detection_{i}.ply", kept.clouds[i]
                if i in rank_of:
                    yield f"chosen_{rank_of[i]}.ply", kept.clouds[i]
            if f not in {int(dets.frame[i]) for i in trace.selection}:
                del self._kept[f]  # a frame asked for beyond the chosen ones (--all-frames) is not held


def with_measurements(trace, recording, **kw):
    """``trace`` measured by a ``MeasureStage`` of its own (reading the chosen frames), with an event per measured
    patch, or one saying why a recording without intrinsics has none. Returns (trace, stage): the stage holds the
    chosen frames' clouds for the views and files that show them."""
    stage = MeasureStage(recording, **kw)
    measured = stage.finish(trace)
    events = list(measured.events)
    if stage.skip:
        events.append(Event(-1, stage.skip, "warning", "warn"))
    for m in measured.measurements:
        events.append(Event(m.frame, f"measured chosen patch {m.rank} (detection {m.detection}): height "
                                     f"{m.height_mm:.0f} mm, width {m.width_mm:.0f} mm, depth {m.depth_mm:.0f} mm "
                                     f"from {m.n_points} points", "measured", "info", m.detection))
    if not stage.enabled:
        measured = dataclasses.replace(measured, timings={**measured.timings, "measure3d": 0.0})
    return dataclasses.replace(measured, events=events), stage


def measured_replay(trace, recording):
    """(``trace`` measured, its processed frames with each detection's cloud): what a sink that logs a finished trace
    with its clouds is given (``massviz.views.rerun.log_trace_with_clouds``' ``frames``). The chosen frames are read
    first (to measure), then every processed frame once; no cloud is made twice."""
    stage = MeasureStage(recording, clouds="active")
    trace = stage.finish(trace)
    return trace, (stage.replay_frames(trace) if stage.enabled else None)


__all__ = ["CLOUDS", "MeasureStage", "by_frame", "with_measurements", "measured_replay"]
