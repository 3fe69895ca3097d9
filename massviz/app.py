"""One builder for the pipeline, shared by the CLI, the notebooks and every runner, and ``process``: the per-frame
pipeline (``massviz.core.pipeline``) with the trace cache and the ground truth (both io), above detect and io.

    options = PipelineOptions(detector="depth", k=5)   # threshold None: the detector's default; or .from_args(args)
    pipeline = build_pipeline(options)                                       # detector + mass CNN + trace cache
    trace = pipeline.process(open_recording("data_samples/cup_handover"))    # cached
    fp = pipeline.frame_pipeline(recording.info())                           # the per-frame step, for a runner

Options are plain values (picklable), so a runner can ship them to another process and build the same pipeline
there. The pipeline's ``selection`` (K, threshold, stride) is resolved once, when it is made, and carried to every
stage. A pipeline built once is remembered (``Pipeline.memory``); ``Pipeline.from_memory`` makes it again without
building anything, to serve traces from the cache (the dataset commands' warm path, ``massviz.commands._warm``).
"""
from __future__ import annotations

import contextlib
import dataclasses
import logging
import time
import typing
from dataclasses import dataclass, field
from pathlib import Path

from massviz.core.detector import detector_info
from massviz.core.pipeline import FramePipeline, repredict, resolve_selection, run
from massviz.core.selection import Selection
from massviz.core.trace import Event, analyse_trace
from massviz.core.types import PRECISIONS
from massviz.errors import MassvizError

_LOG = logging.getLogger(__name__)


#: the metadata of a ``PipelineOptions`` field that is a setting of a run (``PipelineOptions.setting_types``)
_SETTING = {"setting": True}


@dataclass(frozen=True)
class PipelineOptions:
    """Every setting that decides what the pipeline computes (the CLI's pipeline options). The fields marked as
    settings (``setting_types()``) are those a run records and ``massviz compare --a/--b`` may set."""

    detector: str = field(default="auto", metadata=_SETTING)
    #: the score cut; None: the detector's own default (``massviz.core.detector.DEFAULT_THRESHOLDS``)
    threshold: float | None = field(default=None, metadata=_SETTING)
    k: int = field(default=5, metadata=_SETTING)
    stride: int = field(default=1, metadata=_SETTING)
    weights: str | None = field(default=None, metadata=_SETTING)
    detector_weights: str | None = field(default=None, metadata=_SETTING)
    #: Mask R-CNN arithmetic: fp32 (default, the paper's), bf16 (CPU with bf16 support, CUDA; the mass CNN too) or
    #: fp16 (CUDA; the mass CNN stays fp32).
    precision: str = field(default="fp32", metadata=_SETTING)
    replay: str | None = field(default=None, metadata=_SETTING)
    cache: str | None = None
    no_cache: bool = False
    quiet: bool = False
    allow_partial: bool = False  # a video cut short: process what decodes (open_recording(allow_partial=))
    #: frames per detector call; None: the detector's default (1; Mask R-CNN in bf16/fp16 on CUDA: 8). On a CPU
    #: results are equal for any batch.
    batch: int | None = None
    #: where the pipeline computes: auto (CUDA when present, else the CPU), cpu, cuda, cuda:N
    device: str = "auto"

    def check(self) -> "PipelineOptions":
        """``MassvizError`` naming the option when a value is out of range (threshold, K and stride:
        ``Selection.check``)."""
        try:
            for name in ("threshold", "k", "stride"):
                if getattr(self, name) is not None:
                    Selection.check(name, getattr(self, name), f"--{name}")
        except ValueError as err:
            raise MassvizError(str(err)) from None
        if self.batch is not None and self.batch < 1:
            raise MassvizError(f"--batch must be >= 1, got {self.batch}")
        if self.precision not in PRECISIONS:
            raise MassvizError(f"--precision must be one of {', '.join(PRECISIONS)}, got {self.precision!r}")
        return self

    @classmethod
    def setting_types(cls) -> dict:
        """{name: type} of the fields that are settings of a run (detector, threshold, K, stride, weights, detector
        weights, precision, replay), in field order; the type reads a setting from text (``str``, ``float``,
        ``int``)."""
        hints = typing.get_type_hints(cls)
        out = {}
        for f in dataclasses.fields(cls):
            if f.metadata.get("setting"):
                types = [t for t in typing.get_args(hints[f.name]) if t is not type(None)] or [hints[f.name]]
                out[f.name] = types[0]
        return out

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

    def memory_key(self) -> dict:
        """What decides the detector's settings and the mass CNN's id (every option but threshold, K, stride and the
        cache; paths absolute): the key a built pipeline's ``memory`` is remembered by."""
        import os

        from massviz.io.weights import ENV_WEIGHTS

        def absolute(p):
            return None if p is None else str(Path(p).expanduser().resolve())

        weights = self.weights if self.weights is not None else (os.environ.get(ENV_WEIGHTS) or None)
        return {"detector": self.detector, "detector_weights": absolute(self.detector_weights),
                "replay": absolute(self.replay), "precision": self.precision, "weights": absolute(weights),
                "device": self.device}


