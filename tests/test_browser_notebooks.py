"""What a new user sees opening the notebooks the README's way, in Debian's Chromium.

1. JupyterLab started with the documented command (read from docs/notebooks.md, plus a free port on
   127.0.0.1, a random token and ``--allow-root``) opens notebook 01 with no "Build Recommended" dialog (dash's
   source extension must not trigger JupyterLab's build check); no process of the server outlives the test;
2. notebook 03 after Run All: the interactive panel shows the worst recording as displayed (every patch on "keep",
   the lifted pitcher flagged, the estimate with it), no toggle label is cut; "exclude track" on the pitcher lowers the
   estimate and its row stays listed with its toggle, and "keep" on that row restores the estimate (undo without
   re-running).

Uses the shared ``browser`` fixture (tests/conftest.py) and the helpers of tests/test_browser.py.
"""
from __future__ import annotations

import contextlib
import os
import re
import secrets
import shlex
import shutil
import sys
from pathlib import Path

import pytest

from browser_support import (
    ALL_RUN,
    BENIGN,
    ERRORS,
    FAILURE_PANEL,
    KERNEL_IDLE,
    PANEL_STATE,
    free_port,
    offline_page,
    server,
    shot,
    until,
)
from support import WEIGHTS
from support import sample_cache as fill_sample_cache

