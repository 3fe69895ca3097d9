"""Shared fixtures: the reference folders, the published weights, the samples' traces and the browser.

``shared_dir`` is ../shared beside the project root (reference data read in place, never copied). Outside CI a test
that needs it (or the weights in it) is skipped when it is missing; under CI=true it fails instead. Importable
helpers are in helper modules, never in a test module: ``support.py`` (the ``massviz`` command-line runner
``run_massviz``, ``ROOT``, ``WEIGHTS``, the samples' trace cache), ``fakes.py`` (fake detectors and models, recordings
and scenes, the hostile-input building blocks), ``hostile_runs.py`` (a command in a process of its own, measured),
``browser_support.py`` (Chromium, local servers, pages), ``rrd_reader.py`` and ``forkserver.py``. The fixtures below
that several modules use are built on them: one definition each.

``-m "not slow"`` starts no ``massviz`` process (``fast_tests_start_no_massviz``): a test not marked ``slow`` that
starts ``python -m massviz``, the ``massviz`` console script or a Python process that runs the command line (a fork
server, ``python -c`` calling ``massviz.cli.main``) fails.

No process started by the suite outlives it (``no_process_outlives_the_suite``): the pytest process becomes a child
subreaper (Linux), so a server whose parent died (e.g. a wrapper's child) is re-parented to it instead of init; at
the end of the session every descendant that was not there at its start is an error, and is ended.
"""
from __future__ import annotations

import contextlib
import os
import shutil
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

from browser_support import CHROMIUM, CHROMIUM_ARGS, jupyterlab
from support import (
    SAMPLES,
    SHARED,
    WEIGHTS,
    end_processes,
    missing_reference,
    run_massviz,
    samples_and_618,
    session_base,
    started_since,
)
from support import sample_cache as _fill_sample_cache

#: a test that uses one of these fixtures (directly or through another) gets the marker (and ``slow``): the module
#: need not say it again; ``sample_cache`` runs the pipeline over the samples once per session, ``cold``
#: (test_scale) a first ``massviz sweep`` over a dataset
MARK_BY_FIXTURE = {"browser": "browser", "ray_address": "ray", "executed": "notebook", "lab": "notebook",
                   "sample_cache": "slow", "cold": "slow"}
#: markers that imply ``slow`` (so ``-m "not slow"`` leaves them out)
SLOW_KINDS = ("browser", "ray", "notebook")


#: a test's weight when the files are ordered (``heaviest_files_first``): a browser, Ray or notebook test, a slow test,
#: any other test — rough seconds on the 2-core VM
WEIGHT = {"server": 30.0, "slow": 3.0, "fast": 0.1}


def heaviest_files_first(items) -> None:
    """Order ``items`` file by file, the heaviest file first (the sum of its tests' ``WEIGHT``), each file's tests in
    their own order. The README's test command hands files to its two workers in this order
    (``--dist loadfile --no-loadscope-reorder``): xdist's default order, the most tests first, left the browser files
    (2-3 long tests each) for last, and one worker ran them alone for the last ~2 minutes while the other idled."""
    weight: dict = {}  # file -> weight, in the order the files were collected
    for item in items:
        kind = ("server" if any(item.get_closest_marker(k) for k in SLOW_KINDS)
                else "slow" if item.get_closest_marker("slow") else "fast")
        weight[item.path] = weight.get(item.path, 0.0) + WEIGHT[kind]
    rank = {f: r for r, f in enumerate(sorted(weight, key=lambda f: -weight[f]))}  # a stable sort: ties keep order
    items.sort(key=lambda it: rank[it.path])  # stable too: each file's tests keep their order


def pytest_collection_modifyitems(config, items):
    for item in items:
        for fixture, marker in MARK_BY_FIXTURE.items():
            if fixture in item.fixturenames:
                item.add_marker(marker)
        if any(item.get_closest_marker(kind) for kind in SLOW_KINDS) and not item.get_closest_marker("slow"):
            item.add_marker("slow")
    heaviest_files_first(items)


#: seconds a process started by the suite may take to exit after the last fixture ended it
GRACE = 10.0


def _become_subreaper() -> None:
    """Orphaned descendants of this process are re-parented to it (``PR_SET_CHILD_SUBREAPER``), not to init."""
    if sys.platform.startswith("linux"):
        import ctypes

        with contextlib.suppress(OSError, AttributeError):
            ctypes.CDLL(None, use_errno=True).prctl(36, 1, 0, 0, 0)  # PR_SET_CHILD_SUBREAPER


@pytest.fixture(scope="session", autouse=True)
def no_process_outlives_the_suite():
    """Fail the session (an error at its last teardown) if a process the suite started is still alive at its end
    (children of pytest, grandchildren such as a ``rerun --serve-web`` behind a wrapper, and orphans of either), and
    end them. Set up first, torn down last: the other session fixtures (the browser, Ray) have ended theirs."""
    try:
        import psutil
    except ImportError:  # the test extra installs it; without it the check cannot run (CI requires it)
        yield
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail("psutil is missing: cannot check that no process outlives the tests", pytrace=False)
        return
    _become_subreaper()
    before = {p.pid for p in psutil.Process().children(recursive=True)}
    yield
    _, left = psutil.wait_procs(started_since(before), timeout=GRACE)
    left = [p for p in left if p.is_running() and p.status() != psutil.STATUS_ZOMBIE]
    if not left:
        return
    described = []
    for p in left:
        with contextlib.suppress(psutil.Error):
            described.append(f"pid {p.pid} ({' '.join(p.cmdline())[:160]})")
    end_processes(left)
    pytest.fail(f"{len(left)} process(es) started by the tests outlived them (ended now): " + "; ".join(described),
                pytrace=False)