@dataclass
class Pipeline:
    """A built pipeline: the detector, the mass CNN and the trace cache (None: no caching), with its options, and
    the ``selection`` it selects with, resolved once when it is made: the options' K, stride and threshold, the
    detector's own score cut when the options name none (``Selection.at_cut``)."""

    options: PipelineOptions
    detector: object
    model: object
    cache: object | None
    selection: Selection = field(init=False)

    def __post_init__(self) -> None:
        self.selection = self.options.selection.at_cut(self.detector.threshold)

    def process(self, recording, *, exclude=None, progress: bool | None = None, selection: Selection | None = None,
                on_frame=None):
        """The recording's trace, from the cache when there (:func:`process`), selected with ``selection`` (default:
        the pipeline's ``selection``) plus the exclusions ``exclude``; ``on_frame``: the per-frame observer of
        ``massviz.core.pipeline.run`` (not called when the trace comes from the cache)."""
        progress = not self.options.quiet if progress is None else progress
        selection = self.selection if selection is None else selection
        return process(recording, self.detector, self.model, selection=selection, cache=self.cache,
                       progress=progress, exclude=exclude, batch=self.batch, on_frame=on_frame)

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

    def memory(self) -> dict:
        """What the options resolved to, for :meth:`from_memory` (JSON): the detector's name, settings and default
        score cut, the mass CNN's ``weights_id``."""
        return {"name": self.detector.name, "settings": self.detector.settings(),
                "default_threshold": float(self.detector.default_threshold),
                "weights_id": getattr(self.model, "weights_id", "")}

    @classmethod
    def from_memory(cls, options: PipelineOptions, memory: dict, cache_root) -> "CachedPipeline | None":
        """The pipeline ``options`` make, from what they resolved to when last built (``memory()``) and the trace
        cache at ``cache_root``, without building the detector, loading the mass CNN or importing torch: a
        ``CachedPipeline``, which serves cached traces only. None when the options are out of range, the memory is
        not one, or ``--detector auto`` would choose another detector today (the caller builds the pipeline)."""
        from massviz.io.cache import TraceCache

        try:
            options.check()
        except MassvizError:
            return None
        auto = None
        if options.detector == "auto":  # auto decides from local files now, as a cold run would, and says so
            from massviz.detect import choose_auto

            name, why = ("replay", f"--replay {options.replay} given") if options.replay is not None else \
                choose_auto(options.detector_weights)
            if name != memory.get("name"):
                return None
            auto = (name, f"{why} (traces from the cache)")
        try:
            cut = options.threshold if options.threshold is not None else float(memory["default_threshold"])
            detector = _NamedDetector(str(memory["name"]), cut, dict(memory["settings"]))
            model = _NamedModel(str(memory["weights_id"]))
        except (KeyError, TypeError, ValueError):
            return None
        return CachedPipeline(options, detector, model, TraceCache(cache_root), auto=auto)


class _NamedDetector:
    """Stands for a detector by its name, score cut and settings (``Pipeline.from_memory``); it cannot detect."""

    def __init__(self, name: str, threshold: float, settings: dict):
        self.name, self.threshold, self._settings = name, float(threshold), dict(settings)
        self.default_batch = 1

    def settings(self) -> dict:
        return dict(self._settings)

    def detect(self, frame):  # pragma: no cover - a CachedPipeline is used only when every trace is cached
        raise MassvizError("internal error: the warm path reached a recording that is not in the cache")

    detect_batch = detect


class _NamedModel:
    """Stands for the mass CNN by its ``weights_id`` (``Pipeline.from_memory``); it cannot predict."""

    def __init__(self, weights_id: str):
        self.weights_id = weights_id

    def predict(self, *a, **k):  # pragma: no cover - see _NamedDetector.detect
        raise MassvizError("internal error: the warm path needed the mass CNN")


@dataclass
class CachedPipeline(Pipeline):
    """A pipeline of named stand-ins (``Pipeline.from_memory``) that serves cached traces only and opens recordings
    from their remembered identities (``massviz.io.identity.open_remembered``)."""

    #: ``--detector auto``'s (name, reason), said by ``used`` (None for a named detector)
    auto: tuple | None = None

    def used(self) -> "CachedPipeline":
        """This pipeline serves the command: say auto's choice as a built one does
        (``massviz.detect.announce_auto``)."""
        if self.auto is not None:
            from massviz.detect import announce_auto

            announce_auto(*self.auto)
        return self

    def open_recording(self, path, allow_partial: bool = False):
        from massviz.io.identity import open_remembered

        return open_remembered(path, self.cache.root, allow_partial=allow_partial)


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
    selection = resolve_selection(selection, k, stride, cut=detector.threshold)
    if exclude is not None:
        selection = selection.replace(exclude=tuple(selection.exclude) + tuple(Selection(exclude=exclude).exclude))
    k, stride, threshold = selection.k, selection.stride, selection.threshold
    exclude = list(selection.exclude) or None
    info = detector_info(detector)
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
    from massviz.io.cache import TraceCache
    from massviz.io.checkpoint import load_checkpoint
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


def build_pipelines(options: PipelineOptions, settings_of: dict):
    """One pipeline per distinct settings among ``settings_of`` ({key: {``PipelineOptions`` field: value}} over
    ``options``, e.g. what a run folder records per recording), with the keys it serves: (pipeline, keys) pairs in
    the order the settings are first seen, each built when it is reached."""
    groups: dict = {}
    for key, settings in settings_of.items():
        groups.setdefault(tuple(settings.items()), []).append(key)
    for settings, keys in groups.items():
        yield build_pipeline(options.replace(**dict(settings))), keys


def process_recordings(recordings, options: PipelineOptions | None = None, *, progress: bool = False, **kwargs) -> list:
    """One trace per recording (paths or ``Recording`` objects), from the cache when there: what notebooks call."""
    from massviz.io.recording import open_recording

    pipeline = build_pipeline(options, **kwargs)
    return [pipeline.process(r if not isinstance(r, (str, Path)) else open_recording(r), progress=progress)
            for r in recordings]


__all__ = ["PipelineOptions", "Pipeline", "CachedPipeline", "process", "build_pipeline", "build_pipelines",
           "process_recordings", "PRECISIONS"]
