"""What lets the device path overlap its work: a side stream for the detector, events between streams, copies back
into pinned memory, and compiled device functions. On CUDA these are CUDA's; on a CPU each is the plain operation
(no stream, no event, an ordinary copy, the eager function), so the same code runs and is tested there.

* :class:`Lane`: a stream to run work on (``with lane:``), ``record()`` an event after it, ``wait(event)`` before
  using what another lane made, ``keep(tensor)`` for a tensor made on another lane and used on this one (PyTorch's
  ``record_stream``: its memory is not reused while this lane may still read it).
* :func:`to_host`: device tensors copied back in one go into page-locked memory, then waited for once.
* :func:`compiled`: ``torch.compile`` of a function on CUDA (``dynamic=False``: callers round their shapes up with
  :func:`bucket`), the eager function elsewhere, when ``MASSVIZ_COMPILE=0``, or after compiling fails once (said
  once in the log).
"""
from __future__ import annotations

import contextlib
import logging
import os
import threading

log = logging.getLogger("massviz")


class Lane:
    """A CUDA stream of its own on a CUDA ``device`` (``current=True``: the calling thread's current stream); on
    any other device a no-op with the same methods."""

    def __init__(self, device, current: bool = False):
        import torch

        self.device = torch.device(device)
        self.cuda = self.device.type == "cuda"
        self.stream = None
        if self.cuda:
            self.stream = torch.cuda.current_stream(self.device) if current else torch.cuda.Stream(self.device)

    def __enter__(self):
        import torch

        self._ctx = torch.cuda.stream(self.stream) if self.cuda else contextlib.nullcontext()
        self._ctx.__enter__()
        return self

    def __exit__(self, *exc):
        return self._ctx.__exit__(*exc)

    def record(self):
        """An event marking the work queued on this lane so far (None on a CPU: that work is done already)."""
        if not self.cuda:
            return None
        return self.stream.record_event()

    def wait(self, event) -> None:
        """Work queued on this lane from now on starts after ``event``."""
        if self.cuda and event is not None:
            self.stream.wait_event(event)

    def keep(self, *tensors) -> None:
        """Tensors made on another lane and used on this one: their memory stays theirs until this lane's work
        queued so far is done."""
        if not self.cuda:
            return
        for t in tensors:
            if t is not None and getattr(t, "is_cuda", False):
                t.record_stream(self.stream)


def to_host(tensors: list, lane: Lane | None = None) -> list:
    """numpy copies of ``tensors`` (None stays None): on CUDA copied without blocking into pinned memory on
    ``lane`` (default: the current stream), then waited for once; on a CPU ``.numpy()`` of the tensor itself."""
    import torch

    live = [t for t in tensors if t is not None]
    if not live or not live[0].is_cuda:
        return [None if t is None else t.detach().cpu().numpy() for t in tensors]
    outs = []
    for t in tensors:
        if t is None:
            outs.append(None)
            continue
        host = torch.empty(t.shape, dtype=t.dtype, pin_memory=True)
        host.copy_(t, non_blocking=True)
        outs.append(host)
    stream = lane.stream if lane is not None and lane.cuda else torch.cuda.current_stream(live[0].device)
    stream.synchronize()
    return [None if h is None else h.numpy() for h in outs]


_COMPILED: dict = {}
_LOCK = threading.Lock()
#: shapes a compiled function may be specialised for before dynamo runs it eagerly (its default is 8)
RECOMPILE_LIMIT = 64


def bucket(n: int, least: int = 16) -> int:
    """The smallest of least * {1, 1.5, 2, 3, 4, 6, ...} (powers of two and 1.5 times them) that is >= ``n``: a
    compiled function meets few shapes, each padded by less than half."""
    size = int(least)
    while size < n:
        size = size * 3 // 2 if size & (size - 1) == 0 else size * 4 // 3
    return size


def compile_enabled() -> bool:
    """False when ``MASSVIZ_COMPILE=0`` (the eager functions everywhere)."""
    return os.environ.get("MASSVIZ_COMPILE", "1") != "0"


def compiled(fn, device):
    """``fn`` compiled for a CUDA ``device`` (once per function; its shapes bucketed by the caller), else ``fn``.
    A compilation or run that fails falls back to ``fn`` for the rest of the process, with one log line."""
    import torch

    if torch.device(device).type != "cuda" or not compile_enabled():
        return fn
    with _LOCK:
        got = _COMPILED.get(fn)
        if got is None:
            import torch._dynamo

            for name in ("recompile_limit", "cache_size_limit"):
                if hasattr(torch._dynamo.config, name):
                    setattr(torch._dynamo.config, name, max(getattr(torch._dynamo.config, name), RECOMPILE_LIMIT))
            got = _COMPILED[fn] = _Fallback(fn, torch.compile(fn, dynamic=False))
    return got


class _Fallback:
    def __init__(self, eager, fast):
        self.eager, self.fast, self.failed = eager, fast, False

    def __call__(self, *args, **kwargs):
        if not self.failed:
            try:
                return self.fast(*args, **kwargs)
            except Exception as err:  # noqa: BLE001 - a compiler that cannot: the eager function computes the same
                self.failed = True
                log.warning("massviz: compiling %s failed (%s: %s); running it eagerly", self.eager.__name__,
                            type(err).__name__, str(err).splitlines()[0][:200] if str(err) else "")
        return self.eager(*args, **kwargs)


__all__ = ["Lane", "RECOMPILE_LIMIT", "bucket", "to_host", "compiled", "compile_enabled"]
