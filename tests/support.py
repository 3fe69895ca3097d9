"""What test modules import (conftest.py holds the fixtures built on it): the project's folders, the published
weights' path inside ../shared, the one ``massviz`` command-line runner and the samples' trace cache."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("MASSVIZ_SHARED", ROOT.parent / "shared"))
SAMPLES = ROOT / "data_samples"
#: the mass CNN's published weights, relative to the shared folder
WEIGHTS = Path("weights") / "corsmal_visual" / "Encoder_pool_aug_158.torch"
#: variables of the caller's shell that would change what a command prints or which weights it loads
CLEARED_ENV = ("MASSVIZ_DEBUG", "MASSVIZ_WEIGHTS")


def missing_reference(msg: str):
    """Skip the test, or fail it under CI=true (where reference data must be there)."""
    import pytest

    if os.environ.get("CI", "").lower() == "true":
        pytest.fail(msg)
    pytest.skip(msg)


def run_massviz(*args, env: dict | None = None, cwd: Path | None = None, timeout: float = 600,
                check: bool = False) -> subprocess.CompletedProcess:
    """``python -m massviz ARGS`` as a user runs it, from the project root: the caller's environment without
    ``MASSVIZ_DEBUG``/``MASSVIZ_WEIGHTS``, plus ``env``. stdout/stderr are str, decoded from bytes so that progress
    bars' carriage returns stay visible. ``check`` asserts exit 0 (showing the end of stderr)."""
    full = {k: v for k, v in os.environ.items() if k not in CLEARED_ENV}
    full.update({k: str(v) for k, v in (env or {}).items()})
    result = subprocess.run([sys.executable, "-m", "massviz", *map(str, args)], capture_output=True, timeout=timeout,
                            cwd=cwd or ROOT, env=full)
    result.stdout, result.stderr = result.stdout.decode(), result.stderr.decode()
    if check:
        assert result.returncode == 0, result.stderr[-3000:]
    return result


def end_processes(processes) -> None:
    """End ``processes`` (psutil.Process): SIGTERM, then SIGKILL what is still there after 5 s; reap our children."""
    import contextlib

    import psutil

    for p in processes:
        with contextlib.suppress(psutil.Error):
            p.terminate()
    _, alive = psutil.wait_procs(processes, timeout=5)
    for p in alive:
        with contextlib.suppress(psutil.Error):
            p.kill()
    psutil.wait_procs(alive, timeout=5)


def started_since(before: set[int]) -> list:
    """This process's descendants (psutil.Process) whose pid is not in ``before``."""
    import psutil

    return [p for p in psutil.Process().children(recursive=True) if p.pid not in before]


def session_base(tmp_path_factory) -> Path:
    """The temporary folder every worker of this session shares (under xdist: the parent of the worker's own)."""
    base = tmp_path_factory.getbasetemp()
    return base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base


def no_other_ray(tmp_path_factory):
    """A lock across the session's workers, held while a test's Ray cluster is up (``test_runners.ray_address``) and
    by a test that needs none to be (``ray.init(address="auto")`` also finds a cluster by its processes, so another
    worker's cluster would be found and joined)."""
    from filelock import FileLock

    return FileLock(str(session_base(tmp_path_factory) / "massviz-ray-cluster.lock"))


def sample_cache(tmp_path_factory, shared_dir: Path, samples_dir: Path) -> Path:
    """The session's trace cache folder of the bundled samples (depth detector, published weights, the paper's
    threshold 0.4 and K = 5, every frame), filled on first use."""
    import pytest

    from massviz.app import process_recordings
    from massviz.io.recording import collect_recordings

    if not (samples_dir / "cup_handover" / "meta.json").is_file():
        pytest.skip("the bundled samples (data_samples/) are missing")

    from filelock import FileLock, Timeout

    base = session_base(tmp_path_factory)  # under xdist: one cache for the session's workers, filled once
    root = base / "massviz-sample-traces"
    root.mkdir(exist_ok=True)
    # one lock per sample: workers that need the cache at the same time fill it together (each takes a sample no
    # other worker is processing, then waits for the rest) instead of one filling it while the others wait
    pending = collect_recordings([samples_dir])
    for blocking in (False, True):
        for rec in list(pending):
            lock = FileLock(str(base / f"massviz-sample-traces.{rec.id}.lock"))
            try:
                lock.acquire(timeout=-1 if blocking else 0)
            except Timeout:
                continue
            try:
                done = root / f"{rec.id}.complete"
                if not done.is_file():
                    process_recordings([rec], detector="depth", weights=str(shared_dir / WEIGHTS), cache=str(root),
                                       quiet=True)
                    done.write_text("ok\n")
            finally:
                lock.release()
            pending.remove(rec)
    return root


