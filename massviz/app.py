"""One builder for the pipeline, shared by the CLI, the notebooks and every runner, and ``process``: the per-frame
pipeline (``massviz.core.pipeline``) with the trace cache and the ground truth (both io), above detect and io.

    options = PipelineOptions(detector="depth", k=5)   # threshold None: the detector's default; or .from_args(args)
    pipeline = build_pipeline(options)                                       # detector + mass CNN + trace cache
    trace = pipeline.process(open_recording("data_samples/cup_handover"))    # cached
    fp = pipeline.frame_pipeline(recording.info())                           # the per-frame step, for a runner

Options are plain values (picklable), so a runner can ship them to another process and build the same pipeline
there.
"""
from __future__ import annotations

import contextlib
import dataclasses
import logging
import time
from dataclasses import dataclass
from pathlib import Path

from massviz.core.pipeline import FramePipeline, repredict, resolve_selection, run
from massviz.core.selection import Selection
from massviz.core.trace import Event, analyse_trace
from massviz.core.types import PRECISIONS
from massviz.errors import MassvizError

_LOG = logging.getLogger(__name__)


@dataclass(frozen=True)
class PipelineOptions:
    """Every setting that decides what the pipeline computes (the CLI's pipeline options)."""

    detector: str = "auto"
    #: the score cut; None: the detector's own default (``massviz.core.detector.DEFAULT_THRESHOLDS``)
    threshold: float | None = None
    k: int = 5
    stride: int = 1
    weights: str | None = None
    detector_weights: str | None = None
    replay: str | None = None
    cache: str | None = None
    no_cache: bool = False
    quiet: bool = False
    allow_partial: bool = False  # a video cut short: process what decodes (open_recording(allow_partial=))
    #: frames per detector call; None: the detector's default (1; Mask R-CNN in bf16/fp16 on CUDA: 8). On a CPU
    #: results are equal for any batch.
    batch: int | None = None
    #: where the pipeline computes: auto (CUDA when present, else the CPU), cpu, cuda, cuda:N
    device: str = "auto"
    #: Mask R-CNN arithmetic: fp32 (default, the paper's), bf16 (CPU with bf16 support, CUDA; the mass CNN too) or
    #: fp16 (CUDA; the mass CNN stays fp32).
    precision: str = "fp32"

    def check(self) -> "PipelineOptions":
        """``MassvizError`` naming the option when a value is out of range."""
        if self.threshold is not None and not 0.0 <= self.threshold < 1.0:
            raise MassvizError(f"--threshold must be in [0, 1), got {self.threshold}")
        if self.k < 1:
            raise MassvizError(f"--k must be >= 1, got {self.k}")
        if self.stride < 1:
            raise MassvizError(f"--stride must be >= 1, got {self.stride}")
        if self.batch is not None and self.batch < 1:
            raise MassvizError(f"--batch must be >= 1, got {self.batch}")
        if self.precision not in PRECISIONS:
            raise MassvizError(f"--precision must be one of {', '.join(PRECISIONS)}, got {self.precision!r}")
        return self

    @classmethod
    def from_args(cls, args, **overrides) -> "PipelineOptions":
        """The options from parsed CLI arguments (missing ones keep their defaults), then ``overrides``."""
        names = {f.name for f in dataclasses.fields(cls)}
        values = {n: getattr(args, n) for n in names if getattr(args, n, None) is not None}
        values.update(overrides)
        for n in ("weights", "detector_weights", "replay", "cache"):
            if values.get(n) is not None:
                values[n] = str(values[n])
        return cls(**values)

    def replace(self, **changes) -> "PipelineOptions":
        return dataclasses.replace(self, **changes)

    @property
    def selection(self) -> Selection:
        """The selection these options ask for (K, threshold, stride; no exclusions): what the pipeline is given."""
        return Selection(k=self.k, threshold=self.threshold, stride=self.stride)


@dataclass
class Pipeline:
    """A built pipeline: the detector, the mass CNN and the trace cache (None: no caching), with its options."""

    options: PipelineOptions
    detector: object
    model: object
    cache: object | None

    def process(self, recording, *, exclude=None, progress: bool | None = None, selection: Selection | None = None,
                on_frame=None):
        """The recording's trace, from the cache when there (:func:`process`), selected with ``selection`` (default:
        the options' ``selection``) plus the exclusions ``exclude``; ``on_frame``: the per-frame observer of
        ``massviz.core.pipeline.run`` (not called when the trace comes from the cache)."""
        progress = not self.options.quiet if progress is None else progress
        selection = self.selection if selection is None else selection
        return process(recording, self.detector, self.model, selection=selection, cache=self.cache,
                       progress=progress, exclude=exclude, batch=self.batch, on_frame=on_frame)

    @property
    def selection(self) -> Selection:
        """The selection this pipeline selects with, resolved once here (the edge): the options' K, stride and
        threshold, the detector's own score cut when the options name none (``Selection.at_cut``)."""
        return self.options.selection.at_cut(self.detector.threshold)

    @property
    def threshold(self) -> float:
        """The score cut this pipeline selects with (``selection.threshold``)."""
        return float(self.selection.threshold)

    @property
    def batch(self) -> int:
        """Frames per detector call: ``options.batch``, else the detector's ``default_batch`` (1 without one)."""
        return int(self.options.batch or getattr(self.detector, "default_batch", 1))

    def frame_pipeline(self, recording_info=None) -> FramePipeline:
        """A fresh per-frame step for one recording (live camera, dataset workers, batched runners)."""
        return FramePipeline(self.detector, self.model, selection=self.selection, recording=recording_info)


