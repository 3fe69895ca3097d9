"""The faithful fp32 settings on CUDA (``massviz.core.device.faithful_fp32``), checked on any machine: the context is
given ``"cuda"`` and torch's process-wide ``torch.backends`` flags are read (setting them needs no GPU)."""
from __future__ import annotations

import threading

import numpy as np
import pytest
import torch

from massviz.core.device import default_batch, faithful_fp32, faithful_users

B = torch.backends
NEW_API = hasattr(B.cudnn, "conv") and hasattr(B.cudnn.conv, "fp32_precision")


def flags() -> dict:
    """The flags the faithful settings set, as torch reports them."""
    out = {"deterministic": B.cudnn.deterministic, "benchmark": B.cudnn.benchmark}
    if NEW_API:  # (torch refuses to read its older allow_tf32 flags once these are set)
        out.update(conv=B.cudnn.conv.fp32_precision, rnn=B.cudnn.rnn.fp32_precision,
                   matmul=B.cuda.matmul.fp32_precision)
    else:
        out.update(conv=B.cudnn.allow_tf32, matmul=B.cuda.matmul.allow_tf32)
    return out


def tf32_off(f: dict) -> bool:
    """No TF32 in cuDNN's convolutions (and RNNs) nor cuBLAS's matrix products, deterministic cuDNN."""
    precision = (f["conv"], f["rnn"], f["matmul"]) == ("ieee",) * 3 if NEW_API else (f["conv"], f["matmul"]) == (
        False, False)
    return precision and f["deterministic"] is True and f["benchmark"] is False


def assert_faithful() -> None:
    assert tf32_off(flags()), flags()


@pytest.fixture
def fast_flags():
    """The flags a fast run would leave (TF32 on, cuDNN benchmarking, not deterministic); restored afterwards."""
    saved = flags()
    B.cudnn.deterministic, B.cudnn.benchmark = False, True
    if NEW_API:
        B.cudnn.conv.fp32_precision, B.cudnn.rnn.fp32_precision, B.cuda.matmul.fp32_precision = "tf32", "tf32", "tf32"
    else:
        B.cudnn.allow_tf32, B.cuda.matmul.allow_tf32 = True, True
    assert not tf32_off(flags())
    yield flags()
    B.cudnn.deterministic, B.cudnn.benchmark = saved["deterministic"], saved["benchmark"]
    if NEW_API:
        B.cudnn.conv.fp32_precision, B.cudnn.rnn.fp32_precision = saved["conv"], saved["rnn"]
        B.cuda.matmul.fp32_precision = saved["matmul"]
    else:
        B.cudnn.allow_tf32, B.cuda.matmul.allow_tf32 = saved["conv"], saved["matmul"]


def test_tf32_is_off_inside_and_the_flags_are_restored_after(fast_flags):
    with faithful_fp32("cuda"):
        assert_faithful()
        assert faithful_users() == 1
    assert flags() == fast_flags and faithful_users() == 0
    with faithful_fp32(torch.device("cuda", 0)):
        assert_faithful()
    assert flags() == fast_flags


def test_the_flags_are_restored_after_an_exception(fast_flags):
    with pytest.raises(KeyError):
        with faithful_fp32("cuda"):
            assert_faithful()
            raise KeyError("boom")
    assert flags() == fast_flags and faithful_users() == 0


def test_cpu_and_disabled_change_nothing(fast_flags):
    for device, enabled in (("cpu", True), ("cuda", False)):
        with faithful_fp32(device, enabled):
            assert flags() == fast_flags and faithful_users() == 0


def test_nested_use_keeps_the_settings_until_the_outermost_leaves(fast_flags):
    with faithful_fp32("cuda"):
        with faithful_fp32("cuda"):
            assert faithful_users() == 2
        assert_faithful()  # the inner block's exit did not restore the fast flags under the outer one
        with pytest.raises(ValueError):
            with faithful_fp32("cuda"):
                raise ValueError
        assert_faithful()
        assert faithful_users() == 1
    assert flags() == fast_flags


