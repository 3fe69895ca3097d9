"""Where the pipeline computes: ``--device`` (``auto``, ``cpu``, ``cuda``, ``cuda:N``), what fp32 means on a GPU, and
copying frames to the device.

**Faithful on a GPU.** ``--precision fp32`` is the paper's arithmetic: IEEE fp32 in every convolution and matrix
product. On NVIDIA GPUs since Ampere, PyTorch runs fp32 convolutions as TF32 by default (a 10-bit mantissa);
:func:`faithful_fp32` turns that off (cuDNN and cuBLAS in IEEE fp32) and asks cuDNN for deterministic algorithms
without benchmarking, so the same input gives the same bits run after run. cuDNN still chooses its algorithm by the
shape of the call, so a batch of 4 frames may round differently from 4 batches of 1: on CUDA the faithful mode
therefore detects one frame per call by default (:func:`default_batch`), and the mass CNN always runs calls of one fixed
size (``massviz.core.predictor.DEVICE_CALL_ROWS``), so a patch's prediction does not depend on its company.
``bf16``/``fp16`` are the fast modes: batched, reduced precision, results that differ (measure with ``compare``).
"""
from __future__ import annotations

import contextlib
import threading

from massviz.errors import MassvizError

DEVICE_HELP = ("where the pipeline computes: auto (a CUDA GPU when there is one, else the CPU; default), cpu, cuda, "
               "cuda:N")


def resolve_device(name: str | None = "auto"):
    """The ``torch.device`` for a ``--device`` value; ``MassvizError`` (one line) when it names no usable device."""
    import torch

    name = "auto" if name is None else str(name).strip()
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except (RuntimeError, ValueError):
        raise MassvizError(f"--device {name}: not a device (use auto, cpu, cuda or cuda:N)") from None
    if device.type == "cpu":
        return torch.device("cpu")
    if device.type != "cuda":
        raise MassvizError(f"--device {name}: massviz runs on cpu or cuda (auto, cpu, cuda, cuda:N)")
    if not torch.cuda.is_available():
        raise MassvizError(f"--device {name}: no CUDA GPU is available here (torch {torch.__version__}, "
                           f"CUDA build {torch.version.cuda or 'none'}); use --device cpu or --device auto")
    count = torch.cuda.device_count()
    if device.index is not None and device.index >= count:
        raise MassvizError(f"--device {name}: this machine has {count} CUDA GPU(s) (cuda:0"
                           f"{'' if count == 1 else f' ... cuda:{count - 1}'})")
    return torch.device("cuda", device.index if device.index is not None else torch.cuda.current_device())


def describe(device) -> str:
    """``cpu`` or ``cuda:0 (NVIDIA H200)``: what a trace records."""
    import torch

    device = torch.device(device)
    if device.type != "cuda":
        return str(device.type)
    index = device.index if device.index is not None else torch.cuda.current_device()
    return f"cuda:{index} ({torch.cuda.get_device_name(index)})"


class _FaithfulFlags:
    """The process-wide faithful settings, reference-counted: torch's cuDNN and TF32 flags are global to the
    process, so they are set when the first user enters (saving the settings found) and restored when the last user
    leaves, under a lock. Nested use and several threads then share one setting: no thread's exit turns TF32 back on
    under another thread still computing. (A thread running a fast mode beside a faithful run computes with the
    faithful flags too while the run lasts: torch has no per-thread setting of them.)"""

    def __init__(self):
        self._lock = threading.Lock()
        self._users = 0
        self._saved = None

    @property
    def users(self) -> int:
        """How many contexts hold the faithful settings now."""
        return self._users

    def enter(self) -> None:
        with self._lock:
            if self._users == 0:
                self._saved = _read_flags()
                _write_flags(True, False, "ieee")
            self._users += 1

    def leave(self) -> None:
        with self._lock:
            self._users -= 1
            if self._users == 0:
                _write_flags(*self._saved)
                self._saved = None


def _new_precision_api(b) -> bool:
    return hasattr(b.cudnn, "conv") and hasattr(b.cudnn.conv, "fp32_precision")


