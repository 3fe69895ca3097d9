"""The package layout is the architecture (docs/architecture.md): these tests read every module's imports (also the
ones inside functions) and fail on an arrow that breaks it.

* ``massviz.core`` is the ground floor: it imports nothing of massviz but ``core`` and ``errors`` (no io, detect,
  view, command, evaluation, training, sample generator, runner or the builder ``massviz.app``);
* ``massviz.core`` does no file I/O: no ``open``, ``cv2.imread``, ``np.load``, ``Path.read_*``, ``torch.load`` ...
  (an AST scan of its calls);
* ``massviz.core`` never imports Open3D, directly or through a module it imports (and importing every core module
  leaves ``open3d`` out of ``sys.modules``): clouds and measured sizes are the measure stage's (``massviz.measure3d``);
* no two modules import each other, directly or round a longer circle (imports inside functions count);
* no stage (``core``, ``detect``, ``io``) imports a sink (``views``);
* no view imports a stage module for its logic (the pipeline, the builder, a detector) or a runner or command;
* no view calls the measure stage (``massviz.measure3d.stage``, or the geometry's cloud making and measuring): views
  draw the clouds and measurements they are given;
* no view imports a function that computes: the pipeline and its stage, the mass CNN, a detector, a measurement
  (a sink is given each frame's result and the trace; it draws them);
* no command imports another command (only the private helpers ``commands/_*.py``);
* no two modules of the package have the same file name (``__init__.py`` and the commands, which mirror the CLI's
  verbs, aside): a module is named for its job, and a name means one job;
* library code names no repository-relative path and never switches matplotlib's backend.
* no file of the test suite imports a test module (``test_*``): what tests share is in helper modules
  (``tests/fakes.py``, ``tests/support.py``, ...) and fixtures in ``tests/conftest.py``.

Each check is a function of the graph (or of a file), and ``test_the_checks_catch_*`` feed it a bad one.
"""
from __future__ import annotations

import ast
from pathlib import Path, PurePosixPath

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
    assert "massviz.core.pipeline" in MODULES and "massviz.views.rerun.trace_logger" in MODULES
    assert "massviz.core.detector" in GRAPH["massviz.core.pipeline"]
    assert "massviz.core.detector" in GRAPH["massviz.detect"]
    assert "massviz.core.trace" in GRAPH["massviz.views.rerun.trace_logger"]
    assert "massviz.io.ground_truth" in GRAPH["massviz.app"]  # an import inside a function


#: what core may import of massviz: itself and the errors.
CORE_MAY_IMPORT = ("core", "errors")


def core_arrows(graph) -> list:
    """Imports from ``massviz.core`` of anything but core and errors (io, detect, views, commands, evaluation,
    runners, training, samples, the builder ``massviz.app``, the CLI, the lazy top level)."""
    return sorted((m, t) for m, targets in graph.items() if under(m, "core") for t in targets
                  if not under(t, *CORE_MAY_IMPORT))


def test_core_imports_only_core():
    assert core_arrows(GRAPH) == []


def third_party_imports(path: Path) -> set[str]:
    """The top-level names of the packages outside massviz that ``path`` imports, at any depth of the file."""
    tree = ast.parse(path.read_text(), filename=str(path))
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            out.add(node.module.split(".")[0])
    return out - {"massviz"}


THIRD_PARTY = {module_name(p): third_party_imports(p) for p in FILES}


def open3d_in_core(graph, third_party) -> list[tuple[str, str]]:
    """(core module, the module of its imports' closure that imports Open3D) for every core module that reaches
    ``open3d`` (or ``massviz._open3d``), directly or through massviz modules it imports."""
    found = []
    for root in sorted(m for m in graph if under(m, "core")):
        seen, todo = set(), [root]
        while todo:
            m = todo.pop()
            if m in seen:
                continue
            seen.add(m)
            if "open3d" in third_party.get(m, ()) or "massviz._open3d" in graph.get(m, ()):
                found.append((root, m))
            todo.extend(graph.get(m, ()))
    return sorted(set(found))


