"""What a person sees, checked in a real browser: Debian's Chromium (headless, software WebGL through SwiftShader),
driven by the ``playwright`` package pointed at the system browser (no browser download).

1. the Rerun web viewer (``rerun --serve-web``) on the README's demo recording: the 2D view shows the frame with the
   chosen patch's box colour, every patch tile shows its patch, the 3D view is not blank, and the console has no error
   about massviz's data;
2. JupyterLab serving notebook 02: all cells run in the page, the K and threshold sliders are moved through the page
   (keyboard, typed readout) and the shown estimate, table and patch tiles change (notebook 03's panel, "exclude
   track" on the flagged pitcher and its undo, is run in the page the README's way: tests/test_browser_notebooks.py);
3. notebook 01's inline Rerun viewer renders with no network (massviz serves the viewer's code locally by default).

Servers bind 127.0.0.1 on free ports; the browser may only reach 127.0.0.1/localhost. Screenshots go to
``test-artifacts/screenshots/`` (``$MASSVIZ_TEST_ARTIFACTS`` overrides ``test-artifacts``), with the measured
slider-to-redraw times in ``browser_timings.json`` there. Select these tests with ``-m browser``, leave them out with
``-m "not browser"``. Outside CI they are skipped when Chromium or playwright is missing; under ``CI=true`` they fail.
"""
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
import pytest
from support import run_massviz

pytestmark = pytest.mark.browser

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


def picture_difference(a: np.ndarray, b: np.ndarray, px: int = 40, panel: float = 0.766, ignore=()) -> float:
    """How much two screenshots of the viewer differ where it matters: the largest mean absolute difference (0-255) of
    any ``px``-pixel block, left of Rerun's selection panel (the right ``1 - panel`` of the page, which shows each
    run's recording id, times and URL) and outside the ``ignore`` boxes (x1, y1, x2, y2: e.g. a server's port). A
    plot left empty, an empty table, another title or tile colour: tens."""
    if a is None or a.shape != b.shape:
        return 255.0
    w = int(a.shape[1] * panel)
    d = np.abs(a[:, :w].astype(np.int16) - b[:, :w].astype(np.int16)).mean(axis=2)
    for x1, y1, x2, y2 in ignore:
        d[y1:y2, x1:x2] = 0
    return float(max(d[y:y + px, x:x + px].mean() for y in range(0, d.shape[0], px) for x in range(0, w, px)))


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


def check_docs_picture(fresh: np.ndarray, name: str, **kw) -> None:
    """README's ``docs/NAME`` must look like the screenshot a browser test just took (``picture_difference``);
    ``MASSVIZ_REFRESH_DOCS=1`` copies the fresh one there first."""
    docs = ROOT / "docs" / name
    if os.environ.get("MASSVIZ_REFRESH_DOCS"):
        cv2.imwrite(str(docs), fresh)
    diff = picture_difference(cv2.imread(str(docs)), fresh, **kw)
    record_timing(f"docs_{name}_difference", round(diff, 1))
    print(f"docs/{name} against this run's screenshot: largest block difference {diff:.1f}")
    assert diff <= DOCS_MAX_DIFFERENCE, (f"docs/{name} is stale (a block differs by {diff:.0f} from this run's "
                                         "screenshot): run this test with MASSVIZ_REFRESH_DOCS=1 and commit it")


# ------------------------------------------------------------------------------------------------------ fixtures


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


@pytest.fixture(scope="module")
def cup(sample_traces, samples_dir):
    """(recording, trace) of the demo sample, from the session's trace cache."""
    from massviz.io.recording import open_recording

    trace = next(t for t in sample_traces if t.recording.id == "cup_handover")
    return open_recording(samples_dir / "cup_handover"), trace


@pytest.fixture(scope="module")
def demo_rrd(tmp_path_factory, sample_cache, weights, samples_dir) -> Path:
    """The README's demo recording (`massviz log data_samples/cup_handover --detector depth --rrd ...`)."""
    out = tmp_path_factory.mktemp("demo") / "cup_handover.rrd"
    run_massviz("log", samples_dir / "cup_handover", "--detector", "depth", "--rrd", out, "--cache", sample_cache,
                "--quiet", env={"MASSVIZ_WEIGHTS": weights}, check=True)
    return out