def _read_flags() -> tuple:
    """(cudnn.deterministic, cudnn.benchmark, the fp32 precision of cuDNN convolutions, cuDNN RNNs and cuBLAS matrix
    products): ``"ieee"``/``"tf32"``/``"none"`` in torch's newer API, ``allow_tf32`` of cuDNN and cuBLAS in the
    older one."""
    import torch

    b = torch.backends
    if _new_precision_api(b):
        precision = (b.cudnn.conv.fp32_precision, b.cudnn.rnn.fp32_precision, b.cuda.matmul.fp32_precision)
    else:
        precision = (b.cudnn.allow_tf32, b.cuda.matmul.allow_tf32)
    return b.cudnn.deterministic, b.cudnn.benchmark, precision


def _write_flags(deterministic: bool, benchmark: bool, precision) -> None:
    """Set what :func:`_read_flags` reads; ``precision`` ``"ieee"``: no TF32 anywhere. cuDNN's convolutions and
    RNNs get the same setting (torch refuses to read its older ``allow_tf32`` flag when they differ)."""
    import torch

    b = torch.backends
    b.cudnn.deterministic, b.cudnn.benchmark = deterministic, benchmark
    if _new_precision_api(b):
        conv, rnn, matmul = ("ieee",) * 3 if precision == "ieee" else precision
        b.cudnn.conv.fp32_precision, b.cudnn.rnn.fp32_precision = conv, rnn
        b.cuda.matmul.fp32_precision = matmul
    else:
        conv, matmul = (False, False) if precision == "ieee" else precision
        b.cudnn.allow_tf32, b.cuda.matmul.allow_tf32 = conv, matmul


_FAITHFUL = _FaithfulFlags()


def faithful_users() -> int:
    """How many :func:`faithful_fp32` contexts (all threads) hold the faithful settings now."""
    return _FAITHFUL.users


@contextlib.contextmanager
def faithful_fp32(device, enabled: bool = True):
    """IEEE fp32 (no TF32 in cuDNN convolutions nor cuBLAS matrix products), deterministic cuDNN algorithms and no
    cuDNN benchmarking inside the block when ``device`` is CUDA and ``enabled``; a no-op on the CPU (its fp32 is IEEE
    already). Meant to be entered once per run (``massviz.core.pipeline.run`` does, around the whole run); entering
    it again inside (a batch, the detector's own call) only counts a user.

    The flags are process-wide, so the context is reference-counted across threads: the first user to enter sets
    them, saving what it found; the last to leave (also by an exception) restores that. Two threads computing
    faithfully at once both see the faithful flags until both are done."""
    import torch

    if not enabled or torch.device(device).type != "cuda":
        yield
        return
    _FAITHFUL.enter()
    try:
        yield
    finally:
        _FAITHFUL.leave()


def default_batch(device, precision: str) -> int:
    """Frames per detector call when ``--batch`` is not given: 8 in bf16/fp16 on CUDA; 1 in the faithful fp32 mode
    on CUDA (cuDNN chooses its kernels by the call's shape: a frame's detections must not depend on its company) and
    on a CPU (batching gains ~5 % there)."""
    import torch

    return 8 if torch.device(device).type == "cuda" and precision != "fp32" else 1


def pin_frame(frame):
    """``frame`` with its RGB and depth arrays moved into page-locked memory (numpy views of pinned tensors), so that
    copying them to a GPU does not block; unchanged when CUDA is absent. Called in the reading thread."""
    import numpy as np
    import torch

    if not torch.cuda.is_available():
        return frame
    for name in ("rgb", "depth"):
        src = torch.from_numpy(np.ascontiguousarray(getattr(frame, name)))
        out = torch.empty(src.shape, dtype=src.dtype, pin_memory=True)
        out.copy_(src)
        setattr(frame, name, out.numpy())
    return frame


def upload(arrays, device):
    """Equal-shaped numpy arrays as one (N, ...) tensor on ``device``. An array in pinned memory (``pin_frame``) is
    copied without blocking; any other is copied before this returns (a non-blocking copy from pageable memory may
    read it after the caller has freed it: on machines whose GPU reads pageable memory directly it did)."""
    import numpy as np
    import torch

    srcs = [torch.from_numpy(np.ascontiguousarray(a)) for a in arrays]
    if torch.device(device).type == "cpu":
        return torch.stack(srcs)
    out = torch.empty((len(srcs), *srcs[0].shape), dtype=srcs[0].dtype, device=device)
    for i, src in enumerate(srcs):
        out[i].copy_(src, non_blocking=bool(src.is_pinned()))
    return out


__all__ = ["DEVICE_HELP", "resolve_device", "describe", "faithful_fp32", "faithful_users", "default_batch",
           "pin_frame", "upload"]