def test_core_never_imports_open3d():
    assert open3d_in_core(GRAPH, THIRD_PARTY) == []
    # and at run time: importing every core module loads no Open3D (nor the measure stage)
    import subprocess
    import sys

    core = sorted(m for m in MODULES if under(m, "core"))
    code = (f"import importlib, sys\nfor m in {core!r}:\n    importlib.import_module(m)\n"
            "print('open3d' in sys.modules, any(m.startswith('massviz.measure3d') for m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=PKG.parent).stdout.strip()
    assert out == "False False"


def import_circles(graph) -> list[list[str]]:
    """Every set of modules that import each other round a circle (strongly connected components of more than one
    module, or a module importing itself), each sorted; Tarjan's algorithm, iterative."""
    index, low, on_stack, stack, out, counter = {}, {}, set(), [], [], [0]
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph.get(root, ()))))]
        index[root] = low[root] = counter[0]
        counter[0] += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            v, children = work[-1]
            for w in children:
                if w not in graph:
                    continue
                if w not in index:
                    index[w] = low[w] = counter[0]
                    counter[0] += 1
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph.get(w, ())))))
                    break
                if w in on_stack:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    component = []
                    while True:
                        w = stack.pop()
                        on_stack.discard(w)
                        component.append(w)
                        if w == v:
                            break
                    if len(component) > 1 or v in graph.get(v, ()):
                        out.append(sorted(component))
    return sorted(out)


def test_no_import_circle():
    assert import_circles(GRAPH) == []


#: calls that read or write files: plain names, and attribute names on any object (``cv2.imread``, ``np.load``,
#: ``path.read_text``, ``torch.save``, ``Image.open`` ...).
IO_NAMES = {"open"}
IO_ATTRIBUTES = {"open", "imread", "imwrite", "imdecode_file", "VideoCapture", "VideoWriter", "load", "save",
                 "savez", "savez_compressed", "fromfile", "tofile", "loadtxt", "savetxt", "genfromtxt", "memmap",
                 "read_text", "read_bytes", "write_text", "write_bytes", "mkdir", "unlink", "rmdir", "touch",
                 "iterdir", "glob", "rglob", "stat", "is_file", "is_dir", "exists", "read_csv", "to_csv",
                 "read_point_cloud", "write_point_cloud", "read_image", "write_image", "remove", "rmtree",
                 "copyfile", "copy", "move", "listdir", "scandir", "walk", "makedirs"}
#: attribute calls with these names that are not file I/O, by the object they are called on
NOT_IO = {("np", "copy"), ("numpy", "copy"), ("dataclasses", "replace")}


def file_io_calls(path: Path) -> list[str]:
    """``file:line call`` for every call in ``path`` that reads or writes a file (``IO_NAMES``, ``IO_ATTRIBUTES``)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    found = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        f = node.func
        if isinstance(f, ast.Name) and f.id in IO_NAMES:
            found.append(f"{path.name}:{node.lineno} {f.id}()")
        elif isinstance(f, ast.Attribute) and f.attr in IO_ATTRIBUTES:
            owner = f.value.id if isinstance(f.value, ast.Name) else ""
            if (owner, f.attr) not in NOT_IO and not (f.attr == "copy" and not node.args):  # arr.copy(): memory
                found.append(f"{path.name}:{node.lineno} {owner or '...'}.{f.attr}()")
    return found


def test_core_does_no_file_io():
    calls = [c for p in FILES if under(module_name(p), "core") for c in file_io_calls(p)]
    assert calls == []


def test_no_stage_imports_a_sink():
    assert arrows(["core", "detect", "io"], ["views"]) == []


#: layers that may not import a layer above them: io reads and writes files (no scores, tuning or sweeps), runners
#: run stages (signal handling comes from ``massviz.signals``, not from the command line).
LOWER_LAYERS = {"io": ("evaluation",), "runners": ("cli", "commands")}


def layer_arrows(graph) -> list:
    return sorted((m, t) for low, high in LOWER_LAYERS.items() for m, targets in graph.items() if under(m, low)
                  for t in targets if under(t, *high))


def test_io_imports_no_evaluation_and_runners_no_command_line():
    assert layer_arrows(GRAPH) == []


def test_the_checks_catch_io_importing_evaluation_and_a_runner_importing_the_cli():
    graph = {m: set(t) for m, t in GRAPH.items()}
    graph["massviz.io.patch_set"].add("massviz.evaluation.metrics")
    graph["massviz.runners.camera_loop"].add("massviz.cli")
    assert layer_arrows(graph) == [("massviz.io.patch_set", "massviz.evaluation.metrics"),
                                   ("massviz.runners.camera_loop", "massviz.cli")]


#: what a view may not import: the modules that compute (the per-frame step, the builder, detectors), runners,
#: commands, training. A view reads traces (core data types) and asks io for frames.
STAGES_FOR_VIEWS = ["core.pipeline", "app", "detect", "runners", "commands", "cli", "training"]


def view_arrows(graph) -> list:
    return sorted((m, t) for m, targets in graph.items() if under(m, "views") for t in targets
                  if under(t, *STAGES_FOR_VIEWS))


def test_views_import_no_stage_module_for_logic():
    assert view_arrows(GRAPH) == []


#: what a view may take from the measure stage's package: settings, the intrinsics check and back-projection for a
#: picture (the scene around the clouds, ``--points``) and the measured box as Open3D draws it; never a detection's
#: cloud, a measurement or the stage itself.
VIEW_MAY_USE_OF_MEASURE = {"DEPTH_TRUNC_M", "BAND_M", "skip_reason", "require_intrinsics", "pinhole", "rgbd_cloud",
                           "depth_to_points", "measured_box"}


def view_measure_calls(path: Path) -> list[str]:
    """What a view file takes from ``massviz.measure3d`` beyond ``VIEW_MAY_USE_OF_MEASURE``: ``line name`` for each
    name imported from it and each whole-module import (``import massviz.measure3d.stage``, ``from massviz.measure3d
    import stage``: its functions would be called through it)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("massviz.measure3d"):
            for a in node.names:
                if f"{node.module}.{a.name}" in MODULES or node.module == "massviz.measure3d" or \
                        a.name not in VIEW_MAY_USE_OF_MEASURE:
                    found.append(f"{node.lineno} {node.module}.{a.name}")
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("massviz.measure3d"):
                    found.append(f"{node.lineno} {a.name}")
    return found