def test_two_threads_share_the_settings_and_the_last_to_leave_restores(fast_flags):
    """Thread A enters, B enters, A leaves while B still computes: B must still see TF32 off; B leaves: restored."""
    a_in, b_in, a_out, b_checked = (threading.Event() for _ in range(4))
    seen, errors = {}, []

    def a():
        try:
            with faithful_fp32("cuda"):
                a_in.set()
                assert b_in.wait(10)
            a_out.set()
        except Exception as e:  # noqa: BLE001 - reported by the main thread
            errors.append(e)

    def b():
        try:
            assert a_in.wait(10)
            with faithful_fp32("cuda"):
                b_in.set()
                assert a_out.wait(10)
                seen["after a left"] = flags()
                seen["users"] = faithful_users()
            b_checked.set()
        except Exception as e:  # noqa: BLE001 - reported by the main thread
            errors.append(e)

    threads = [threading.Thread(target=a), threading.Thread(target=b)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(20)
    assert not errors and b_checked.is_set()
    assert seen["users"] == 1
    assert tf32_off(seen["after a left"])
    assert flags() == fast_flags and faithful_users() == 0


def test_many_threads_entering_and_leaving_restore_the_flags(fast_flags):
    def work():
        for _ in range(200):
            with faithful_fp32("cuda"):
                assert tf32_off(flags())

    threads = [threading.Thread(target=work) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert flags() == fast_flags and faithful_users() == 0


def test_batch_1_is_the_fp32_default_on_cuda():
    assert default_batch("cuda", "fp32") == 1 and default_batch(torch.device("cuda", 0), "fp32") == 1
    assert default_batch("cuda", "fp16") == 8 and default_batch("cuda", "bf16") == 8
    assert [default_batch("cpu", p) for p in ("fp32", "bf16", "fp16")] == [1, 1, 1]


class CudaStandIn:
    """A mass CNN that says it is on CUDA (no GPU is needed: it predicts 1 g on the CPU) and records the flags of
    every prediction and the thread that made it."""

    device = torch.device("cuda")
    weights_id = "stand-in"

    def __init__(self, precision: str = "fp32"):
        self.precision, self.seen = precision, []

    def predict(self, patches, features):
        self.seen.append((flags(), threading.current_thread().name))
        return np.ones(len(patches), np.float32)


@pytest.fixture
def no_gpu_name(monkeypatch):
    """The trace's description of a CUDA device without asking the driver for its name."""
    import massviz.core.device as device

    monkeypatch.setattr(device, "describe", lambda d: f"{torch.device(d)} (stand-in)")


@pytest.fixture(scope="module")
def recording(samples_dir):
    from massviz.io.recording import open_recording

    return open_recording(samples_dir / "cup_handover")


def test_a_run_sets_the_faithful_settings_once_for_all_its_batches(recording, fast_flags, monkeypatch, no_gpu_name):
    """``run`` enters the settings once: every batch, computed in the stage's own thread (a run on CUDA overlaps),
    sees TF32 off, the flags are written once to set and once to restore, and the trace says faithful."""
    import massviz.core.device as device
    from massviz.core.pipeline import run
    from massviz.detect import make_detector

    writes = []
    real = device._write_flags
    monkeypatch.setattr(device, "_write_flags", lambda *a: (writes.append(a[2]), real(*a)))
    model = CudaStandIn()
    trace = run(recording, make_detector("depth", 0.4, quiet=True), model, k=3, stride=9, prefetch=0,
                kernels="exact")
    assert len(trace.frames) >= 3 and len(model.seen) >= 3
    assert all(tf32_off(f) for f, _ in model.seen)
    assert {name for _, name in model.seen} != {threading.current_thread().name}  # in the stage's thread
    assert len(writes) == 2 and writes[0] == "ieee"  # set once, restored once
    assert flags() == fast_flags and faithful_users() == 0
    assert trace.compute["mode"] == "faithful" and trace.compute["precision"] == "fp32"


def test_a_fast_run_leaves_tf32_on(recording, fast_flags, no_gpu_name):
    """A fast mode does not get the faithful settings, even when its mass CNN stays fp32 (``--precision fp16``)."""
    from massviz.core.pipeline import run
    from massviz.detect import make_detector

    class Fp16Depth:
        def __init__(self):
            self.inner = make_detector("depth", 0.4, quiet=True)
            self.precision, self.threshold, self.name = "fp16", self.inner.threshold, self.inner.name

        def detect(self, frame):
            return self.inner.detect(frame)

        def settings(self):
            return self.inner.settings()

    model = CudaStandIn("fp32")
    trace = run(recording, Fp16Depth(), model, k=3, stride=12, prefetch=0, kernels="exact")
    assert model.seen and all(f == fast_flags for f, _ in model.seen)
    assert trace.compute["mode"] == "fast"