def process(recording, detector, model, *, selection: Selection | None = None, k: int | None = None,
            stride: int | None = None, cache=None, progress: bool = False, exclude=None, batch: int = 1,
            prefetch: int = 2, annotate=None, on_frame=None):
    """``massviz.core.pipeline.run`` with the trace cache: reuse cached detections when the recording, detector settings and stride match
    and the cached threshold is <= the selection's; re-predict only when the model differs. ``cache`` is a
    ``massviz.io.cache.TraceCache`` or None (no caching). ``selection`` (or ``k=``/``stride=``), ``batch``,
    ``prefetch``: see ``run``; ``exclude`` adds to the selection's exclusions. ``annotate``: a function
    trace -> trace applied to every trace this returns, before a new one is cached; default
    ``massviz.io.ground_truth.with_ground_truth`` (the ground truth's overlaps, for the flags). ``on_frame``: see
    ``run``; called only when the pipeline runs (not for a trace from the cache)."""
    from massviz.io.ground_truth import with_ground_truth

    annotate = annotate or with_ground_truth
    selection = resolve_selection(selection, k, stride).at_cut(detector.threshold)
    if exclude is not None:
        selection = selection.replace(exclude=tuple(selection.exclude) + tuple(Selection(exclude=exclude).exclude))
    k, stride, threshold = selection.k, selection.stride, selection.threshold
    exclude = list(selection.exclude) or None
    info = {"name": detector.name, **detector.settings()}
    trace = cache.load(recording, info, stride, threshold) if cache is not None else None
    if trace is not None:
        t0 = time.perf_counter()
        note = (f"reused cached detections (made at threshold {trace.detect_threshold}); the detector did not run")
        if trace.weights_id != getattr(model, "weights_id", ""):
            trace = repredict(trace, recording, model, progress=progress, detector=detector)
            cache.save(trace, recording, info)
            note += "; predictions recomputed for this model"
        # the key is the frames' content: the recording's path, meta and intrinsics are today's, not the cached run's;
        # annotated with them, then selected and analysed once
        trace = annotate(dataclasses.replace(trace, recording=recording.info()))
        trace = trace.reselect(k=k, threshold=threshold, exclude=exclude)
        events = [e for e in trace.events if not e.is_selection]
        events.append(Event(-1, note, "cache", "debug"))
        events.extend(e for e in trace.events if e.is_selection)
        timings = {"cache": time.perf_counter() - t0}
        return analyse_trace(dataclasses.replace(trace, events=events, timings={**trace.timings, **timings}))
    from massviz.io.identity import LocatedRecording

    if isinstance(recording, LocatedRecording):  # recognised from its files, not opened: only the cache serves it
        raise MassvizError("its cached trace was found when this run started but could not be read now (removed, or "
                           "damaged and dropped); run the command again to compute it", recording.path)
    from massviz.io.identity import changed_inputs, input_identities

    inputs = input_identities(recording)
    # the content key of the bytes the run reads (each frame file read once), not of a second read
    with cache.watch(recording) if cache is not None else contextlib.nullcontext() as read:
        # the cached trace holds every detection (no exclusions): they are applied to the trace returned
        trace = run(recording, detector, model, selection=selection.replace(exclude=()), progress=progress,
                    batch=batch, prefetch=prefetch, on_frame=on_frame, analyse=False)
    trace = analyse_trace(annotate(trace))  # the flags, once, with the ground truth's overlaps
    changed = changed_inputs(inputs)
    if changed:  # whatever the command and the cache: said once, and such a result is never cached
        more = f" and {len(changed) - 1} more" if len(changed) > 1 else ""
        _LOG.warning("massviz: warning: %s: %s%s changed while the run read it; the result may mix two versions of "
                     "the recording and is not cached: run again", recording.path, changed[0], more)
        trace = dataclasses.replace(trace, events=[*trace.events, Event(
            -1, f"input files changed during the run ({changed[0]}{more}); the result may mix two versions",
            "warning", "warn")])
    elif cache is not None:
        cache.save(trace, recording, info, known=read)
    if exclude is not None:
        trace = trace.reselect(exclude=exclude)
    return trace


def build_pipeline(options: PipelineOptions | None = None, **kwargs) -> Pipeline:
    """Build the detector, load the mass CNN and open the trace cache from ``options`` (or keyword options)."""
    from massviz.core.device import resolve_device
    from massviz.detect import make_detector
    from massviz.io.checkpoint import load_checkpoint
    from massviz.io.cache import TraceCache
    from massviz.io.weights import resolve_weights

    options = (options or PipelineOptions()).replace(**kwargs) if kwargs else (options or PipelineOptions())
    options.check()
    device = resolve_device(options.device)
    model = load_checkpoint(resolve_weights(options.weights)).set_precision(options.precision).to(device)
    detector = make_detector(options.detector, options.threshold, detector_weights=options.detector_weights,
                             replay=options.replay, quiet=options.quiet, precision=options.precision,
                             device=device)
    cache = None if options.no_cache else TraceCache(options.cache).check_writable()
    return Pipeline(options, detector, model, cache)


def process_recordings(recordings, options: PipelineOptions | None = None, *, progress: bool = False, **kwargs) -> list:
    """One trace per recording (paths or ``Recording`` objects), from the cache when there: what notebooks call."""
    from massviz.io.recording import open_recording

    pipeline = build_pipeline(options, **kwargs)
    return [pipeline.process(r if not isinstance(r, (str, Path)) else open_recording(r), progress=progress)
            for r in recordings]


__all__ = ["PipelineOptions", "Pipeline", "process", "build_pipeline", "process_recordings", "PRECISIONS"]
