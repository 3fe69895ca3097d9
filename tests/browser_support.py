"""What the browser tests share: Debian's Chromium and its flags, local servers (a command's HTTP server, a static
file server), screenshots and template matching, the pictures in docs/, and JupyterLab pages (open a notebook, run
it, read its panel). The ``browser`` and ``lab`` fixtures built on it are in ``conftest.py``."""
from __future__ import annotations

import contextlib
import json
import os
import platform
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path
from urllib.parse import quote

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
ARTIFACTS = Path(os.environ.get("MASSVIZ_TEST_ARTIFACTS", ROOT / "test-artifacts")) / "screenshots"
CHROMIUM = Path(os.environ.get("MASSVIZ_CHROMIUM", "/usr/bin/chromium"))
CHROMIUM_ARGS = ["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 "--disable-quic", "--disable-dev-shm-usage", "--disable-renderer-backgrounding",
                 "--disable-background-timer-throttling", "--disable-backgrounding-occluded-windows"]
LOCAL_URL = re.compile(r"^(https?://(127\.0\.0\.1|localhost)(:\d+)?/|data:|blob:)")
VIEWER = {"width": 1280, "height": 800}
LOAD_TIMEOUT_S = 120
#: console lines of Rerun's own page offline (web fonts, the welcome screen's examples), not about massviz's data
BENIGN = re.compile(r"net::ERR_FAILED|ERR_NAME_NOT_RESOLVED|ERR_INTERNET_DISCONNECTED|Failed to fetch|"
                    r"Failed to load examples|fonts\.g", re.I)
OUR_ENTITIES = re.compile(r"/(camera|world|patches|predictions|log|summary|timings)\b")


# ------------------------------------------------------------------------------------------------------- helpers
def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_http(url: str, proc: subprocess.Popen, log: Path, timeout: float = 90) -> None:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        if proc.poll() is not None:
            raise AssertionError(f"server exited ({proc.returncode}): {log.read_text()[-2000:]}")
        with contextlib.suppress(OSError):
            with urllib.request.urlopen(url, timeout=5) as r:
                if r.status == 200:
                    return
        time.sleep(0.3)
    raise AssertionError(f"{url} did not answer within {timeout} s: {log.read_text()[-2000:]}")


@contextlib.contextmanager
def server(cmd: list[str], url: str, log: Path, env: dict | None = None):
    """Run a server (own process group, so its children go too) until the block ends."""
    with open(log, "w") as out:
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, env=env, start_new_session=True)
    try:
        wait_http(url, proc, log)
        yield proc
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(15)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(5)


@contextlib.contextmanager
def file_server(path: Path):
    """``path`` served over HTTP on 127.0.0.1 (a free port, any origin may read it) until the block ends; yields its
    URL."""
    import functools
    import http.server
    import threading

    class Handler(http.server.SimpleHTTPRequestHandler):
        def end_headers(self):
            self.send_header("Access-Control-Allow-Origin", "*")  # the viewer's page is on another port
            super().end_headers()

        def log_message(self, *args):
            pass

    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0),
                                            functools.partial(Handler, directory=str(path.parent)))
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{httpd.server_address[1]}/{quote(path.name)}"
    finally:
        httpd.shutdown()
        httpd.server_close()
        thread.join(5)


def shot(page, name: str, locator=None) -> np.ndarray:
    """Screenshot (the page, or one element) saved as an artefact; returns it as a BGR array."""
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    path = ARTIFACTS / f"{name}.png"
    (locator or page).screenshot(path=str(path), timeout=120_000)
    return cv2.imread(str(path))


def wait_for_image(page, name: str, locator, template: np.ndarray, scales, timeout: float, *,
                   at_least: float = 0.6) -> float:
    """Screenshot ``locator`` (saved as ``name``) every 2 s until ``template`` (BGR) is found in it with a
    correlation of ``at_least`` (``find`` over ``scales``) or ``timeout`` seconds pass; returns the best last match."""
    t0, match = time.monotonic(), -1.0
    while time.monotonic() - t0 < timeout and match < at_least:
        page.wait_for_timeout(2000)
        match, _ = find(shot(page, name, locator), template, scales)
    return match


