"""The notebooks: stored without outputs, and executed top to bottom (headless, offline) on the bundled samples.

Execution uses the venv's ``python3`` kernel spec (ipykernel), cwd ``notebooks/``, the published weights by path
(``MASSVIZ_WEIGHTS`` from the ``weights`` fixture) and the session's trace cache of the samples
(the ``sample_cache`` fixture), so the notebooks read cached traces as a user's second run does.
"""
from __future__ import annotations

import logging
import os
import re
import sys
import time
from pathlib import Path

import nbformat
import pytest

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = ROOT / "notebooks"
NAMES = ["01_inspect_recording.ipynb", "02_tune_threshold_and_k.ipynb", "03_failure_cases.ipynb",
         "04_failure_browser.ipynb", "05_two_runs_and_patch_map.ipynb"]


@pytest.mark.parametrize("name", NAMES)
def test_notebook_is_stored_without_outputs(name):
    book = nbformat.read(NOTEBOOKS / name, as_version=4)
    nbformat.validate(book)
    code = [c for c in book.cells if c.cell_type == "code"]
    assert code, name
    for cell in code:
        assert cell.outputs == [], f"{name}: a code cell has stored outputs (clear them before committing)"
        assert cell.execution_count is None, f"{name}: a code cell has an execution count"


@pytest.mark.parametrize("name", NAMES)
def test_notebook_metadata_is_what_jupyterlab_would_write(name):
    """When its kernel starts, JupyterLab writes the kernel's ``language_info`` into the notebook: a notebook stored
    with less (``{"name": "python"}``) opened marked modified. They are stored as ipykernel reports them for the
    project's Python 3.11 (JupyterLab compares the whole object: with another Python version it still records that
    version). The browser tests check that a notebook opens unmodified (``test_browser.open_and_run``)."""
    from ipykernel.ipkernel import IPythonKernel

    meta = nbformat.read(NOTEBOOKS / name, as_version=4).metadata
    assert meta.kernelspec == {"display_name": "Python 3 (ipykernel)", "language": "python", "name": "python3"}
    expected = {k: v for k, v in IPythonKernel.language_info.items() if k != "version"}
    assert {k: v for k, v in meta.language_info.items() if k != "version"} == expected
    assert re.fullmatch(r"3\.11\.\d+", meta.language_info.get("version", "")), meta.language_info


def _kernel_env(weights: Path, cache: Path) -> dict:
    env = dict(os.environ)
    env.update(MASSVIZ_WEIGHTS=str(weights), MASSVIZ_CACHE_DIR=str(cache), PYTHONWARNINGS="ignore")
    # the kernel must be the venv's python (its kernel spec lives in sys.prefix/share/jupyter/kernels)
    env["JUPYTER_PATH"] = os.pathsep.join(filter(None, [str(Path(sys.prefix) / "share" / "jupyter"),
                                                         env.get("JUPYTER_PATH")]))
    env["PATH"] = os.pathsep.join([str(Path(sys.executable).parent), env.get("PATH", "")])
    return env


def _outputs_text(book) -> str:
    parts = []
    for cell in book.cells:
        for out in cell.get("outputs", []):
            if out.get("output_type") == "stream":
                parts.append(out.get("text", ""))
            elif "data" in out:
                parts.append(str(out["data"].get("text/plain", "")))
                parts.append(str(out["data"].get("text/html", "")))
    return "\n".join(parts)


#: what the notebook client logged while running each notebook (warnings and above)
CLIENT_LOG: dict[str, list[str]] = {}
#: lines that must not clutter a notebook's outputs (Open3D's WebVisualizer, Filament's start-up) or the run's log
CLUTTER = ("WebVisualizer", "WebRTC", "FEngine", "Vulkan device driver", "No handler found for comm target")


class _Collect(logging.Handler):
    def __init__(self):
        super().__init__(logging.WARNING)
        self.lines: list[str] = []

    def emit(self, record):
        self.lines.append(record.getMessage())


