"""The README's first set-up command ends with `massviz log` on a bundled sample: its .rrd must hold every entity of the
documented tree, as `rerun rrd print -v` shows it."""
from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from support import run_massviz

pytestmark = pytest.mark.slow  # the README's demo command as a subprocess

ROOT = Path(__file__).resolve().parents[1]
CONTRACT = ["/camera", "/camera/rgb", "/camera/depth", "/camera/detections", "/camera/masks", "/world",
            "/log", "/predictions/estimate", "/predictions/ground_truth", "/predictions/running_estimate",
            "/latency/detect", "/predictions/estimate_without_flagged"]


def demo_command() -> list[str]:
    """The `massviz log ...` line of scripts/setup.sh's demo job, as arguments."""
    line = next(ln for ln in (ROOT / "scripts" / "setup.sh").read_text().splitlines()
                if "massviz log data_samples/" in ln)
    return line.split()[1:]  # drop ".venv/bin/massviz"


def test_readme_demo_rrd_holds_the_entity_tree(tmp_path, sample_cache, weights):
    readme = (ROOT / "README.md").read_text()
    assert "bash scripts/setup.sh demo" in readme and "bash scripts/setup.sh test" in readme
    args = demo_command()
    out = tmp_path / "demo.rrd"
    args[args.index("--rrd") + 1] = str(out)
    # the sample cache has the same settings: the detector need not run
    run = run_massviz(*args, "--cache", sample_cache, "--quiet", env={"MASSVIZ_WEIGHTS": weights})
    assert run.returncode == 0, run.stderr
    assert "cup_handover:" in run.stderr and "ground truth" in run.stderr
    rerun = shutil.which("rerun", path=str(Path(sys.executable).parent)) or shutil.which("rerun")
    printed = subprocess.run([rerun, "rrd", "print", "-v", str(out)], capture_output=True, text=True, timeout=300)
    assert printed.returncode == 0, printed.stderr
    entities = set(re.findall(r" - (/[A-Za-z0-9_/]+) - data columns", printed.stdout))
    k = 5
    expected = CONTRACT + [f"/patches/{r}" for r in range(k)] + [f"/predictions/patch_{r}" for r in range(k)]
    missing = [e for e in expected if e not in entities]
    assert not missing, f"missing from the demo .rrd: {missing}"
    assert any(e.startswith("/world/detections/") for e in entities)  # Open3D clouds of the detections
    assert "/camera/rgb@EncodedImage:blob" in printed.stdout  # a frame folder: compressed images
    assert "/camera/depth@EncodedDepthImage:blob" in printed.stdout  # the depth PNGs' own bytes
    # small by default: Rerun back-projects the depth itself (no /world/points), the depth PNGs are not decoded
    sample = ROOT / "data_samples" / "cup_handover"
    inputs = sum(p.stat().st_size for kind in ("rgb", "depth") for p in (sample / kind).iterdir())  # the frames
    # the patch tiles follow the running selection (JPEG tiles logged wherever a rank changes hands, ~120 logs on this
    # sample); a file-only stream is chunked by size, so the size does not vary with the machine's load; the budget
    # catches raw depth, points or frames
    assert out.stat().st_size <= 1.5 * inputs, f"demo .rrd {out.stat().st_size} B > 1.5 x the sample's frames, {inputs} B"