#: Rerun's web viewer sizes its time panel once, when it first draws it expanded: a quarter of the page's height,
#: 150 to 250 px. Drawn while the canvas is still being sized it gets 150 px, drawn after it 191 px on an 800 px
#: page: a race between loading and layout that moved every view by 40 px from one machine to another. On a page
#: this high the panel is a collapsed bar (the viewer expands it on pages over 600 px), so it is first drawn
#: expanded when the page is made its full size, at the size that page gives it.
FIRST_DRAW = {"width": 1280, "height": 600}


def open_rerun_viewer(page, url: str, frame: np.ndarray, viewport: dict = VIEWER,
                      timeout: float = LOAD_TIMEOUT_S) -> float:
    """Opens Rerun's web viewer at ``url`` on a ``FIRST_DRAW`` page until the recording's ``frame`` (BGR) is shown,
    then makes the page ``viewport``'s size; returns the frame's match. The layout is then the same on every
    machine, whatever the order in which the viewer loaded the recording and sized its canvas."""
    page.set_viewport_size(FIRST_DRAW)
    page.goto(url)
    match = wait_for_image(page, "rerun_first_draw", None, frame, np.arange(0.3, 2.01, 0.05), timeout)
    page.set_viewport_size(viewport)
    return match


def find(image: np.ndarray, template: np.ndarray, scales, reduce: float = 1.0
         ) -> tuple[float, tuple[int, int, int, int]]:
    """Best normalised correlation of ``template`` (BGR) in ``image`` over ``scales`` (searched on both shrunk by
    ``reduce``): (score, (x1, y1, x2, y2)) in ``image``'s pixels."""
    gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if reduce != 1.0:
        gray = cv2.resize(gray, None, fx=reduce, fy=reduce, interpolation=cv2.INTER_AREA)
    best = (-1.0, (0, 0, 0, 0))
    for s in scales:
        t = cv2.cvtColor(cv2.resize(template, None, fx=s * reduce, fy=s * reduce, interpolation=cv2.INTER_AREA),
                         cv2.COLOR_BGR2GRAY)
        if t.shape[0] >= gray.shape[0] or t.shape[1] >= gray.shape[1] or min(t.shape) < 8:
            continue
        res = cv2.matchTemplate(gray, t, cv2.TM_CCOEFF_NORMED)
        _, score, _, (x, y) = cv2.minMaxLoc(res)
        if score > best[0]:
            best = (float(score), tuple(int(round(v / reduce)) for v in (x, y, x + t.shape[1], y + t.shape[0])))
    return best


def colour_pixels(image: np.ndarray, rgb, tol: int = 40) -> int:
    bgr = np.array(rgb[::-1], np.int16)
    return int((np.abs(image.astype(np.int16) - bgr).max(axis=2) <= tol).sum())


def saturated_fraction(image: np.ndarray) -> float:
    hsv = cv2.cvtColor(image, cv2.COLOR_BGR2HSV)
    return float(((hsv[..., 1] > 100) & (hsv[..., 2] > 60)).mean()) if image.size else 0.0


def record_timing(key: str, value) -> None:
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    path = ARTIFACTS / "browser_timings.json"
    data = json.loads(path.read_text()) if path.is_file() else {}
    data[key] = value
    path.write_text(json.dumps(data, indent=1) + "\n")


#: the side of the square blocks screenshots are compared by (``block_differences``), pixels
BLOCK_PX = 40


def block_differences(a: np.ndarray, b: np.ndarray, px: int = BLOCK_PX, panel: float = 0.766, ignore=()):
    """Mean absolute difference (0-255) of each ``px``-pixel block of two screenshots of the viewer, left of Rerun's
    selection panel (the right ``1 - panel`` of the page, which shows each run's recording id, times and URL) and
    outside the ``ignore`` boxes (x1, y1, x2, y2: e.g. a server's port): {(x, y): difference}; None when the
    shapes differ."""
    if a is None or a.shape != b.shape:
        return None
    w = int(a.shape[1] * panel)
    d = np.abs(a[:, :w].astype(np.int16) - b[:, :w].astype(np.int16)).mean(axis=2)
    for x1, y1, x2, y2 in ignore:
        d[y1:y2, x1:x2] = 0
    return {(x, y): float(d[y:y + px, x:x + px].mean()) for y in range(0, d.shape[0], px) for x in range(0, w, px)}


