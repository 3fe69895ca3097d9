"""Where the pipeline computes: ``--device`` (``auto``, ``cpu``, ``cuda``, ``cuda:N``), what fp32 means on a GPU, and
copying frames to the device.

**Faithful on a GPU.** ``--precision fp32`` is the paper's arithmetic: IEEE fp32 in every convolution and matrix
product. On NVIDIA GPUs since Ampere, PyTorch runs fp32 convolutions as TF32 by default (a 10-bit mantissa);
:func:`faithful_fp32` turns that off (cuDNN and cuBLAS in IEEE fp32) and asks cuDNN for deterministic algorithms
without benchmarking, so the same input gives the same bits run after run. cuDNN still chooses its algorithm by the
shape of the call, so a batch of 4 frames may round differently from 4 batches of 1: on CUDA the faithful mode
therefore detects one frame per call by default (``default_batch``), and the mass CNN always runs calls of one fixed
size (``massviz.core.model.DEVICE_CALL_ROWS``), so a patch's prediction does not depend on its company.
``bf16``/``fp16`` are the fast modes: batched, reduced precision, results that differ (measure with ``compare``).
"""
from __future__ import annotations

import contextlib

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


@contextlib.contextmanager
def faithful_fp32(device, enabled: bool = True):
    """IEEE fp32 (no TF32) and deterministic cuDNN algorithms inside the block when ``device`` is CUDA; the previous
    settings are restored after it. A no-op on the CPU (its fp32 is IEEE already)."""
    import torch

    if not enabled or torch.device(device).type != "cuda":
        yield
        return
    b = torch.backends
    new_api = hasattr(b.cudnn, "conv") and hasattr(b.cudnn.conv, "fp32_precision")
    saved = (b.cudnn.deterministic, b.cudnn.benchmark,
             (b.cudnn.conv.fp32_precision, b.cuda.matmul.fp32_precision) if new_api
             else (b.cudnn.allow_tf32, b.cuda.matmul.allow_tf32))
    b.cudnn.deterministic, b.cudnn.benchmark = True, False
    if new_api:
        b.cudnn.conv.fp32_precision, b.cuda.matmul.fp32_precision = "ieee", "ieee"
    else:
        b.cudnn.allow_tf32, b.cuda.matmul.allow_tf32 = False, False
    try:
        yield
    finally:
        b.cudnn.deterministic, b.cudnn.benchmark = saved[0], saved[1]
        if new_api:
            b.cudnn.conv.fp32_precision, b.cuda.matmul.fp32_precision = saved[2]
        else:
            b.cudnn.allow_tf32, b.cuda.matmul.allow_tf32 = saved[2]


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


__all__ = ["DEVICE_HELP", "resolve_device", "describe", "faithful_fp32", "pin_frame", "upload"]