@pytest.fixture(scope="module")
def executed(weights, sample_cache):
    """Run the notebooks once (in order, sharing one trace cache); returns {name: executed notebook}."""
    from jupyter_client.kernelspec import KernelSpecManager
    from nbclient import NotebookClient

    env = _kernel_env(weights, sample_cache)
    spec = KernelSpecManager().get_kernel_spec("python3")
    assert Path(spec.argv[0]).resolve().parent == Path(sys.executable).resolve().parent or spec.argv[0] in (
        "python", "python3", sys.executable), f"python3 kernel spec is not the venv's python: {spec.argv}"
    out, seconds = {}, {}
    for name in NAMES:
        book = nbformat.read(NOTEBOOKS / name, as_version=4)
        t0 = time.perf_counter()
        client = NotebookClient(book, timeout=300, kernel_name="python3",
                                resources={"metadata": {"path": str(NOTEBOOKS)}})
        handler = _Collect()
        client.log.addHandler(handler)  # e.g. "No handler found for comm target 'dash'" (a comm nobody handles)
        try:
            client.execute(env=env)
        finally:
            client.log.removeHandler(handler)
        CLIENT_LOG[name] = handler.lines
        seconds[name] = time.perf_counter() - t0
        out[name] = book
    print("notebook execution times (s):", {k: round(v, 1) for k, v in seconds.items()})
    return out


@pytest.mark.parametrize("name", NAMES)
def test_notebook_runs_top_to_bottom(executed, name):
    book = executed[name]
    for cell in book.cells:
        if cell.cell_type == "code":
            errors = [o for o in cell.outputs if o.get("output_type") == "error"]
            assert not errors, f"{name}: {errors[0]['ename']}: {errors[0]['evalue']}"
            assert cell.execution_count is not None


def test_notebook_01_shows_each_stage(executed):
    book = executed["01_inspect_recording.ipynb"]
    text = _outputs_text(book)
    assert "estimate" in text and "ground truth" in text
    assert "within 10 % of the final" in text  # the running estimate and how long it took to settle
    images = sum("image/png" in o.get("data", {}) for c in book.cells for o in c.get("outputs", []))
    assert images >= 6, f"expected the frame, depth, point cloud, patches, estimate and timings figures, got {images}"
    widgets = sum("application/vnd.jupyter.widget-view+json" in o.get("data", {})
                  for c in book.cells for o in c.get("outputs", []))
    assert widgets >= 1, "the inline Rerun viewer was not displayed"


def test_notebook_02_scores(executed):
    text = _outputs_text(executed["02_tune_threshold_and_k.ipynb"])
    assert "score" in text and "cup" in text and "glass" in text and "box" in text


def test_notebook_03_flags_the_pitcher(executed):
    text = _outputs_text(executed["03_failure_cases.ipynb"])
    assert "FLAGGED" in text and "pitcher" in text
    assert "after excluding the pitcher" in text
    assert "57.4 g -> 8.3 g" in text and "chosen frames [8, 9, 10] removed" in text  # one exclude-track
    assert "cues alone flag ['★0', '★1', '★2'] ; ground truth flags ['★0', '★1', '★2']" in text


def test_notebook_04_browses_the_dataset(executed):
    text = _outputs_text(executed["04_failure_browser.ipynb"])
    assert "3 recordings, 15 chosen patches, 3 of them flagged" in text
    assert "catalog and pandas agree: True (dataset folder), True (traces); flagged patches: pandas 3, catalog 3" in text
    assert "flagged only: 3 patches in 1 recording(s)" in text and "all: 15 patches" in text
    assert "cup_handover: 57.4 g -> 8.3 g without them (true 9.0 g); 0 unmatched" in text
    assert "opened cup_handover at frame" in text


def test_notebook_05_compares_two_runs_and_maps_the_patches(executed):
    text = _outputs_text(executed["05_two_runs_and_patch_map.ipynb"])
    assert "A: k=5 | B: k=10: 3 recordings, 3 with changed patches" in text
    assert "got better by > 0.1: ['cup_handover']" in text and "all: 3 recordings" in text
    assert "wrote 3 two-run recordings" in text
    assert re.search(r"30 patches, 3 flagged, layout: (t-SNE|umap|PCA)", text), text[-1500:]
    near = re.search(r"nearest to cup_handover/\S+: (.*)", text).group(1)
    assert near.count("(pitcher,") == 2 and near.index("(pitcher,") < near.index("(container,"), near
    assert "opened cup_handover at frame" in text