def picture_difference(a: np.ndarray, b: np.ndarray, **kw) -> float:
    """How much two screenshots of the viewer differ where it matters: the largest block difference
    (``block_differences``; 255 when the sizes differ). A plot left empty, an empty table, another title or tile
    colour: tens."""
    blocks = block_differences(a, b, **kw)
    return 255.0 if blocks is None else max(blocks.values())


def settle(page, name: str, timeout: float = 30.0, locator=None) -> np.ndarray:
    """Screenshots until two in a row are the same (``picture_difference`` ≤ 2: the viewer has stopped playing and
    loading) or ``timeout``; returns the last, saved as ``name``."""
    t0, before = time.monotonic(), shot(page, name, locator)
    while time.monotonic() - t0 < timeout:
        page.wait_for_timeout(1500)
        now = shot(page, name, locator)
        if picture_difference(before, now) <= 2.0:
            return now
        before = now
    return before


#: README's screenshots are the browser tests' own: a committed one differing more than this from a fresh one is stale
DOCS_MAX_DIFFERENCE = 20.0


def check_docs_picture(fresh: np.ndarray, name: str, *, retake=None, timeout: float = 0.0, page=None,
                       **kw) -> np.ndarray:
    """README's ``docs/NAME`` must look like the screenshot a browser test just took (``picture_difference``);
    ``MASSVIZ_REFRESH_DOCS=1`` copies the fresh one there first. With ``retake`` (a function taking a new
    screenshot), screenshots are taken again for up to ``timeout`` seconds until one matches: a viewer on a loaded
    machine may still be loading or playing when it first looks still. A stale picture fails naming the block that
    differs most, with both pictures and their difference saved beside the screenshots (``NAME`` .fresh/.diff.png)
    and, given the ``page``, the browser's graphics (a renderer other than the committed picture's draws points and
    images differently). Returns the screenshot that matched."""
    docs = ROOT / "docs" / name
    if os.environ.get("MASSVIZ_REFRESH_DOCS"):
        cv2.imwrite(str(docs), fresh)
    committed = cv2.imread(str(docs))
    t0 = time.monotonic()
    diff = picture_difference(committed, fresh, **kw)
    while diff > DOCS_MAX_DIFFERENCE and retake is not None and time.monotonic() - t0 < timeout:
        time.sleep(2.0)
        fresh = retake()
        diff = picture_difference(committed, fresh, **kw)
    record_timing(f"docs_{name}_difference", round(diff, 1))
    print(f"docs/{name} against this run's screenshot: largest block difference {diff:.1f}")
    if diff <= DOCS_MAX_DIFFERENCE:
        return fresh
    stem = ARTIFACTS / Path(name).stem
    cv2.imwrite(f"{stem}.fresh.png", fresh)
    blocks = block_differences(committed, fresh, **kw)
    if blocks is not None:
        (x, y), _ = max(blocks.items(), key=lambda kv: kv[1])
        cv2.imwrite(f"{stem}.diff.png", np.abs(committed.astype(np.int16) - fresh.astype(np.int16)).astype(np.uint8))
        px = kw.get("px", BLOCK_PX)
        where = f" at x {x}-{x + px}, y {y}-{y + px} px"
    else:
        where = f" (sizes {None if committed is None else committed.shape} and {fresh.shape})"
    graphics = f"; the browser draws with {page_graphics(page)}" if page is not None else ""
    raise AssertionError(f"docs/{name} is stale (a block differs by {diff:.0f}{where} from this run's screenshot, "
                         f"{stem}.fresh.png, difference {stem}.diff.png{graphics}): run this test with "
                         "MASSVIZ_REFRESH_DOCS=1 and commit it")


def page_graphics(page) -> str:
    """The page's WebGL renderer and whether it is offered a WebGPU adapter, in words."""
    return page.evaluate("""async () => {
        const gl = document.createElement('canvas').getContext('webgl2');
        const info = gl && gl.getExtension('WEBGL_debug_renderer_info');
        const webgl = info ? gl.getParameter(info.UNMASKED_RENDERER_WEBGL) : (gl ? 'WebGL2' : 'no WebGL2');
        let webgpu = 'no WebGPU';
        try { if (navigator.gpu && await navigator.gpu.requestAdapter()) webgpu = 'a WebGPU adapter'; } catch (e) {}
        return webgl + ', ' + webgpu;
    }""")


