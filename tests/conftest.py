"""Shared fixtures: the reference folders, the published weights, the samples' traces and the browser.

``shared_dir`` is ../shared beside the project root (reference data read in place, never copied). Outside CI a test
that needs it (or the weights in it) is skipped when it is missing; under CI=true it fails instead. Importable
helpers (the ``massviz`` command-line runner ``run_massviz``, ``ROOT``, ``WEIGHTS``) are in ``support.py``.

No process started by the suite outlives it (``no_process_outlives_the_suite``): the pytest process becomes a child
subreaper (Linux), so a server whose parent died (e.g. a wrapper's child) is re-parented to it instead of init; at
the end of the session every descendant that was not there at its start is an error, and is ended.
"""
from __future__ import annotations

import contextlib
import os
import sys
from pathlib import Path

import pytest
from support import SAMPLES, SHARED, WEIGHTS, end_processes, missing_reference, started_since
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
    from test_browser import CHROMIUM, CHROMIUM_ARGS

    if not CHROMIUM.is_file():
        missing.append(f"{CHROMIUM} (Debian's chromium; 'bash scripts/setup.sh test' installs it)")
    if missing:
        missing_reference("browser tests need " + " and ".join(missing))
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=str(CHROMIUM), headless=True, args=CHROMIUM_ARGS)
        yield b
        b.close()
