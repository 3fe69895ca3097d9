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