#: console.debug does nothing in the test pages: Rerun's web viewer (0.41) logs its shader compiler's (naga's) DEBUG
#: lines to the console, ~25,000 while it loads the demo, and each one crossed to this process as a Playwright event:
#: 11 s of this process's CPU and 10 s of the viewer test's load time. The tests read errors and warnings only.
QUIET_DEBUG = "console.debug = () => {};"


@contextlib.contextmanager
def offline_page(browser, viewport: dict):
    """A fresh browser context whose page may only reach this machine; collects console messages (not
    ``console.debug``: ``QUIET_DEBUG``)."""
    ctx = browser.new_context(viewport=viewport, device_scale_factor=1)
    page = ctx.new_page()
    page.set_default_timeout(60_000)
    messages, blocked = [], []
    page.on("console", lambda m: messages.append((m.type, m.text)))
    page.on("pageerror", lambda e: messages.append(("pageerror", str(e))))

    def route(r):
        if LOCAL_URL.match(r.request.url):
            r.continue_()
        else:
            blocked.append(r.request.url)
            r.abort()

    page.route("**/*", route)
    page.add_init_script(QUIET_DEBUG)
    try:
        yield page, messages, blocked
    finally:
        with contextlib.suppress(Exception):  # a notebook's kernel goes with its test
            page.evaluate("""() => { const w = window.jupyterapp && window.jupyterapp.shell.currentWidget;
                return w && w.sessionContext ? w.sessionContext.shutdown() : null; }""")
        ctx.close()


KERNEL_IDLE = """() => { const w = window.jupyterapp && window.jupyterapp.shell.currentWidget;
  const k = w && w.sessionContext && w.sessionContext.session && w.sessionContext.session.kernel;
  return !!k && k.status === 'idle'; }"""
ALL_RUN = """(n) => { const w = window.jupyterapp.shell.currentWidget;
  const cells = w.content.widgets.filter(c => c.model.type === 'code').slice(0, n);
  return cells.every(c => c.model.executionCount !== null) && w.sessionContext.session.kernel.status === 'idle'; }"""
ERRORS = """() => [...document.querySelectorAll('.jp-RenderedText[data-mime-type="application/vnd.jupyter.error"]')]
  .map(e => e.innerText)"""


def open_and_run(page, lab: str, name: str, upto: str | None = None) -> float:
    """Open a notebook in JupyterLab and run its code cells (all, or those before the first containing ``upto``)
    through the page; returns the seconds it took. Fails on an error output."""
    page.goto(f"{lab}/lab/tree/notebooks/{name}?reset")  # ?reset: not the tabs of an earlier test
    page.wait_for_function(f"() => window.jupyterapp && window.jupyterapp.shell.currentWidget && "
                           f"window.jupyterapp.shell.currentWidget.title.label === {json.dumps(name)}",
                           timeout=120_000)
    page.wait_for_function(KERNEL_IDLE, timeout=120_000)
    page.wait_for_timeout(500)  # the kernel's language_info reaches the model just after it is idle
    stored = json.loads((ROOT / "notebooks" / name).read_text())["metadata"]["language_info"]["version"]
    if stored == platform.python_version():  # (another Python's version would be recorded: modified)
        dirty = page.evaluate("() => window.jupyterapp.shell.currentWidget.context.model.dirty")
        assert not dirty, f"{name} opened marked modified in JupyterLab"
    t0 = time.monotonic()
    n = page.evaluate("""(upto) => { const w = window.jupyterapp.shell.currentWidget;
      const cells = w.content.widgets; let n = 0, stop = cells.length;
      for (let i = 0; i < cells.length; i++) {
        if (upto && cells[i].model.type === 'code' && cells[i].model.sharedModel.getSource().includes(upto)) {
          stop = i; break; }
        if (cells[i].model.type === 'code') n++; }
      w.content.activeCellIndex = Math.min(stop, cells.length - 1);
      window.jupyterapp.commands.execute(stop < cells.length ? 'notebook:run-all-above' : 'notebook:run-all-cells');
      return n; }""", upto)
    page.wait_for_function(ALL_RUN, arg=n, timeout=300_000, polling=500)
    errors = page.evaluate(ERRORS)
    assert not errors, f"{name}: a cell failed in the browser: {errors[0][:2000]}"
    return time.monotonic() - t0