def test_views_call_no_measure_stage():
    bad = {str(p.relative_to(PKG)): view_measure_calls(p) for p in FILES if under(module_name(p), "views")}
    assert {f: calls for f, calls in bad.items() if calls} == {}
    assert arrows(["views"], ["measure3d.stage"]) == []
#: what computes and so is no view's to call: the per-frame step and its stage (``core.pipeline``, ``core.frame_stage``),
#: the mass CNN's predictions (``core.model``), the detectors (``detect``) and the measure stage (``measure3d.stage``
#: and the geometry's cloud making and measuring). A sink is given results and traces; it draws them.
COMPUTE_FOR_VIEWS = {"massviz.core.pipeline": None, "massviz.core.frame_stage": None, "massviz.core.model": None,
                     "massviz.detect": None,
                     "massviz.measure3d.stage": None,
                     "massviz.measure3d.geometry": {"measure_cloud", "measure_cloud_as", "measure_crop",
                                                    "measure_detection", "detection_cloud", "masked_cloud"}}


def view_calls(sources: dict[str, str]) -> list[tuple[str, str]]:
    """(view module, ``module.name``) for every name a view imports from a module that computes
    (:data:`COMPUTE_FOR_VIEWS`; None: every name of it), at any depth of the file; ``sources``: module -> text."""
    out = []
    for module, text in sources.items():
        if not under(module, "views"):
            continue
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.ImportFrom) and node.module and not node.level:
                for target, names in COMPUTE_FOR_VIEWS.items():
                    if node.module == target or node.module.startswith(target + "."):
                        out += [(module, f"{node.module}.{a.name}") for a in node.names
                                if names is None or a.name in names]
            elif isinstance(node, ast.Import):
                out += [(module, a.name) for a in node.names for target, names in COMPUTE_FOR_VIEWS.items()
                        if names is None and (a.name == target or a.name.startswith(target + "."))]
    return sorted(out)


def test_views_call_no_pipeline_detector_or_measure_function():
    assert view_calls({module_name(p): p.read_text() for p in FILES}) == []


def test_the_checks_catch_a_view_calling_the_pipeline_a_detector_or_a_measurement():
    bad = {"massviz.views.rerun.bad": "def f(trace):\n"
                                      "    from massviz.measure3d.geometry import measure_crop, measured_box\n"
                                      "    from massviz.core.pipeline import run\n    import massviz.detect.depth\n"
                                      "    from massviz.detect.depth import DepthDetector\n",
           "massviz.views.fine": "from massviz.measure3d.geometry import measured_box\n"
                                 "from massviz.core.trace import Trace\n",
           "massviz.runners.logged": "from massviz.core.pipeline import run\n"}
    assert view_calls(bad) == [("massviz.views.rerun.bad", "massviz.core.pipeline.run"),
                               ("massviz.views.rerun.bad", "massviz.detect.depth"),
                               ("massviz.views.rerun.bad", "massviz.detect.depth.DepthDetector"),
                               ("massviz.views.rerun.bad", "massviz.measure3d.geometry.measure_crop")]


