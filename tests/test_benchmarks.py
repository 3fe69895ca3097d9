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
