"""One builder for the pipeline, shared by the CLI, the notebooks and every runner.

    options = PipelineOptions(detector="depth", threshold=0.4, k=5)        # or PipelineOptions.from_args(args)
    pipeline = build_pipeline(options)                                       # detector + mass CNN + trace cache
    trace = pipeline.process(open_recording("data_samples/cup_handover"))    # cached
    fp = pipeline.frame_pipeline(recording.info())                           # the per-frame step, for a runner

Options are plain values (picklable), so a runner can ship them to another process and build the same pipeline
there.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

from massviz.core import pipeline as _pipeline
from massviz.core.pipeline import FramePipeline
from massviz.errors import MassvizError

#: ``--precision`` choices (``massviz.detect.maskrcnn`` runs them).
PRECISIONS = ("fp32", "bf16", "fp16")


@dataclass(frozen=True)
class PipelineOptions:
    """Every setting that decides what the pipeline computes (the CLI's pipeline options)."""

    detector: str = "auto"
    threshold: float = 0.4
    k: int = 5
    stride: int = 1
    weights: str | None = None
    detector_weights: str | None = None
    replay: str | None = None
    cache: str | None = None
    no_cache: bool = False
    quiet: bool = False
    allow_partial: bool = False  # a video cut short: process what decodes (open_recording(allow_partial=))
    #: frames per detector call; None: the detector's default (Mask R-CNN: 1 on a CPU, 4 on CUDA). Results are equal.
    batch: int | None = None
    #: Mask R-CNN arithmetic: fp32 (default, the paper's), bf16 (CPU with bf16 support, CUDA; the mass CNN too) or
    #: fp16 (CUDA; the mass CNN stays fp32).
    precision: str = "fp32"

    def check(self) -> "PipelineOptions":
        """``MassvizError`` naming the option when a value is out of range."""
        if not 0.0 <= self.threshold < 1.0:
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


@dataclass
class Pipeline:
    """A built pipeline: the detector, the mass CNN and the trace cache (None: no caching), with its options."""

    options: PipelineOptions
    detector: object
    model: object
    cache: object | None

    def process(self, recording, *, exclude=None, progress: bool | None = None):
        """The recording's trace, from the cache when there (:func:`process`)."""
        progress = not self.options.quiet if progress is None else progress
        return process(recording, self.detector, self.model, k=self.options.k, stride=self.options.stride,
                       cache=self.cache, progress=progress, exclude=exclude, batch=self.batch)

    @property
    def batch(self) -> int:
        """Frames per detector call: ``options.batch``, else the detector's ``default_batch`` (1 without one)."""
        return int(self.options.batch or getattr(self.detector, "default_batch", 1))

    def frame_pipeline(self, recording_info=None) -> FramePipeline:
        """A fresh per-frame step for one recording (live camera, dataset workers, batched runners)."""
        return FramePipeline(self.detector, self.model, k=self.options.k, stride=self.options.stride,
                             recording=recording_info)


def process(recording, detector, model, **kwargs):
    """``massviz.core.pipeline.process`` with the ground truth's overlaps read into the trace
    (``massviz.io.ground_truth.with_ground_truth``: the flags of a recording with instance masks use them)."""
    from massviz.io.ground_truth import with_ground_truth

    return _pipeline.process(recording, detector, model, annotate=with_ground_truth, **kwargs)


def build_pipeline(options: PipelineOptions | None = None, **kwargs) -> Pipeline:
    """Build the detector, load the mass CNN and open the trace cache from ``options`` (or keyword options)."""
    from massviz.io.checkpoint import load_checkpoint
    from massviz.detect import make_detector
    from massviz.io.cache import TraceCache
    from massviz.io.weights import resolve_weights

    options = (options or PipelineOptions()).replace(**kwargs) if kwargs else (options or PipelineOptions())
    options.check()
    model = load_checkpoint(resolve_weights(options.weights)).set_precision(options.precision)
    detector = make_detector(options.detector, options.threshold, detector_weights=options.detector_weights,
                             replay=options.replay, quiet=options.quiet, precision=options.precision)
    cache = None if options.no_cache else TraceCache(options.cache).check_writable()
    return Pipeline(options, detector, model, cache)


def process_recordings(recordings, options: PipelineOptions | None = None, *, progress: bool = False, **kwargs) -> list:
    """One trace per recording (paths or ``Recording`` objects), from the cache when there: what notebooks call."""
    from massviz.io.recording import open_recording

    pipeline = build_pipeline(options, **kwargs)
    return [pipeline.process(r if not isinstance(r, (str, Path)) else open_recording(r), progress=progress)
            for r in recordings]


__all__ = ["PipelineOptions", "Pipeline", "process", "build_pipeline", "process_recordings", "PRECISIONS"]