def test_no_command_imports_another_command():
    bad = [(m, t) for m, targets in GRAPH.items() if under(m, "commands") for t in targets
           if under(t, "commands") and t != m and not t.split(".")[-1].startswith("_") and t != "massviz.commands"]
    assert bad == []


#: the package's folder whose modules mirror the CLI's verbs (``massviz/cli.py`` finds a command by its name): a
#: command may have the file name of a library module (``commands/live.py`` runs ``massviz live``).
CLI_VERBS = "commands"


def same_file_names(paths) -> dict[str, list[str]]:
    """{file name: the modules that have it} for every file name two modules have; ``paths``: the modules' paths
    relative to ``massviz/`` (``core/trace.py``), ``__init__.py`` and the modules under ``CLI_VERBS`` left out."""
    by_name: dict[str, list[str]] = {}
    for path in map(PurePosixPath, paths):
        if path.name != "__init__.py" and path.parts[0] != CLI_VERBS:
            by_name.setdefault(path.name, []).append(str(path))
    return {name: sorted(found) for name, found in sorted(by_name.items()) if len(found) > 1}


def test_no_two_modules_have_the_same_file_name():
    assert same_file_names(p.relative_to(PKG).as_posix() for p in FILES) == {}


def test_the_checks_catch_two_modules_with_the_same_file_name():
    real = [p.relative_to(PKG).as_posix() for p in FILES]
    assert same_file_names([*real, "io/pipeline.py", "views/rerun/pipeline.py", "commands/pipeline.py"]) == {
        "pipeline.py": ["core/pipeline.py", "io/pipeline.py", "views/rerun/pipeline.py"]}
    assert same_file_names(["a/x.py", "b/c/x.py", "commands/x.py", "commands/_x.py", "__init__.py", "a/__init__.py",
                            "b/y.py"]) == {"x.py": ["a/x.py", "b/c/x.py"]}


@pytest.mark.parametrize("needle", ["../shared", "shared/weights", "matplotlib.use("])
def test_library_names_no_repository_path_and_keeps_the_backend(needle):
    hits = [str(p.relative_to(PKG.parent)) for p in FILES if needle in p.read_text()]
    assert hits == []


def test_the_checks_catch_a_bad_arrow(tmp_path):
    # a view that imports the pipeline is found by the same reader
    bad = tmp_path / "massviz" / "views" / "bad.py"
    bad.parent.mkdir(parents=True)
    bad.write_text("def f():\n    from massviz.core.pipeline import run\n")
    assert "massviz.core.pipeline" in imports_of(bad)


def test_the_checks_catch_core_importing_io_and_a_circle():
    # the real graph plus one bad arrow each: core importing io (inside a function, as the reader sees it) makes
    # both checks fail; a circle round three modules is found with its members
    graph = {m: set(t) for m, t in GRAPH.items()}
    graph["massviz.core.trace"].add("massviz.io.trace_file")
    assert core_arrows(graph) == [("massviz.core.trace", "massviz.io.trace_file")] and core_arrows(GRAPH) == []
    assert ["massviz.core.trace", "massviz.io.trace_file"] in import_circles(graph)
    for target in ("massviz.detect.depth", "massviz.views.plots", "massviz.commands.log", "massviz.runners.dataset",
                   "massviz.evaluation.metrics", "massviz.app"):
        assert core_arrows({"massviz.core.flags": {target}}) == [("massviz.core.flags", target)]
    ring = {"massviz.a": {"massviz.b"}, "massviz.b": {"massviz.c"}, "massviz.c": {"massviz.a"}, "massviz.d": {"massviz.a"}}
    assert import_circles(ring) == [["massviz.a", "massviz.b", "massviz.c"]]
    assert import_circles({"massviz.a": {"massviz.a"}}) == [["massviz.a"]]
    assert import_circles({"massviz.a": {"massviz.b"}, "massviz.b": set()}) == []