def test_notebook_01_shows_the_flags(executed):
    text = _outputs_text(executed["01_inspect_recording.ipynb"])
    assert "3 of 5 chosen patches look like another object (frames 8–10, track 1): without them 8.3 g" in text
    assert "★0 frame   9 track  1: FLAGGED" in text


@pytest.mark.parametrize("name", NAMES)
def test_notebook_outputs_are_not_cluttered(executed, name):
    outputs = _outputs_text(executed[name])
    for line in CLUTTER:
        assert line not in outputs, f"{name}: {line!r} in the outputs"
        assert not any(line in m for m in CLIENT_LOG.get(name, [])), f"{name}: {line!r} logged while running"


# ------------------------------------------------------------------------- notebook 03's panel after Run All
def _widget_states(book) -> dict:
    return book.metadata.get("widgets", {}).get("application/vnd.jupyter.widget-state+json", {}).get("state", {})


def _displayed_widget(book, source_start: str) -> str:
    """Model id of the widget the code cell starting with ``source_start`` displayed."""
    for cell in book.cells:
        if cell.cell_type == "code" and cell.source.startswith(source_start):
            for out in cell.outputs:
                view = out.get("data", {}).get("application/vnd.jupyter.widget-view+json")
                if view:
                    return view["model_id"]
    raise AssertionError(f"no cell starting with {source_start!r} displayed a widget")


def _descendants(states: dict, model_id: str) -> list[dict]:
    """The widget ``model_id`` and every widget under it (children), depth first, as their state dicts."""
    out, todo = [], [model_id]
    while todo:
        mid = todo.pop(0)
        state = states[mid]["state"]
        out.append(state)
        todo[:0] = [c.removeprefix("IPY_MODEL_") for c in state.get("children", [])]
    return out


def test_notebook_03_panel_after_run_all_is_as_displayed(executed):
    """A later cell must not change the interactive panel cell 9 displayed: after Run All it
    still shows the worst recording with every patch on "keep", the lifted pitcher flagged (not "excluded" and
    "not flagged" in green) and the estimate with the pitcher (57.4 g)."""
    book = executed["03_failure_cases.ipynb"]
    states = _widget_states(book)
    assert states, "the executed notebook stored no widget state"
    widgets = _descendants(states, _displayed_widget(book, "panel = FailurePanel"))
    toggles = [w for w in widgets if w["_model_name"] == "ToggleButtonsModel"]
    html_text = [w.get("value", "") for w in widgets if w["_model_name"] == "HTMLModel"]
    assert len(toggles) == 5, f"expected the 5 chosen patches' toggles, got {len(toggles)}"
    modes = [w["_options_labels"][w["index"]] for w in toggles]
    assert modes == ["keep"] * 5, f"the displayed panel was changed by a later cell: modes {modes}"
    assert not any("excluded by you" in t for t in html_text)
    assert any("estimate <b>57.4 g</b>" in t for t in html_text), [t for t in html_text if "estimate" in t]
    rows = [t for t in html_text if "frame " in t and " · track " in t and "pred " in t]
    pitcher = [t for t in rows if "pitcher" in t]
    assert len(pitcher) == 3 and all("⚑ flagged" in t for t in pitcher), pitcher
    assert not any("pitcher" in t and "not flagged" in t for t in rows)


def test_notebook_03_prints_the_real_exclusions_path(executed):
    """The re-estimate command names the file the notebook wrote (not a bare file name)."""
    import re

    from massviz.evaluation.failures import load_exclusions

    text = _outputs_text(executed["03_failure_cases.ipynb"])
    m = re.search(r"--exclude (\S+) --out", text)
    assert m, text[-2000:]
    path = Path(m.group(1))
    assert path.is_absolute() and path.is_file(), f"printed {path}, which is not the written file"
    assert len(load_exclusions(path)) > 0
