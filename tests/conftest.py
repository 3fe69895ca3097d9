"""Shared fixtures.

``shared_dir`` is ../shared beside the project root (reference data read in place, never copied). Outside CI a test
that needs it is skipped when it is missing; under CI=true it fails instead.
"""
from __future__ import annotations

import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("MASSVIZ_SHARED", ROOT.parent / "shared"))
SAMPLES = ROOT / "data_samples"


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    if not SHARED.is_dir():
        msg = f"reference data folder {SHARED} is missing (tests read ../shared in place)"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(msg)
        pytest.skip(msg)
    return SHARED


@pytest.fixture(scope="session")
def samples_dir() -> Path:
    return SAMPLES


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
        msg = "browser tests need " + " and ".join(missing)
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(msg)
        pytest.skip(msg)
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=str(CHROMIUM), headless=True, args=CHROMIUM_ARGS)
        yield b
        b.close()
