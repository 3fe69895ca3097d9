"""The package layout is the architecture (README, "Architecture"): these tests read every module's imports (also the
ones inside functions) and fail on an arrow that breaks it.

* ``massviz.core`` imports no view, command, evaluation, training, sample generator or runner;
* no stage (``core``, ``detect``, ``io``) imports a sink (``views``);
* no view imports a stage module for its logic (the pipeline, the builder, a detector) or a runner or command;
* no command imports another command (only the private helpers ``commands/_*.py``);
* library code names no repository-relative path and never switches matplotlib's backend.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "massviz"


def module_name(path: Path) -> str:
    parts = list(path.relative_to(PKG.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def imports_of(path: Path) -> set[str]:
    """Every massviz module ``path`` imports, at any depth of the file (``from massviz.x import y`` counts as
    ``massviz.x.y`` when that is a module, else ``massviz.x``)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name.startswith("massviz")}
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("massviz") and not node.level:
            for a in node.names:
                full = f"{node.module}.{a.name}"
                out.add(full if full in MODULES else node.module)
    return out


FILES = sorted(PKG.rglob("*.py"))
MODULES = {module_name(p) for p in FILES}
GRAPH = {module_name(p): imports_of(p) for p in FILES}


def under(module: str, *packages: str) -> bool:
    return any(module == f"massviz.{p}" or module.startswith(f"massviz.{p}.") for p in packages)


def arrows(source_packages, target_packages, allowed=()):
    return sorted((m, t) for m, targets in GRAPH.items() if under(m, *source_packages)
                  for t in targets if under(t, *target_packages) and (m, t) not in allowed)


def test_the_graph_is_read():
    # the reader itself can fail: the CLI imports its commands' package, the pipeline its detector protocol
    assert "massviz.core.pipeline" in MODULES and "massviz.views.rerun_log" in MODULES
    assert "massviz.detect.base" in GRAPH["massviz.core.pipeline"]
    assert "massviz.core.trace" in GRAPH["massviz.views.rerun_log"]


def test_core_imports_no_view_command_evaluation_training_or_runner():
    assert arrows(["core"], ["views", "commands", "evaluation", "training", "samples", "runners", "cli"]) == []


def test_no_stage_imports_a_sink():
    assert arrows(["core", "detect", "io"], ["views"]) == []


def test_views_import_no_stage_module_for_logic():
    stages = ["core.pipeline", "app", "detect", "runners", "commands", "cli", "training"]
    assert arrows(["views"], stages) == []


def test_no_command_imports_another_command():
    bad = [(m, t) for m, targets in GRAPH.items() if under(m, "commands") for t in targets
           if under(t, "commands") and t != m and not t.split(".")[-1].startswith("_") and t != "massviz.commands"]
    assert bad == []


@pytest.mark.parametrize("needle", ["../shared", "shared/weights", "matplotlib.use("])
def test_library_names_no_repository_path_and_keeps_the_backend(needle):
    hits = [str(p.relative_to(PKG.parent)) for p in FILES if needle in p.read_text()]
    assert hits == []


def test_the_checks_catch_a_bad_arrow(tmp_path):
    # a view that imports the pipeline is found by the same reader
    bad = tmp_path / "massviz" / "views" / "bad.py"
    bad.parent.mkdir(parents=True)
    bad.write_text("def f():\n    from massviz.core.pipeline import process\n")
    assert "massviz.core.pipeline" in imports_of(bad)


def test_one_selection_one_score_formula_one_ground_truth_reader():
    # the K-nearest sort lives in core/selection.py, exp(-eps) in evaluation/metrics.py, meta.json's container in
    # core/types.py (GroundTruth.from_meta) and its one check in io/meta.py (check_meta); every other module calls them
    def files_with(needle):
        return sorted(str(p.relative_to(PKG)) for p in FILES if needle in p.read_text())

    assert files_with("argsort(") == ["core/selection.py"]
    assert files_with("np.exp(") == ["evaluation/metrics.py"]
    assert files_with('get("container")') == ["core/types.py", "io/meta.py"]


def test_help_start_up_loads_no_heavy_library():
    # `massviz --help` (and `import massviz`) must not load torch, open3d, pandas or rerun: commands import them
    # when they run
    import subprocess
    import sys

    code = ("import sys, io, contextlib\nfrom massviz.cli import build_parser\n"
            "with contextlib.redirect_stdout(io.StringIO()):\n    build_parser().format_help()\n"
            "import massviz\nprint(' '.join(m for m in ('torch', 'open3d', 'pandas', 'rerun', 'cv2') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == ""


def test_baseline_help_range_is_the_baselines_range():
    from massviz.commands import baseline as command
    from massviz.evaluation import baselines

    assert command.RANDOM_RANGE_G == baselines.RANDOM_RANGE_G