def samples_and_618(root: Path, shared_dir: Path, samples_dir: Path, intrinsics: dict) -> Path:
    """The three samples and CCM 618 as one folder ``root`` of massviz recordings (frames linked, not copied)."""
    import json

    root.mkdir()
    for name in ("box_handover", "cup_handover", "glass_handover"):
        (root / name).symlink_to(samples_dir / name, target_is_directory=True)
    rec = root / "618"
    rec.mkdir()
    for part in ("rgb", "depth"):
        (rec / part).symlink_to(shared_dir / "ccm_real" / "618" / part, target_is_directory=True)
    (rec / "intrinsics.json").write_text(json.dumps(intrinsics))
    (rec / "meta.json").write_text(json.dumps({"id": "618", "fps": 3.0,
                                               "container": {"mass_g": 10.0, "class": "cup", "id": 1}}))
    return root


def require_pyrealsense2():
    """pyrealsense2, else skip the test (fail it under CI=true, where the test extra has installed it)."""
    try:
        import pyrealsense2
    except ImportError:
        missing_reference("pyrealsense2 is missing (the test extra installs it)")
    return pyrealsense2


# ------------------------------------------------------------------------------------------------- killed commands
#: ``os.replace`` wrapped: the process's ``KILL_AT``-th call (``KILL_WHEN``: just before or just after it) kills it
#: (SIGKILL); without ``KILL_AT`` it only counts. Counted per process id: a fork server's child counts its own calls.
KILL_HOOK = """
import os, signal
real, seen = os.replace, {}
def replace(src, dst, *args, **kwargs):
    pid = os.getpid()
    seen[pid] = seen.get(pid, 0) + 1
    n, when = int(os.environ.get("KILL_AT", "0")), os.environ.get("KILL_WHEN")
    if seen[pid] == n and when == "before":
        os.kill(pid, signal.SIGKILL)
    out = real(src, dst, *args, **kwargs)
    if seen[pid] == n and when == "after":
        os.kill(pid, signal.SIGKILL)
    return out
os.replace = replace
import atexit
# KILL_COUNT (a file): where a run that was not killed writes how many commits it made
atexit.register(lambda: os.environ.get("KILL_COUNT") and open(os.environ["KILL_COUNT"], "w").write(
    str(seen.get(os.getpid(), 0))))
"""
#: the command line of a run killed at a commit, in a process of its own
KILLED_RUN = KILL_HOOK + """
import sys
from massviz.cli import main
sys.exit(main(sys.argv[1:]))
"""
#: a fork server (``tests/forkserver.py``) whose children run with the hook: the same kills without each run's
#: imports of torch and massviz (training's too: ``torch.use_deterministic_algorithms`` loads ``torch._dynamo``)
KILLING_SERVER = KILL_HOOK + f"""
import sys
sys.path.insert(0, {str(Path(__file__).resolve().parent)!r})
from massviz.cli import _quiet_native_logs
_quiet_native_logs()  # before cv2 loads
import massviz.training.train, torch._dynamo
from forkserver import serve
serve()
"""


def small_recording(dst: Path, frames: int = 3, sample: str = "cup_handover") -> Path:
    """A recording folder holding the first ``frames`` frames of a bundled sample (rgb/, depth/, gt/, its
    intrinsics.json, and its meta.json cut to those frames, its id the folder's name)."""
    import json
    import shutil

    src = SAMPLES / sample
    for sub in ("rgb", "depth", "gt"):
        (dst / sub).mkdir(parents=True)
        for frame in sorted((src / sub).glob("*.png"))[:frames]:
            shutil.copyfile(frame, dst / sub / frame.name)
    shutil.copyfile(src / "intrinsics.json", dst / "intrinsics.json")
    meta = json.loads((src / "meta.json").read_text())
    (dst / "meta.json").write_text(json.dumps({**meta, "id": dst.name, "frames": meta["frames"][:frames]}))
    return dst


def random_mask_case(n, seed=0, width=200, height=150):
    """Mask R-CNN-like outputs for ``n`` detections in a ``width`` x ``height`` frame: (probabilities (n, 1, 28, 28),
    float boxes (n, 4) inside the frame, the generator, to draw more from it)."""
    import torch

    g = torch.Generator().manual_seed(seed)
    probs = torch.rand(n, 1, 28, 28, generator=g)
    xy = torch.rand(n, 2, generator=g) * torch.tensor([width - 2.0, height - 2.0])
    wh = torch.rand(n, 2, generator=g) * torch.tensor([width / 2.0, height / 2.0]) + 0.3
    boxes = torch.cat([xy, torch.minimum(xy + wh, torch.tensor([width - 0.01, height - 0.01]))], 1)
    return probs, boxes, g
