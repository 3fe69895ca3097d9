"""The benchmark scripts keep working as the library changes: every name they import from massviz exists (a renamed
function once broke ``benchmarks/log_vs_estimate.py`` unnoticed: its imports are inside functions, so only running
it showed it), and each one's ``--help`` runs."""
from __future__ import annotations

import ast
import importlib
import subprocess
import sys

import pytest

from support import ROOT

SCRIPTS = sorted((ROOT / "benchmarks").glob("*.py"))


def massviz_imports(path):
    """(module, name) of every ``from massviz... import name`` in the file, at any depth."""
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "massviz":
            for alias in node.names:
                yield node.module, alias.name
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] == "massviz":
                    yield alias.name, None


def test_there_are_benchmarks():
    assert len(SCRIPTS) >= 10, SCRIPTS


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda p: p.stem)
def test_every_massviz_name_a_benchmark_imports_exists(script):
    missing = []
    for module, name in massviz_imports(script):
        mod = importlib.import_module(module)
        if name is not None and not hasattr(mod, name):
            try:
                importlib.import_module(f"{module}.{name}")
            except ImportError:
                missing.append(f"{module}.{name}")
    assert not missing, f"{script.name} imports names massviz no longer has: {missing}"


@pytest.mark.slow
@pytest.mark.parametrize("script", SCRIPTS, ids=lambda p: p.stem)
def test_benchmark_help_runs(script):
    r = subprocess.run([sys.executable, str(script), "--help"], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 0 and "usage" in r.stdout.lower(), (r.returncode, r.stdout[-500:], r.stderr[-2000:])


@pytest.mark.slow
def test_gpu_benchmark_on_a_cpu_compares_like_with_like(tmp_path, weights):
    """``benchmarks/gpu.py --device cpu``, a few small frames: every row on the same frames, in one mode and batch,
    with a warm and a cold column, the paper's loop timed both ways, the relative estimate check, and the versions,
    the device and the load average printed with the table (the rules, not the speed)."""
    import json

    out = tmp_path / "gpu.json"
    r = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "gpu.py"), "--device", "cpu", "--frames", "2",
                        "--scenarios", "b", "--modes", "fp32", "--size", "320x180", "--weights", str(weights),
                        "--json", str(out)], capture_output=True, text=True, cwd=ROOT, timeout=1500)
    assert r.returncode == 0, (r.stdout[-2000:], r.stderr[-3000:])
    import torch
    import torchvision

    head = r.stdout.splitlines()[0]
    assert f"torch {torch.__version__}" in head and f"torchvision {torchvision.__version__}" in head, head
    assert "cpu" in head and "load average" in head and "2 distinct frames 320x180 in every row" in head, head
    assert "warm frames/s | cold s | cold frames/s" in r.stdout
    result = json.loads(out.read_text())
    rows = result["scenarios"]["b"]["rows"]
    assert [row["what"] for row in rows] == ["detector alone", "massviz end to end", "paper's loop"]
    assert {row["frames"] for row in rows} == {2} and {(row["mode"], row["batch"]) for row in rows} == {("fp32", 1)}
    assert all(row["warm_fps"] > 0 for row in rows), rows
    assert all(row["cold_s"] > 0 and row["cold_fps"] > 0 for row in rows[1:]), rows
    check = result["scenarios"]["b"]["estimate_checks"]["default"]
    assert check["relative"] is not None and check["within_half_percent"], check
    assert result["machine"]["torchvision"] == torchvision.__version__ and result["machine"]["load_average"]