# ------------------------------------------------------------------------------ no massviz process in a fast test
#: the test now running (set around each test's setup, call and teardown): whom a started process is charged to
_running: list = []


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    _running.append(item)
    try:
        yield
    finally:
        _running.pop()


def massviz_command(args) -> bool:
    """Whether the command line ``args`` (``subprocess.Popen``'s) runs massviz's command line: ``python -m massviz``,
    the ``massviz`` console script, ``python -c`` code that runs ``massviz.cli.main`` or a fork server
    (tests/forkserver.py) that does."""
    argv = [os.fsdecode(a) for a in ([args] if isinstance(args, (str, bytes, os.PathLike)) else args)]
    if len(argv) == 1 and " " in argv[0]:  # a shell command line
        argv = argv[0].split()
    if not argv:
        return False
    if Path(argv[0]).name == "massviz":
        return True
    for flag, value in zip(argv, argv[1:], strict=False):
        if flag == "-m" and value.split(".")[0] == "massviz":
            return True
        if flag == "-c" and ("massviz.cli import main" in value or "forkserver" in value):
            return True
    return any(Path(a).name == "forkserver.py" for a in argv[1:2])


@pytest.fixture(scope="session", autouse=True)
def fast_tests_start_no_massviz():
    """A test not marked ``slow`` (``-m "not slow"``, the inner loop) that starts a massviz process fails: it runs
    the command in-process (``massviz.cli.main``) or is marked ``slow``. Every process start goes through
    ``subprocess.Popen._execute_child``; the check wraps it for the session (so a module or session fixture set up
    for a fast test is caught too)."""
    import subprocess

    real = subprocess.Popen._execute_child

    def execute_child(self, args, *rest, **kw):
        item = _running[-1] if _running else None
        if item is not None and not item.get_closest_marker("slow") and massviz_command(args):
            command = args if isinstance(args, (str, bytes)) else " ".join(map(os.fsdecode, args))
            pytest.fail(f"{item.nodeid} is not marked slow but starts a massviz process ({command[:200]}): run it "
                        "in-process (massviz.cli.main) or mark the test slow", pytrace=False)
        return real(self, args, *rest, **kw)

    subprocess.Popen._execute_child = execute_child
    try:
        yield
    finally:
        subprocess.Popen._execute_child = real


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    if not SHARED.is_dir():
        missing_reference(f"reference data folder {SHARED} is missing (tests read ../shared in place)")
    return SHARED


@pytest.fixture(scope="session")
def samples_dir() -> Path:
    return SAMPLES


@pytest.fixture(scope="session")
def weights(shared_dir) -> Path:
    """The mass CNN's published weights (../shared/weights/corsmal_visual/Encoder_pool_aug_158.torch)."""
    path = shared_dir / WEIGHTS
    if not path.is_file():
        missing_reference(f"the published weights {path} are missing")
    return path


@pytest.fixture(scope="session")
def sample_cache(tmp_path_factory, shared_dir, weights, samples_dir) -> Path:
    """The session's trace cache of the bundled samples (depth detector, published weights, threshold 0.4, K = 5)."""
    return _fill_sample_cache(tmp_path_factory, shared_dir, samples_dir)


@pytest.fixture(scope="module")
def sample_traces(sample_cache, weights, samples_dir) -> list:
    """The samples' traces (box, cup, glass) with the cache's settings, read from the session's cache; one list per
    module (a module may change them)."""
    from massviz.app import process_recordings
    from massviz.io.recording import collect_recordings

    return process_recordings(collect_recordings([samples_dir]), detector="depth", weights=str(weights),
                              cache=str(sample_cache), threshold=0.4, quiet=True)


# One Playwright instance for every browser test module (two sync_playwright() at once refuse to start).
@pytest.fixture(scope="session")
def browser():
    missing = []
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        missing.append("the playwright package (the test extra: pip install -e '.[test]')")

    if not CHROMIUM.is_file():
        missing.append(f"{CHROMIUM} (Debian's chromium; 'bash scripts/setup.sh test' installs it)")
    if missing:
        missing_reference("browser tests need " + " and ".join(missing))
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=str(CHROMIUM), headless=True, args=CHROMIUM_ARGS)
        yield b
        b.close()


@pytest.fixture(scope="module")
def lab(tmp_path_factory, sample_cache, weights, samples_dir):
    """JupyterLab on 127.0.0.1 over a copy of notebooks/ (``browser_support.jupyterlab``): its URL, one per module."""
    with jupyterlab(tmp_path_factory.mktemp("lab"), sample_cache, weights, samples_dir) as url:
        yield url


