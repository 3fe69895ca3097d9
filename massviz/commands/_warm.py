"""The warm path of the dataset commands: when every recording's trace is in the cache, find it from file identities
(``massviz.io.identity``) and the selection index (``massviz.io.cache.TraceIndex``) without opening a frame, loading
the mass CNN, building the detector or importing torch.

* ``build_remembering(args, threshold)``: ``_common.build`` that also remembers what the options resolved to (the
  detector's cache settings, the model's ``weights_id``), keyed by the options and valid while the files read to
  build it (weights, replay source, ...) are unchanged.
* ``warm_pipeline(args, threshold)``: a ``massviz.app.Pipeline`` made from that memory (a detector and a model that
  only *name* themselves: they cannot run), or None. Use it only for recordings whose trace is in the cache.
"""
from __future__ import annotations

from pathlib import Path

from massviz.errors import MassvizError


class _NamedDetector:
    """Stands for a detector whose settings are remembered; it cannot detect."""

    def __init__(self, name: str, threshold: float, settings: dict):
        self.name, self.threshold, self._settings = name, float(threshold), dict(settings)
        self.default_batch = 1

    def settings(self) -> dict:
        return dict(self._settings)

    def detect(self, frame):  # pragma: no cover - the warm path is taken only when every trace is cached
        raise MassvizError("internal error: the warm path reached a recording that is not in the cache")

    detect_batch = detect


class _NamedModel:
    """Stands for the mass CNN by its ``weights_id``; it cannot predict."""

    def __init__(self, weights_id: str):
        self.weights_id = weights_id

    def predict(self, *a, **k):  # pragma: no cover - see _NamedDetector.detect
        raise MassvizError("internal error: the warm path needed the mass CNN")


def _warm_class():
    from massviz.app import Pipeline

    class WarmPipeline(Pipeline):
        """A ``massviz.app.Pipeline`` of named stand-ins (``warm_pipeline``) that opens recordings from their
        remembered identities (``massviz.io.identity.open_remembered``)."""

        #: ``--detector auto``'s (name, reason), said by ``used`` (None for a named detector)
        auto = None

        def used(self) -> "WarmPipeline":
            """This pipeline serves the command: say auto's choice as a cold run does (massviz.detect.announce_auto)."""
            if self.auto is not None:
                from massviz.detect import announce_auto

                announce_auto(*self.auto)
            return self

        def open_recording(self, path, allow_partial: bool = False):
            from massviz.io.identity import open_remembered

            return open_remembered(path, self.cache.root, allow_partial=allow_partial)

    return WarmPipeline


def cache_root(args) -> Path | None:
    """The trace cache folder the options name (None with --no-cache)."""
    from massviz.io.cache import default_cache_dir

    if getattr(args, "no_cache", False):
        return None
    return Path(args.cache) if getattr(args, "cache", None) else default_cache_dir()


def _key(options) -> dict:
    """What decides the detector's cache settings and the model's id: everything but threshold, K, stride, cache."""
    import os

    from massviz.io.weights import ENV_WEIGHTS

    def absolute(p):
        return None if p is None else str(Path(p).expanduser().resolve())

    weights = options.weights if options.weights is not None else (os.environ.get(ENV_WEIGHTS) or None)
    return {"detector": options.detector, "detector_weights": absolute(options.detector_weights),
            "replay": absolute(options.replay), "precision": options.precision, "weights": absolute(weights),
            "device": options.device}


def build_remembering(args, threshold: float | None = None):
    """``_common.build(args, threshold)``, remembering what it resolved to for :func:`warm_pipeline`."""
    from massviz.app import PipelineOptions
    from massviz.commands._common import build
    from massviz.io.identity import capture_reads, remember_pipeline

    root = cache_root(args)
    if root is None:
        return build(args, threshold)
    with capture_reads() as reads:
        pipeline = build(args, threshold)
        resolved = {"name": pipeline.detector.name, "settings": pipeline.detector.settings(),
                    "default_threshold": float(pipeline.detector.default_threshold),
                    "weights_id": getattr(pipeline.model, "weights_id", "")}
    try:
        remember_pipeline(root, _key(PipelineOptions.from_args(args)), resolved, reads)
    except Exception:  # noqa: BLE001 - the memory is an optimisation
        pass
    return pipeline


def warm_pipeline(args, threshold: float | None = None):
    """A pipeline that serves cached traces only (see the module docstring), or None when the options were never
    built here or a file they read changed."""
    from massviz.app import PipelineOptions
    from massviz.io.cache import TraceCache
    from massviz.io.identity import remembered_pipeline

    _Warm = _warm_class()

    root = cache_root(args)
    if root is None:
        return None
    options = PipelineOptions.from_args(args, **({} if threshold is None else {"threshold": threshold}))
    try:
        options.check()
    except MassvizError:
        return None
    resolved = remembered_pipeline(root, _key(options))
    if resolved is None:
        return None
    if options.detector == "auto":  # auto decides from local files now, as a cold run would, and says so
        from massviz.detect import announce_auto, choose_auto

        name, why = ("replay", f"--replay {options.replay} given") if options.replay is not None else \
            choose_auto(options.detector_weights)
        if name != resolved.get("name"):  # it would choose another detector today: the cold path builds that one
            return None
        auto = (name, f"{why} (traces from the cache)")
    else:
        auto = None
    try:
        threshold = options.threshold if options.threshold is not None else float(resolved["default_threshold"])
        detector = _NamedDetector(str(resolved["name"]), threshold, dict(resolved["settings"]))
        model = _NamedModel(str(resolved["weights_id"]))
    except (KeyError, TypeError, ValueError):
        return None
    pipeline = _Warm(options, detector, model, TraceCache(root))
    pipeline.auto = auto
    return pipeline


def cache_info(pipeline) -> dict:
    """The detector part of the trace cache's key."""
    return {"name": pipeline.detector.name, **pipeline.detector.settings()}


def locate_all(paths, root, allow_partial: bool = False):
    """Every recording recognised from its file identities (``massviz.io.identity.locate``), or None when one is not."""
    from massviz.io.identity import locate

    out = []
    for p in paths:
        rec = locate(p, root, allow_partial)
        if rec is None:
            return None
        out.append(rec)
    return out


def all_cached(pipeline, recordings, stride: int, threshold: float) -> bool:
    """True when every recording was recognised (``LocatedRecording``) and has a trace in the cache made with this
    pipeline's detector settings and model (a warm pipeline serves those only)."""
    from massviz.io.identity import LocatedRecording

    if not all(isinstance(r, LocatedRecording) for r in recordings):
        return False
    return cached_indexes(pipeline, recordings, stride, threshold) is not None


def cached_indexes(pipeline, recordings, stride: int, threshold: float):
    """The selection index of every recording's cached trace made with this pipeline's detector and model, with the
    recording's info as found today; None when one is missing or was made with another model."""
    import dataclasses

    info = cache_info(pipeline)
    weights_id = getattr(pipeline.model, "weights_id", "")
    out = []
    for rec in recordings:
        index = pipeline.cache.load_index(rec, info, stride, threshold)
        if index is None or index.weights_id != weights_id:
            return None
        out.append(dataclasses.replace(index, recording=rec.info()))
    return out


__all__ = ["cache_root", "build_remembering", "warm_pipeline", "locate_all", "all_cached", "cached_indexes", "cache_info"]
