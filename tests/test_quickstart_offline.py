"""The README's quickstart right after set-up, with no network and no ``$MASSVIZ_WEIGHTS``: the weights that
``scripts/setup.sh`` found beside the repository are found again from the user cache."""
from __future__ import annotations

import re
import subprocess
import sys

import pytest

from support import ROOT, WEIGHTS, run_massviz

pytestmark = pytest.mark.slow  # set-up's weights step and the quickstart, as subprocesses

#: a download address that answers nothing at once, as with no network
NO_NETWORK = "http://127.0.0.1:9/"


def setup_weights_step() -> str:
    """The weights step of scripts/setup.sh (from its marked ``if`` to its ``fi``), with this interpreter."""
    lines = (ROOT / "scripts" / "setup.sh").read_text().splitlines()
    start = next(i for i, ln in enumerate(lines) if "# setup: cache the reference weights" in ln)
    end = next(i for i in range(start, len(lines)) if lines[i].strip() == "fi")
    return "\n".join(lines[start:end + 1]).replace(".venv/bin/python", f'"{sys.executable}"')


def quickstart_first_line() -> list[str]:
    """The first command of the README's quickstart, as arguments after ``massviz``."""
    readme = (ROOT / "README.md").read_text()
    block = readme.split("## Quickstart", 1)[1]
    line = next(ln for ln in block.splitlines() if ln.startswith("$ massviz "))
    return line.split()[2:]


def test_the_quickstart_runs_offline_after_setup(tmp_path, shared_dir):
    assert (shared_dir / WEIGHTS).is_file()
    args = quickstart_first_line()
    assert args[:1] == ["log"] and "--rrd" in args
    args[args.index("--rrd") + 1] = str(tmp_path / "cup.rrd")
    env = {"MASSVIZ_CACHE_DIR": str(tmp_path / "cache"), "MASSVIZ_WEIGHTS_URL": NO_NETWORK}

    before = run_massviz(*args, "--quiet", env=env)  # without the set-up step: nothing to find offline
    assert before.returncode == 2 and "cannot download" in before.stderr, before.stderr

    step = subprocess.run(["bash", "-c", setup_weights_step()], cwd=ROOT, capture_output=True, text=True,
                          env={"PATH": "/usr/bin:/bin", "MASSVIZ_CACHE_DIR": env["MASSVIZ_CACHE_DIR"]}, timeout=120)
    assert step.returncode == 0, step.stderr
    assert "weights cached at" in step.stderr
    assert list((tmp_path / "cache" / "weights").glob("*.torch"))

    after = run_massviz(*args, "--quiet", env=env)
    assert after.returncode == 0, after.stderr
    assert re.search(r"cup_handover: \d+\.\d g", after.stderr) and (tmp_path / "cup.rrd").is_file()


def test_install_checkpoint_refuses_a_file_that_is_not_published(tmp_path, monkeypatch):
    from massviz.errors import WeightsError
    from massviz.io.weights import install_checkpoint

    monkeypatch.setenv("MASSVIZ_CACHE_DIR", str(tmp_path / "cache"))
    odd = tmp_path / "odd.torch"
    odd.write_bytes(b"not a checkpoint")
    with pytest.raises(WeightsError, match="not one of the published checkpoints"):
        install_checkpoint(odd)
    assert not (tmp_path / "cache").exists() or not any((tmp_path / "cache").rglob("*.torch"))