# ------------------------------------------------------------------------------------------- 1. Rerun web viewer
def expected_views(rec, trace):
    """What the viewer shows at its start (the last processed frame): that frame's RGB, the chosen boxes' colours
    there, and every chosen patch as the model saw it (BGR)."""
    from massviz.core.patches import crop, model_view

    last = int(trace.frames[-1])
    frame = rec.read_frame(last)
    dets = trace.detections
    from massviz.views.palette import CHOSEN_COLOUR, FLAGGED_COLOUR, rgb255

    def colour(i: int):
        flag = trace.flags.of(int(i))
        return rgb255(FLAGGED_COLOUR if flag is not None and flag.flagged else CHOSEN_COLOUR)

    colours = [colour(i) for i in trace.selection if int(dets.frame[i]) == last]
    patches = []
    for i in trace.selection:
        i = int(i)
        patch = dets.patches[i] if dets.patches[i] is not None else crop(rec.read_frame(int(dets.frame[i])).rgb,
                                                                          dets.xyxy[i])
        patches.append(cv2.cvtColor(model_view(patch), cv2.COLOR_RGB2BGR))
    return cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR), colours, patches


def check_viewer(image: np.ndarray, frame: np.ndarray, colours, patches) -> dict:
    """Pixel checks of one screenshot of the default layout; returns what was measured and a list of failures."""
    out = {"failures": []}
    # a small screenshot (the notebook's inline viewer) is searched at full size and finer scales: shrunk, the frame
    # there is too small for the correlation to find its place
    small = image.shape[1] <= 1400
    score, (x1, y1, x2, y2) = find(image, frame, np.arange(0.5, 2.01, 0.02 if small else 0.05),
                                   reduce=1.0 if small else 0.5)
    out["rgb_match"] = round(score, 3)
    if score < 0.6:
        out["failures"].append(f"the 2D view does not show the recording's frame (best match {score:.2f})")
        return out
    view = image[y1:y2, x1:x2]
    out["box_pixels"] = {str(c): colour_pixels(view, c, tol=30) for c in colours}
    for c, n in out["box_pixels"].items():
        if n < 50:
            out["failures"].append(f"the chosen patch's box colour {c} is not in the 2D view ({n} pixels)")
    out["patch_match"] = []
    w, h = x2 - x1, y2 - y1
    grid = image[:y2 + h // 4, x2:]  # the patch tiles are right of the RGB view (default_blueprint)
    for r, p in enumerate(patches):
        s, _ = find(grid, p, np.arange(0.3, 1.51, 0.05))
        out["patch_match"].append(round(s, 3))
        if s < 0.6:
            out["failures"].append(f"patch tile ★{r} does not show its patch (best match {s:.2f})")
    # the 3D view is the right half of the row below the RGB view (default_blueprint)
    region = image[int(y2 + 0.2 * h):int(y2 + 0.7 * h), int(x1 + 0.55 * w):int(x2 - 0.05 * w)]
    out["3d_coloured"] = round(saturated_fraction(region), 3)
    # a blank view has ~0 %; the 3D view starts oblique and backed off, so the cloud covers a small part
    # of it (8 % in the notebook's 640-pixel-high inline viewer, where the region also takes in the time panel)
    if out["3d_coloured"] < 0.04:
        out["failures"].append(f"the 3D view is blank ({out['3d_coloured']:.0%} coloured pixels)")
    return out


def wait_for_viewer(page, name: str, expected, timeout: float = LOAD_TIMEOUT_S, locator=None):
    """Screenshots until every pixel check passes (the viewer has loaded the recording) or ``timeout``."""
    t0 = time.monotonic()
    while True:
        image = shot(page, name, locator)
        result = check_viewer(image, *expected)
        result["seconds"] = round(time.monotonic() - t0, 1)
        print(f"{name} at {result['seconds']} s: {result['failures'] or 'all checks pass'}")
        if not result["failures"] or time.monotonic() - t0 > timeout:
            return result
        page.wait_for_timeout(2000)


@contextlib.contextmanager
def massviz_view(rrd: Path, log: Path):
    """``massviz view RRD`` as a user starts it; yields (its process, the page URL it printed). Ended by SIGTERM, as
    a service manager or ``kill PID`` ends it, when the block ends."""
    with open(log, "w") as err:
        proc = subprocess.Popen([sys.executable, "-m", "massviz", "view", str(rrd)], cwd=ROOT, stdout=subprocess.PIPE,
                                stderr=err, text=True)
    try:
        lines = []
        while not any("Ctrl-C" in line for line in lines):
            lines.append(proc.stdout.readline())
            assert lines[-1] or proc.poll() is None, f"massviz view exited: {log.read_text()}"
        yield proc, re.search(r"open in a browser: (\S+)", "".join(lines)).group(1)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        proc.wait(30)


@pytest.mark.slow
def test_rerun_web_viewer_shows_the_demo_recording(browser, demo_rrd, cup, tmp_path):
    """README's way to look at a recording on a machine without a display, ``massviz view OUT.rrd``: the page it
    prints shows the recording in Chromium; it listens on 127.0.0.1 only, costs no CPU while the page is open and
    idle, and ends whole on SIGTERM (``rerun --serve-web FILE``, what this test ran before, kept a core busy and,
    started through Rerun's Python wrapper, left its server running when the wrapper was killed)."""
    import psutil

    rec, trace = cup
    expected = expected_views(rec, trace)
    with massviz_view(demo_rrd, tmp_path / "view.log") as (proc, url), \
            offline_page(browser, VIEWER) as (page, messages, _):
        tree = [psutil.Process(proc.pid), *psutil.Process(proc.pid).children(recursive=True)]
        listening = [(p.name(), c.laddr.ip) for p in tree for c in p.net_connections(kind="inet")
                     if c.status == psutil.CONN_LISTEN]
        page.goto(url)
        result = wait_for_viewer(page, "rerun_web_viewer", expected)
        settle(page, "rerun_web_viewer")  # (the time cursor plays to the end of the recording, then stops)
        for p in tree:
            p.cpu_percent()
        time.sleep(3)
        idle_cpu = {p.name(): p.cpu_percent() for p in tree}
        record_timing("massviz_view_idle_cpu_percent", idle_cpu)
        print("massviz view: listening on", listening, "; CPU while idle (%, over 3 s):", idle_cpu)
    assert proc.returncode == 0, (tmp_path / "view.log").read_text()
    assert len(listening) == 2 and all(ip == "127.0.0.1" for _, ip in listening), listening
    assert sum(idle_cpu.values()) < 5.0, idle_cpu
    assert not [p for p in tree if p.is_running() and p.status() != psutil.STATUS_ZOMBIE], tree
    print("rerun web viewer:", result)
    assert not result["failures"], f"{result} (see {ARTIFACTS / 'rerun_web_viewer.png'})"
    # the 2D view fits the whole image (its right edge is not cropped): the frame's right-most tenth is found
    # at the right end of where the whole frame is found, at the same scale
    image = cv2.imread(str(ARTIFACTS / "rerun_web_viewer.png"))
    frame = expected[0]
    score, (x1, y1, x2, y2) = find(image, frame, np.arange(0.5, 2.01, 0.05), reduce=0.5)
    scale = (x2 - x1) / frame.shape[1]
    strip = frame[:, -frame.shape[1] // 10:]
    s_strip, (sx1, _, sx2, _) = find(image, strip, [scale])
    assert s_strip > 0.6 and abs(sx2 - x2) <= max(4, 0.02 * (x2 - x1)), (s_strip, (sx1, sx2), (x1, x2))
    check_docs_picture(image, "rerun_viewer.png")
    errors = [(t, m[:300]) for t, m in messages if t in ("error", "pageerror") and not BENIGN.search(m)]
    about_data = [(t, m[:300]) for t, m in messages if t in ("error", "warning") and OUR_ENTITIES.search(m)]
    assert not errors and not about_data, errors + about_data


@pytest.fixture(scope="module")
def rs_module():
    from test_realsense import need_realsense

    return need_realsense()


@pytest.mark.slow
def test_live_tiles_show_the_flag_in_the_browser(browser, rs_module, tmp_path_factory, tmp_path):
    """A live session whose nearest chosen patch is flagged (tests/test_live_tiles.py ``flagged_session``), opened
    with ``massviz view``: at the session's end the tile ★0 has the flagged colour's outline; the other tiles the
    chosen colour's (live logged every tile plain, whatever the flags said at the end)."""
    from test_live_tiles import flagged_session
    from test_recording import write_recording

    from massviz.io.formats.realsense_write import write_realsense
    from massviz.io.recording import open_recording
    from massviz.views.palette import CHOSEN_COLOUR, FLAGGED_COLOUR, rgb255
    from rrd_reader import rrd_rows

    sample = open_recording(ROOT / "data_samples" / "cup_handover")
    frames = list(sample.frames(indices=range(18, 30)))
    played = write_recording(tmp_path / "played", [f.rgb for f in frames], [f.depth for f in frames],
                             intrinsics=sample.intrinsics.to_dict(), meta={"id": "played", "fps": 10})
    db3 = write_realsense(open_recording(played), tmp_path / "played.db3")
    rrd = flagged_session(db3, tmp_path)
    patch0 = [row for row in rrd_rows(rrd, "/patches/0") if "d_mm" in row][-1]
    assert patch0["flagged"] == [True]
    with massviz_view(rrd, tmp_path / "view.log") as (proc, url), offline_page(browser, VIEWER) as (page, _, _):
        page.goto(url)
        t0, red = time.monotonic(), 0
        while time.monotonic() - t0 < LOAD_TIMEOUT_S:
            page.wait_for_timeout(2000)
            image = shot(page, "live_flagged_tiles")
            h, w = image.shape[:2]  # the tiles: above the predictions plot, between the 2D view and the side panel
            tiles = image[int(0.05 * h):int(0.3 * h), int(0.51 * w):int(0.77 * w)]
            red = colour_pixels(tiles, rgb255(FLAGGED_COLOUR), tol=30)
            pink = colour_pixels(tiles, rgb255(CHOSEN_COLOUR), tol=30)
            if red > 100 and pink > 100:
                break
    print(f"live tiles in the browser: {red} flagged-colour and {pink} chosen-colour pixels in the tiles' area")
    assert red > 100, f"no flagged tile outline in the browser ({red} pixels; see live_flagged_tiles.png)"
    assert pink > 100, f"no plain chosen tile outline ({pink} pixels; see live_flagged_tiles.png)"


# ------------------------------------------------------------------------------------------------ 2./3. notebooks
@pytest.fixture(scope="module")
def lab(tmp_path_factory, sample_cache, weights, samples_dir):
    """JupyterLab on 127.0.0.1 (no token) over a copy of notebooks/ (so nothing is saved into the repository), with
    ../data_samples beside it; kernels use this checkout, the published weights and the session's trace cache."""
    root = tmp_path_factory.mktemp("lab")
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
WATCH = """(sel) => { window.__mutations = []; window.__input = null;
  const p = document.querySelector(sel);
  new MutationObserver(() => { const t = performance.now();
      requestAnimationFrame(() => window.__mutations.push([t, performance.now()])); })
    .observe(p, {subtree: true, childList: true, characterData: true, attributes: true, attributeFilter: ['src']});
  for (const type of ['keydown', 'change']) document.addEventListener(type, () => {
      if (window.__input === null) window.__input = performance.now(); }, true); }"""


def slider_change(page, act, done: str) -> float:
    """Do ``act`` (an input through the page), wait until the panel shows ``done`` (JS predicate over PANEL_STATE's
    result ``s``) and no update has arrived for 1 s; returns ms from the input to the last redraw (next frame)."""
    page.evaluate(WATCH, PANEL)
    act()
    until(page, done)
    while True:  # settle: the last change (tiles, tables) may come after the estimate
        n = page.evaluate("window.__mutations.length")
        page.wait_for_timeout(1000)
        if page.evaluate("window.__mutations.length") == n:
            break
    t_input, mutations = page.evaluate("[window.__input, window.__mutations]")
    assert t_input is not None and mutations
    return round(mutations[-1][1] - t_input, 1)


def panel_slider(page, label: str):
    return page.locator(".jp-OutputArea-output .widget-slider").filter(
        has=page.locator(".widget-label", has_text=re.compile(rf"^{label}$"))).first


def test_notebook_02_sliders_in_the_browser(browser, lab, sample_traces):
    from massviz.views.widgets import Tuner

    tuner = Tuner(sample_traces, k=5, threshold=0.4)
    ids = [str(t.recording.id) for t in tuner.traces]
    cup = ids.index("cup_handover")
    tuner.update(k=6)
    expected_k6 = tuner.current[cup].estimate
    tuner.update(k=5, threshold=0.99)  # which recording's chosen patches change at threshold 0.99, if any
    changed = [j for j in range(len(ids)) if tuner.current[j].selection.tolist() != tuner.traces[j].selection.tolist()
               or tuner.current[j].estimate != tuner.traces[j].estimate]
    with offline_page(browser, {"width": 1280, "height": 1000}) as (page, messages, _):
        run_s = open_and_run(page, lab, "02_tune_threshold_and_k.ipynb")
        panel = page.locator(".jp-OutputArea-output .widget-vbox").first
        panel.scroll_into_view_if_needed()
        panel.locator(".widget-dropdown select").first.select_option(label="cup_handover")
        until(page, "s.estimate.includes('cup_handover')")
        before = page.evaluate(PANEL_STATE, PANEL)
        assert "K=5" in before["estimate"] and len(before["tiles"]) == 5, before

        # K: 5 -> 6 with the keyboard on the slider's handle
        handle = panel_slider(page, "K").locator(".noUi-handle")
        k_ms = slider_change(page, lambda: (handle.focus(), page.keyboard.press("ArrowRight")),
                             "s.estimate.includes('K=6')")
        after = page.evaluate(PANEL_STATE, PANEL)
        shot(page, "notebook02_k6", panel)
        assert f"{expected_k6:.1f} g" in after["estimate"] and after["estimate"] != before["estimate"], after
        assert after["tables"][0] != before["tables"][0] and len(after["tiles"]) == 6

        # stride: 1 -> 2 with the keyboard (every other frame: other patches, images, tables), then back
        stride = panel_slider(page, "stride").locator(".noUi-handle")
        s_ms = slider_change(page, lambda: (stride.focus(), page.keyboard.press("ArrowRight")),
                             "s.estimate.includes('stride 2')")
        strided = page.evaluate(PANEL_STATE, PANEL)
        assert strided["tables"][0] != after["tables"][0] and len(strided["tiles"]) == 6, strided
        slider_change(page, lambda: (stride.focus(), page.keyboard.press("ArrowLeft")),
                      "s.estimate.includes('stride 1')")

        # threshold: typed into the slider's readout, on a recording whose chosen patches it changes (the recording
        # picked in the dropdown: every tile's image and caption change)
        others = [j for j in range(len(ids)) if j != cup]
        show = ids[next((j for j in others if j in changed), others[0])]
        r_ms = slider_change(page, lambda: panel.locator(".widget-dropdown select").first.select_option(label=show),
                             f"s.estimate.includes({json.dumps(show)})")
        before = page.evaluate(PANEL_STATE, PANEL)
        assert before["tiles"] != after["tiles"], (before, after)
        readout = panel_slider(page, "threshold").locator(".widget-readout")

        # typed into the readout first; the change is Enter (timing the typing would time Playwright's key events)
        readout.click()
        page.keyboard.press("Control+A")
        page.keyboard.type("0.99")
        t_ms = slider_change(page, lambda: page.keyboard.press("Enter"), "s.estimate.includes('threshold 0.99')")
        after = page.evaluate(PANEL_STATE, PANEL)
        shot(page, "notebook02_threshold", panel)
        assert after["estimate"] != before["estimate"]
        if ids.index(show) in changed:
            assert after["tables"][0] != before["tables"][0] and after["tiles"] != before["tiles"], (before, after)
    load = round(os.getloadavg()[0], 1)
    record_timing("notebook02", {"run_all_s": round(run_s, 1), "k_slider_ms": k_ms, "stride_slider_ms": s_ms,
                                 "threshold_slider_ms": t_ms, "recording_ms": r_ms, "load_1min": load})
    print(f"notebook 02 in the browser: run all {run_s:.1f} s; slider to redraw: K {k_ms} ms, stride {s_ms} ms, "
          f"threshold {t_ms} ms, recording {r_ms} ms (load {load})")
    errors = [m for t, m in messages if t in ("error", "pageerror") and not BENIGN.search(m)]
    assert not errors, errors


def test_notebook_01_inline_rerun_viewer_renders_offline(browser, lab, cup):
    rec, trace = cup
    expected = expected_views(rec, trace)
    with offline_page(browser, {"width": 1280, "height": 1000}) as (page, messages, blocked):
        open_and_run(page, lab, "01_inspect_recording.ipynb", upto="plots.best_frame")
        canvas = page.locator(".jp-OutputArea-output canvas").first
        canvas.wait_for(state="visible", timeout=120_000)
        canvas.scroll_into_view_if_needed()
        result = wait_for_viewer(page, "notebook01_inline_viewer", expected, locator=canvas)
    print("notebook 01 inline viewer:", result, "blocked requests:", blocked[:5])
    assert not result["failures"], f"{result} (see {ARTIFACTS / 'notebook01_inline_viewer.png'})"