# ------------------------------------------------------------------------------------------- models and recordings
@pytest.fixture(scope="module")
def model(weights):
    """The published mass CNN (``load_checkpoint``), one per module (a module may change its device or precision)."""
    from massviz.io.checkpoint import load_checkpoint

    return load_checkpoint(weights)


@pytest.fixture(scope="module")
def recording(samples_dir):
    """The bundled ``cup_handover`` sample, opened."""
    from massviz.io.recording import open_recording

    if not (samples_dir / "cup_handover").is_dir():
        pytest.skip("the bundled samples (data_samples/) are missing")
    return open_recording(samples_dir / "cup_handover")


@pytest.fixture(scope="module")
def rec(tmp_path_factory):
    """``fakes.scene()`` written as a recording folder and opened: 6 frames whose detections' distances are known."""
    from fakes import scene, write_recording
    from massviz.io.recording import open_recording

    rgbs, depths = scene()
    return open_recording(write_recording(tmp_path_factory.mktemp("scene") / "scene", rgbs, depths))


# ------------------------------------------------------------------------------------- hostile inputs (untrusted)
@pytest.fixture(scope="session")
def base(tmp_path_factory):
    """What the hostile-input tests mutate (``fakes.Base``): a 3-frame copy of the cup sample, a random-weight
    checkpoint, a replay JSON and a saved trace. Read only: each case copies what it changes."""
    from fakes import make_base

    return make_base(tmp_path_factory.mktemp("hostile_base"))


@pytest.fixture(scope="session")
def sample_patch_set(base, tmp_path_factory) -> Path:
    """Patches extracted from four copies of the cup sample (``fakes.make_patch_set``), for training cases. Read only."""
    from fakes import make_patch_set

    return make_patch_set(base, tmp_path_factory.mktemp("sample_patches"))


# ------------------------------------------------------------------------------------------------ RealSense live
@pytest.fixture(scope="module")
def rs():
    """pyrealsense2 (skipped without it; under CI=true a failure)."""
    from fakes import need_realsense

    return need_realsense()


@pytest.fixture(scope="module")
def played(tmp_path_factory) -> Path:
    """The played frames of cup_handover (``fakes.PLAYED``) as a recording folder of their own (the offline
    reference)."""
    from fakes import PLAYED, SAMPLE, write_recording
    from massviz.io.recording import open_recording

    sample = open_recording(SAMPLE)
    frames = list(sample.frames(indices=PLAYED))
    root = tmp_path_factory.mktemp("played") / "played"
    return write_recording(root, [f.rgb for f in frames], [f.depth for f in frames],
                           intrinsics=sample.intrinsics.to_dict(), meta={"id": "played", "fps": 10})


@pytest.fixture(scope="module")
def played_db3(rs, played, tmp_path_factory) -> Path:
    """A .db3 of the played frames, recorded at 10 fps in real time (so real-time playback takes 1.2 s)."""
    from massviz.io.formats.realsense_write import write_realsense
    from massviz.io.recording import open_recording

    return write_realsense(open_recording(played), tmp_path_factory.mktemp("db3") / "played.db3", pace=True)


@pytest.fixture(scope="module")
def depth_detector():
    from massviz.detect import make_detector

    return make_detector("depth", 0.4)


# ---------------------------------------------------------------------------------------- the logged dataset
#: CCM recording 618's intrinsics in the logged dataset
INTR_618 = {"fx": 922.7552, "fy": 922.7061, "cx": 640.0656, "cy": 354.5494, "width": 1280, "height": 720}


@pytest.fixture(scope="module")
def env(weights):
    """This process's environment with ``MASSVIZ_WEIGHTS`` the published weights."""
    return {**os.environ, "MASSVIZ_WEIGHTS": str(weights)}


@pytest.fixture(scope="session")
def logged(tmp_path_factory, shared_dir, samples_dir, weights) -> SimpleNamespace:
    """The samples and CCM 618 as one folder of massviz recordings (``dataset``: frames linked, not copied), logged
    with ``massviz log DATASET --rrd-dir OUT --cache CACHE`` (``out``, ``cache``, the command's ``stderr``) once per
    session: under xdist the first worker to need it logs it, the other waits for it (test_browser_dataset.py
    serves the same OUT). Tests only read OUT; the trace cache is test_dataset_catalog's (its extract and log runs
    use it)."""
    from filelock import FileLock

    root = session_base(tmp_path_factory) / "massviz-logged-dataset"
    done = SimpleNamespace(dataset=root / "ds", out=root / "out", cache=root / "cache", log=root / "log.stderr")
    with FileLock(str(root) + ".lock"):
        if not done.log.is_file():
            if root.exists():
                shutil.rmtree(root)
            root.mkdir()
            samples_and_618(done.dataset, shared_dir, samples_dir, INTR_618)
            run = run_massviz("log", done.dataset, "--detector", "depth", "--rrd-dir", done.out, "--cache",
                              done.cache, "--quiet", env={"MASSVIZ_WEIGHTS": str(weights)}, check=True)
            done.log.write_text(run.stderr)
    done.stderr = done.log.read_text()
    return done