pytestmark = [pytest.mark.browser, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[1]


def readme_lab_command() -> list[str]:
    """The ``jupyter lab`` command of docs/notebooks.md, as argv."""
    section = (ROOT / "docs" / "notebooks.md").read_text()
    for block in re.findall(r"```(?:bash|sh|console)\n(.*?)```", section, re.S):
        for line in block.splitlines():
            if "jupyter lab" in line:
                return shlex.split(line.split("#", 1)[0])
    raise AssertionError("docs/notebooks.md has no `jupyter lab` command")


@pytest.fixture(scope="module")
def readme_lab(tmp_path_factory, shared_dir, samples_dir):
    """JupyterLab started as README says, in a copy of the repository's notebooks and scripts (nothing is saved into
    the repository), with Jupyter's per-user folders empty (a new user's) so that only the README command's own
    configuration counts. Yields (base URL, token, server process)."""
    argv = readme_lab_command()
    assert argv[:2] == [".venv/bin/jupyter", "lab"], argv
    root = tmp_path_factory.mktemp("readme_lab")
    shutil.copytree(ROOT / "notebooks", root / "notebooks")
    shutil.copytree(ROOT / "scripts", root / "scripts")
    (root / "data_samples").symlink_to(samples_dir)
    cache = fill_sample_cache(tmp_path_factory, shared_dir, samples_dir)
    user = root / "user"
    env = {k: v for k, v in os.environ.items() if k not in ("RERUN_NOTEBOOK_ASSET", "JUPYTER_CONFIG_PATH")}
    env.update(MASSVIZ_WEIGHTS=str(shared_dir / WEIGHTS), MASSVIZ_CACHE_DIR=str(cache), PYTHONWARNINGS="ignore",
               PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")])),
               JUPYTER_CONFIG_DIR=str(user / "config"), JUPYTER_DATA_DIR=str(user / "data"),
               JUPYTER_RUNTIME_DIR=str(user / "runtime"), IPYTHONDIR=str(user / "ipython"),
               JUPYTERLAB_SETTINGS_DIR=str(user / "settings"), JUPYTERLAB_WORKSPACES_DIR=str(user / "workspaces"),
               JUPYTER_PATH=os.pathsep.join(filter(None, [str(Path(sys.prefix) / "share" / "jupyter"),
                                                          env.get("JUPYTER_PATH")])),
               PATH=os.pathsep.join([str(Path(sys.executable).parent), env.get("PATH", "")]))
    port, token = free_port(), secrets.token_hex(16)
    # the README's arguments, run by this venv's python (-m jupyterlab is .venv/bin/jupyter lab)
    cmd = [sys.executable, "-m", "jupyterlab", *argv[2:], "--no-browser", "--allow-root",
           "--ServerApp.ip=127.0.0.1", f"--ServerApp.port={port}", "--ServerApp.port_retries=0",
           f"--IdentityProvider.token={token}", "--LabApp.expose_app_in_browser=True"]
    log = root / "jupyterlab.log"
    with contextlib.ExitStack() as stack:
        cwd = os.getcwd()
        os.chdir(root)  # README: run it from the repository's root (its --config path is relative)
        try:
            proc = stack.enter_context(server(cmd, f"http://127.0.0.1:{port}/lab?token={token}", log, env=env))
        finally:
            os.chdir(cwd)
        yield f"http://127.0.0.1:{port}", token, proc
    # nothing this server started may outlive the test: not its process group, not a kernel (their command lines
    # name connection files in this fixture's runtime folder)
    with pytest.raises(ProcessLookupError):
        os.killpg(proc.pid, 0)
    assert not survivors(str(root)), f"processes outlived JupyterLab: {survivors(str(root))}"


def survivors(marker: str) -> list[str]:
    out = []
    for cmdline in Path("/proc").glob("[0-9]*/cmdline"):
        with contextlib.suppress(OSError):
            text = cmdline.read_bytes().replace(b"\0", b" ").decode(errors="replace")
            if marker in text and cmdline.parent.name != str(os.getpid()):
                out.append(f"{cmdline.parent.name}: {text[:200]}")
    return out


def login(page, lab: str, token: str) -> None:
    page.goto(f"{lab}/lab?token={token}")  # sets the session cookie the later page loads use


def open_notebook(page, lab: str, name: str) -> None:
    """Open ``name`` (the README's command serves notebooks/ as JupyterLab's root) and wait for its tab."""
    page.goto(f"{lab}/lab/tree/{name}?reset")
    page.wait_for_function(f"() => window.jupyterapp && window.jupyterapp.shell.currentWidget && "
                           f"window.jupyterapp.shell.currentWidget.title.label === {name!r}", timeout=120_000)


def run_all(page) -> None:
    """Run > Run All Cells through the page; wait until every code cell ran; fail on an error output."""
    page.wait_for_function(KERNEL_IDLE, timeout=120_000)
    n = page.evaluate("""() => { const w = window.jupyterapp.shell.currentWidget;
      window.jupyterapp.commands.execute('notebook:run-all-cells');
      return w.content.widgets.filter(c => c.model.type === 'code').length; }""")
    page.wait_for_function(ALL_RUN, arg=n, timeout=300_000, polling=500)
    errors = page.evaluate(ERRORS)
    assert not errors, f"a cell failed in the browser: {errors[0][:2000]}"


DIALOG = "() => [...document.querySelectorAll('.jp-Dialog')].map(d => d.innerText)"


def test_readme_jupyterlab_opens_without_build_dialog(browser, readme_lab):
    lab, token, proc = readme_lab
    with offline_page(browser, {"width": 1280, "height": 900}) as (page, messages, _):
        login(page, lab, token)
        name = "01_inspect_recording.ipynb"
        page.goto(f"{lab}/lab/tree/{name}?reset")
        # the notebook's tab, or a dialog in front of it (the build dialog blocks the tab)
        page.wait_for_function(f"() => document.querySelector('.jp-Dialog') || (window.jupyterapp && "
                               f"window.jupyterapp.shell.currentWidget && "
                               f"window.jupyterapp.shell.currentWidget.title.label === {name!r})", timeout=120_000)
        # JupyterLab asks the server's build check once the app has started; give its answer time to arrive
        page.wait_for_timeout(8000)
        dialogs = page.evaluate(DIALOG)
        shot(page, "readme_jupyterlab_notebook01")
        build = page.evaluate(f"() => fetch('{lab}/lab/api/build', {{headers: {{Authorization: 'token {token}'}}}})"
                              ".then(r => r.json())")
    assert not any("Build" in d for d in dialogs), f"JupyterLab showed a dialog: {dialogs}"
    assert not dialogs, dialogs
    # the check is off in the page, although dash's source extension would make it say "needed"
    config = page_config(lab, token)
    assert config.get("buildCheck") is False and config.get("buildAvailable") is False, config
    print("build check the server would report:", build)
    errors = [m for t, m in messages if t in ("error", "pageerror") and not BENIGN.search(m)]
    assert not errors, errors


def page_config(lab: str, token: str) -> dict:
    import json
    import urllib.request

    with urllib.request.urlopen(f"{lab}/lab?token={token}", timeout=30) as r:
        html = r.read().decode()
    m = re.search(r'<script id="jupyter-config-data" type="application/json">(.*?)</script>', html, re.S)
    assert m, "no page config in JupyterLab's page"
    return json.loads(m.group(1))


ROWS = """(sel) => { const p = document.querySelector(sel);
  return [...p.querySelectorAll('.widget-hbox')].filter(r => r.querySelector(':scope > .widget-vbox .widget-toggle-buttons'))
    .map(r => ({text: r.innerText,
                active: [...r.querySelectorAll('.widget-toggle-button.mod-active')].map(b => b.innerText.trim()),
                cut: [...r.querySelectorAll('.widget-toggle-button')].filter(b => b.scrollWidth > b.clientWidth + 1)
                       .map(b => b.innerText.trim())})); }"""

#: buttons of the panel whose label does not fit (CSS cuts it to "…")
CUT = """(sel) => [...document.querySelector(sel).querySelectorAll('button')]
  .filter(b => b.scrollWidth > b.clientWidth + 1).map(b => b.innerText.trim())"""


def test_notebook_03_panel_after_run_all_in_the_browser(browser, readme_lab):
    lab, token, _ = readme_lab
    with offline_page(browser, {"width": 1400, "height": 1000}) as (page, messages, _):
        login(page, lab, token)
        open_notebook(page, lab, "03_failure_cases.ipynb")
        run_all(page)
        panel = page.locator(FAILURE_PANEL).first
        panel.scroll_into_view_if_needed()
        state = page.evaluate(PANEL_STATE, FAILURE_PANEL)
        rows = page.evaluate(ROWS, FAILURE_PANEL)
        shot(page, "notebook03_after_run_all", panel)
        # as displayed: the worst recording with every chosen patch on "keep" and the pitcher flagged
        assert "estimate 57.4 g" in state["estimate"], state["estimate"]
        assert len(rows) == 5 and all(r["active"] == ["keep"] for r in rows), rows
        pitcher = [r for r in rows if "pitcher" in r["text"]]
        assert len(pitcher) == 3 and all("⚑ flagged" in r["text"] for r in pitcher), pitcher
        assert not any("excluded" in r["text"].split("\n")[0] for r in rows), rows
        assert not any(r["cut"] for r in rows), f"toggle labels cut: {[r['cut'] for r in rows]}"
        assert not page.evaluate(CUT, FAILURE_PANEL), f"button labels cut: {page.evaluate(CUT, FAILURE_PANEL)}"

        # exclude the pitcher's track, then undo it from its row (which stays listed, with its toggle)
        row = panel.locator(".widget-hbox").filter(has_text=re.compile(r"flagged \(.*\): .*pitcher")).filter(
            has=page.locator(".widget-toggle-buttons")).first
        row.locator("button", has_text="exclude track").click()
        until(page, "/estimate 8\\.3 g/.test(s.estimate)", FAILURE_PANEL)
        page.wait_for_function(f"(sel) => ({ROWS})(sel).some(r => r.text.includes('excluded by you'))",
                               arg=FAILURE_PANEL)
        rows = page.evaluate(ROWS, FAILURE_PANEL)
        shot(page, "notebook03_excluded_row", panel)
        excluded = [r for r in rows if "excluded by you" in r["text"]]
        assert len(excluded) == 1 and excluded[0]["active"] == ["exclude track"], rows
        assert "not flagged" not in excluded[0]["text"], excluded
        assert not page.evaluate(CUT, FAILURE_PANEL), f"button labels cut: {page.evaluate(CUT, FAILURE_PANEL)}"
        assert not any(r["cut"] for r in rows), f"toggle labels cut: {[r['cut'] for r in rows]}"
        undo = panel.locator(".widget-hbox").filter(has_text="excluded by you").filter(
            has=page.locator(".widget-toggle-buttons")).first
        undo.locator("button", has_text=re.compile(r"^keep$")).click()
        until(page, "/estimate 57\\.4 g/.test(s.estimate)", FAILURE_PANEL)
        page.wait_for_function(f"(sel) => ({ROWS})(sel).length === 5", arg=FAILURE_PANEL)  # the rows come last
        rows = page.evaluate(ROWS, FAILURE_PANEL)
        assert len(rows) == 5 and all(r["active"] == ["keep"] for r in rows), rows
    errors = [m for t, m in messages if t in ("error", "pageerror") and not BENIGN.search(m)]
    assert not errors, errors
