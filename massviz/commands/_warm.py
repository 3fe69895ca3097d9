"""The warm path of the dataset commands: when every recording's trace is in the cache, find it from file identities
(``massviz.io.identity``) and the selection index (``massviz.io.cache.TraceIndex``) without opening a frame, loading
the mass CNN, building the detector or importing torch.

* ``build_remembering(args, threshold)``: ``_common.build`` that also remembers what the options resolved to
  (``massviz.app.Pipeline.memory``), keyed by the options and valid while the files read to build it (weights,
  replay source, ...) are unchanged.
* ``warm_pipeline(args, threshold)``: the ``massviz.app.CachedPipeline`` made from that memory
  (``Pipeline.from_memory``), or None. Use it only for recordings whose trace is in the cache.
"""
from __future__ import annotations

from pathlib import Path

from massviz.core.detector import detector_info


def cache_root(args) -> Path | None:
    """The trace cache folder the options name (None with --no-cache)."""
    from massviz.io.cache import default_cache_dir

    if getattr(args, "no_cache", False):
        return None
    return Path(args.cache) if getattr(args, "cache", None) else default_cache_dir()


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
        memory = pipeline.memory()
    try:
        remember_pipeline(root, PipelineOptions.from_args(args).memory_key(), memory, reads)
    except Exception:  # noqa: BLE001 - the memory is an optimisation
        pass
    return pipeline


def warm_pipeline(args, threshold: float | None = None):
    """A pipeline that serves cached traces only (see the module docstring), or None when the options were never
    built here or a file they read changed."""
    from massviz.app import Pipeline, PipelineOptions
    from massviz.io.identity import remembered_pipeline

    root = cache_root(args)
    if root is None:
        return None
    options = PipelineOptions.from_args(args, **({} if threshold is None else {"threshold": threshold}))
    memory = remembered_pipeline(root, options.memory_key())
    return None if memory is None else Pipeline.from_memory(options, memory, root)


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


def all_cached(pipeline, recordings, stride: int | None = None, threshold: float | None = None) -> bool:
    """True when every recording was recognised (``LocatedRecording``) and has a trace in the cache made with this
    pipeline's detector settings and model (a warm pipeline serves those only), at ``stride`` and ``threshold``
    (default: the pipeline's selection's)."""
    from massviz.io.identity import LocatedRecording

    if not all(isinstance(r, LocatedRecording) for r in recordings):
        return False
    return cached_indexes(pipeline, recordings, stride, threshold) is not None


def cached_indexes(pipeline, recordings, stride: int | None = None, threshold: float | None = None):
    """The selection index of every recording's cached trace made with this pipeline's detector and model at
    ``stride`` and ``threshold`` (default: the pipeline's selection's), with the recording's info as found today;
    None when one is missing or was made with another model."""
    import dataclasses

    stride = pipeline.selection.stride if stride is None else stride
    threshold = pipeline.selection.threshold if threshold is None else threshold
    info = detector_info(pipeline.detector)
    weights_id = getattr(pipeline.model, "weights_id", "")
    out = []
    for rec in recordings:
        index = pipeline.cache.load_index(rec, info, stride, threshold)
        if index is None or index.weights_id != weights_id:
            return None
        out.append(dataclasses.replace(index, recording=rec.info()))
    return out


__all__ = ["cache_root", "build_remembering", "warm_pipeline", "locate_all", "all_cached", "cached_indexes"]
