"""massviz: container empty-mass estimation from one RGB-D camera, every stage traced and visible.

``import massviz as mv`` gives the few things notebooks and scripts use; each is imported on first use, so
``import massviz`` (and the CLI) start fast::

    rec = mv.open_recording("data_samples/cup_handover")
    trace = mv.process(rec, mv.make_detector("depth"), mv.load_checkpoint(weights))
    mv.log_trace(trace, rec, rrd="cup.rrd")

The packages: ``massviz.core`` (types, trace, features, selection, model, the per-frame step; no file I/O),
``massviz.app`` (the builder and ``process``), ``massviz.detect``, ``massviz.io`` (recordings, trace files, cache,
checkpoints, weights, CSV), ``massviz.measure3d`` (the optional 3D measure stage, Open3D), ``massviz.views`` (Rerun,
Open3D, figures, widgets), ``massviz.evaluation``, ``massviz.training``, ``massviz.samples``, ``massviz.runners``,
``massviz.commands``.
"""
from __future__ import annotations

import importlib

__version__ = "0.1.0"

#: public name -> module that defines it
_API = {
    "open_recording": "massviz.io.recording",
    "find_recordings": "massviz.io.recording",
    "collect_recordings": "massviz.io.recording",
    "Recording": "massviz.io.recording",
    "make_detector": "massviz.detect",
    "MassNet": "massviz.core.model",
    "MassPredictor": "massviz.core.predictor",
    "load_checkpoint": "massviz.io.checkpoint",
    "process": "massviz.app",
    "run": "massviz.core.pipeline",
    "FramePipeline": "massviz.core.pipeline",
    "FrameResult": "massviz.core.pipeline",
    "PipelineOptions": "massviz.app",
    "build_pipeline": "massviz.app",
    "process_recordings": "massviz.app",
    "Selection": "massviz.core.selection",
    "Trace": "massviz.core.trace",
    "Event": "massviz.core.trace",
    "Detections": "massviz.core.types",
    "Frame": "massviz.core.types",
    "Intrinsics": "massviz.core.types",
    "GroundTruth": "massviz.core.types",
    "RecordingInfo": "massviz.core.types",
    "TraceCache": "massviz.io.cache",
    "resolve_weights": "massviz.io.weights",
    "log_trace": "massviz.runners.trace_to_rerun",
    "show_in_notebook": "massviz.runners.trace_to_rerun",
    "default_blueprint": "massviz.views.rerun",
    "score": "massviz.evaluation.metrics",
    "read_annotations": "massviz.io.ccm_annotations",
    "read_predictions": "massviz.evaluation.metrics",
    "sweep": "massviz.evaluation.sweep",
    "MassvizError": "massviz.errors",
}

__all__ = ["__version__", *_API]


def __getattr__(name: str):
    module = _API.get(name)
    if module is None:
        raise AttributeError(f"module 'massviz' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(__all__)