#: the widget panel of a notebook (the first output VBox; in 03 the one with toggle buttons)
PANEL = ".jp-OutputArea-output .widget-vbox"
FAILURE_PANEL = ".jp-OutputArea-output .widget-vbox:has(.widget-toggle-buttons)"
STATE_FN = """function panelState(sel) { const p = document.querySelector(sel);
  const html = [...p.querySelectorAll('.widget-html-content')].map(e => e.innerText);
  return {estimate: html.find(t => / · K=\\d+, threshold /.test(t)) || '',
          tables: [...p.querySelectorAll('table')].map(t => t.innerText),
          tiles: [...p.querySelectorAll('img')].filter(i => i.offsetParent !== null)  // shown: not the spares
                  .map(i => i.src.length + ':' + i.src.slice(-64))}; }"""
PANEL_STATE = f"(sel) => {{ {STATE_FN}; return panelState(sel); }}"


def until(page, predicate: str, sel: str = PANEL, timeout: float = 60_000) -> None:
    """Wait until ``predicate`` (JS over ``s``, the panel's state) holds."""
    page.wait_for_function(f"(sel) => {{ {STATE_FN}; const s = panelState(sel); return {predicate}; }}", arg=sel,
                           timeout=timeout)


# ------------------------------------------------------------------------------------------------ 2./3. notebooks
@contextlib.contextmanager
def jupyterlab(root: Path, sample_cache: Path, weights: Path, samples_dir: Path):
    """JupyterLab on 127.0.0.1 (no token) over a copy of notebooks/ (so nothing is saved into the repository), with
    ../data_samples beside it, in ``root``; kernels use this checkout, the published weights and the session's trace
    cache. Yields its URL while it runs."""
    (root / "notebooks").mkdir()
    for nb in (ROOT / "notebooks").glob("*.ipynb"):
        shutil.copy(nb, root / "notebooks" / nb.name)
    (root / "data_samples").symlink_to(samples_dir)
    config = root / "config"
    (config / "labconfig").mkdir(parents=True)
    (config / "labconfig" / "page_config.json").write_text(json.dumps({"buildCheck": False, "buildAvailable": False}))
    settings = root / "settings" / "@jupyterlab" / "apputils-extension"
    settings.mkdir(parents=True)
    (settings / "notification.jupyterlab-settings").write_text(
        json.dumps({"fetchNews": "false", "checkForUpdates": False}))
    env = {k: v for k, v in os.environ.items() if k != "RERUN_NOTEBOOK_ASSET"}  # the default is what is tested
    env.update(MASSVIZ_WEIGHTS=str(weights), MASSVIZ_CACHE_DIR=str(sample_cache), PYTHONWARNINGS="ignore",
               PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")])),
               JUPYTER_CONFIG_DIR=str(config), JUPYTER_DATA_DIR=str(root / "data"),
               JUPYTER_RUNTIME_DIR=str(root / "runtime"), IPYTHONDIR=str(root / "ipython"),
               JUPYTER_PATH=os.pathsep.join(filter(None, [str(Path(sys.prefix) / "share" / "jupyter"),
                                                          env.get("JUPYTER_PATH")])),
               PATH=os.pathsep.join([str(Path(sys.executable).parent), env.get("PATH", "")]))
    port = free_port()
    cmd = [sys.executable, "-m", "jupyterlab", "--no-browser", "--allow-root", "--ServerApp.ip=127.0.0.1",
           f"--ServerApp.port={port}", "--ServerApp.port_retries=0", "--IdentityProvider.token=",
           "--ServerApp.password=", "--LabApp.expose_app_in_browser=True", f"--ServerApp.root_dir={root}",
           f"--LabApp.workspaces_dir={root / 'workspaces'}", f"--LabApp.user_settings_dir={root / 'settings'}"]
    with server(cmd, f"http://127.0.0.1:{port}/lab", root / "jupyterlab.log", env=env):
        yield f"http://127.0.0.1:{port}"