def test_the_checks_catch_file_io_in_core(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text("import cv2\nimport numpy as np\nfrom pathlib import Path\nimport torch\n"
                   "def f(p):\n    img = cv2.imread(p)\n    with open(p) as fh:\n        pass\n"
                   "    np.load(p)\n    Path(p).read_text()\n    torch.load(p)\n    return np.copy(img), img.copy()\n")
    assert sorted(c.split(" ", 1)[1] for c in file_io_calls(bad)) == sorted(
        ["cv2.imread()", "open()", "np.load()", "....read_text()", "torch.load()"])


def test_the_checks_catch_core_reaching_open3d():
    graph = {m: set(t) for m, t in GRAPH.items()}
    third_party = {m: set(t) for m, t in THIRD_PARTY.items()}
    # directly, through the library shim, and through a core module that imports one that does
    third_party["massviz.core.flags"].add("open3d")
    assert ("massviz.core.flags", "massviz.core.flags") in open3d_in_core(graph, third_party)
    assert ("massviz.core.trace", "massviz.core.flags") in open3d_in_core(graph, third_party)  # trace imports flags
    assert open3d_in_core({"massviz.core.x": {"massviz._open3d"}}, {}) == [("massviz.core.x", "massviz.core.x")]
    assert open3d_in_core({"massviz.core.x": {"massviz.core.y"}, "massviz.core.y": set()},
                          {"massviz.core.y": {"open3d"}}) == [("massviz.core.x", "massviz.core.y"),
                                                              ("massviz.core.y", "massviz.core.y")]
    assert core_arrows({"massviz.core.x": {"massviz.measure3d.geometry"}}) == [("massviz.core.x",
                                                                               "massviz.measure3d.geometry")]


def test_the_checks_catch_a_view_calling_the_measure_stage(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text("from massviz.measure3d.geometry import rgbd_cloud, detection_cloud\n"
                   "def f(t, r):\n    from massviz.measure3d.stage import MeasureStage\n"
                   "    from massviz.measure3d import stage\n    import massviz.measure3d.geometry as G\n"
                   "    return G.measure_cloud(MeasureStage(r).finish(t))\n")
    assert [c.split(" ", 1)[1] for c in view_measure_calls(bad)] == [
        "massviz.measure3d.geometry.detection_cloud", "massviz.measure3d.stage.MeasureStage", "massviz.measure3d.stage",
        "massviz.measure3d.geometry"]
    fine = tmp_path / "fine.py"
    fine.write_text("from massviz.measure3d.geometry import DEPTH_TRUNC_M, measured_box, rgbd_cloud\n")
    assert view_measure_calls(fine) == []


def test_the_checks_catch_a_view_importing_a_stage():
    graph = {"massviz.views.plots": {"massviz.core.trace", "massviz.app"},
             "massviz.views.widgets": {"massviz.detect.depth", "massviz.core.flags"}}
    assert view_arrows(graph) == [("massviz.views.plots", "massviz.app"),
                                  ("massviz.views.widgets", "massviz.detect.depth")]


def test_one_selection_one_score_formula_one_ground_truth_reader():
    # the K-nearest sort (by d) lives in core/selection.py, exp(-eps) in evaluation/metrics.py, meta.json's container
    # in core/types.py (GroundTruth.from_meta) and its one check in io/meta.py (check_meta); every other module calls
    # them. Other sorts (the device path orders patches and masks by size to pad them less) sort no d.
    def files_with(needle):
        return sorted(str(p.relative_to(PKG)) for p in FILES if needle in p.read_text())

    assert files_with("argsort(d") == ["core/selection.py"]
    assert [f for f in files_with("argsort(") if f != "core/selection.py"] == ["core/frame_stage.py", "core/resample.py"]
    assert files_with("np.exp(-") == ["evaluation/metrics.py"]  # the score's exp(-eps) (a softmax is no score)
    assert files_with('get("container")') == ["core/types.py", "io/meta.py"]


#: the CCM annotation CSV's columns: only its one reader (massviz/io/ccm_annotations.py) names them
CCM_COLUMNS = {"id", "container id", "container mass", "width at the top", "width at the bottom", "height", "depth",
               "container capacity"}


def files_naming(strings, files) -> dict[str, list[str]]:
    """{file: the ``strings`` it has as string constants (not counting docstrings)}, for the files that have some."""
    out = {}
    for p in files:
        tree = ast.parse(p.read_text(), filename=str(p))
        docs = {id(n.body[0].value) for n in ast.walk(tree) if isinstance(n, (ast.Module, ast.FunctionDef,
                ast.ClassDef, ast.AsyncFunctionDef)) and n.body and isinstance(n.body[0], ast.Expr)}
        found = sorted({n.value for n in ast.walk(tree) if isinstance(n, ast.Constant) and n.value in strings
                        and id(n) not in docs})
        if found:
            out[str(p.relative_to(PKG)) if PKG in p.parents else p.name] = found
    return out


def test_one_ccm_annotation_reader(tmp_path):
    # "height" and "id" are also other things' names: the columns that only an annotation file has are checked
    only_ccm = CCM_COLUMNS - {"id", "height", "depth"}
    assert files_naming(only_ccm, FILES) == {"io/ccm_annotations.py": sorted(only_ccm)}
    bad = tmp_path / "bad.py"
    bad.write_text('"""reads \'container mass\'"""\ndef f(row):\n    return row["container mass"], row["width at the top"]\n')
    assert files_naming(only_ccm, [bad]) == {"bad.py": ["container mass", "width at the top"]}  # not the docstring


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


def calls_of(text: str, names) -> set[str]:
    """The functions of ``names`` that ``text`` calls (plain or attribute calls), at any depth."""
    out = set()
    for node in ast.walk(ast.parse(text)):
        if isinstance(node, ast.Call):
            f = node.func
            name = f.id if isinstance(f, ast.Name) else f.attr if isinstance(f, ast.Attribute) else None
            if name in names:
                out.add(name)
    return out


#: what a finished trace's conclusion and overlays are logged with: called in one place, the one trace-to-Rerun path
ONE_PATH = {"log_predictions", "log_running", "log_events", "log_flags", "log_detections", "detection_class_ids"}


def test_one_path_from_a_finished_trace_to_rerun():
    # massviz log, the dataset's light recordings and massviz live log a finished trace's overlays, predictions,
    # decisions and flags through views/rerun/trace_logger.py (log_overlays, log_conclusion); the live sink's per-frame
    # overlays of a FrameResult are its own
    callers = {str(p.relative_to(PKG)): sorted(calls_of(p.read_text(), ONE_PATH)) for p in FILES}
    assert {f: c for f, c in callers.items() if c} == {
        "views/rerun/trace_logger.py": sorted(ONE_PATH),
        "views/rerun/live_logger.py": ["detection_class_ids", "log_detections"]}
    assert calls_of("def f(s, t):\n    rl.log_flags(s, t)\n    log_predictions(s, t)\n", ONE_PATH) == {
        "log_flags", "log_predictions"}


#: what only the one per-frame mapping calls: a processed frame's camera frustum, RGB, depth and points
PER_FRAME = {"frustum_depth", "log_frame", "log_depth", "log_points"}


def test_one_per_frame_mapping_for_log_and_live():
    # massviz log (TraceLogger) and massviz live (LiveLogger) log each processed frame's time, camera, RGB, depth and
    # points through views/rerun/frame_logger.py (FrameLogger)
    callers = {str(p.relative_to(PKG)): sorted(calls_of(p.read_text(), PER_FRAME)) for p in FILES}
    assert {f: c for f, c in callers.items() if c} == {"views/rerun/frame_logger.py": sorted(PER_FRAME)}
    assert calls_of("def f(s, r, fr):\n    log_depth(s, fr.depth)\n    r.log_frame(s, fr)\n", PER_FRAME) == {
        "log_depth", "log_frame"}


TESTS = PKG.parent / "tests"


def imported_test_modules(path: Path) -> list[str]:
    """The test modules (``test_*``) the file ``path`` imports, at any depth of the file (``import``, ``from ...
    import``, ``importlib.import_module("...")``)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    names = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            names += [node.module] if node.module else [a.name for a in node.names]  # ``from . import test_x``
        elif (isinstance(node, ast.Call) and getattr(node.func, "attr", getattr(node.func, "id", "")) in
              ("import_module", "__import__") and node.args and isinstance(node.args[0], ast.Constant)):
            names.append(str(node.args[0].value))
    return sorted({n for n in names if n.split(".")[0].startswith("test_")})


def test_no_test_module_imports_another():
    imported = {p.name: imported_test_modules(p) for p in sorted(TESTS.glob("*.py"))}
    assert {name: found for name, found in imported.items() if found} == {}


def test_the_checks_catch_a_test_module_importing_another(tmp_path):
    bad = tmp_path / "test_bad.py"
    bad.write_text("import json\nfrom fakes import scene\nfrom test_recording import write_recording\n\n\n"
                   "def test_x():\n    import test_pipeline\n    from . import test_selection\n"
                   "    importlib.import_module('test_live')\n")
    assert imported_test_modules(bad) == ["test_live", "test_pipeline", "test_recording", "test_selection"]
