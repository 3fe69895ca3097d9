"""Every command that serves a browser until it is stopped stops while a page is open on it: ``massviz serve`` (the
catalog server and Rerun's web viewer), ``massviz view`` (the file server and the web viewer) and ``massviz live
--serve-web`` (Rerun's gRPC server and web viewer, playing a RealSense .db3), each with a page of Debian's Chromium
(through playwright, as ``test_browser.py``) open on the URL it printed and, where the page keeps a connection open
(the catalog server, the gRPC server), that connection checked first. SIGTERM, and Ctrl-C (SIGINT) for serve and view:
exit 0 within ``STOP_S`` seconds, and none of the command's child processes is left.

(``massviz serve`` used to stay up for as long as the page was open: Rerun's catalog server waits, when shut down,
for every open request to end, and a page's never does.)
"""
from __future__ import annotations

import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from support import CLEARED_ENV, ROOT, require_pyrealsense2, run_massviz

pytestmark = [pytest.mark.browser, pytest.mark.slow]

#: seconds a command may take to exit after the signal
STOP_S = 10
#: seconds a command may take to start and print its page
START_S = 180


@pytest.fixture(scope="module")
def served(tmp_path_factory, samples_dir, weights, sample_cache) -> Path:
    """A dataset folder of one light recording (``massviz log cup_handover --rrd-dir OUT``)."""
    out = tmp_path_factory.mktemp("served") / "out"
    run_massviz("log", samples_dir / "cup_handover", "--detector", "depth", "--weights", weights, "--cache",
                sample_cache, "--rrd-dir", out, "--quiet", check=True)
    return out


@pytest.fixture(scope="module")
def slow_db3(tmp_path_factory, samples_dir) -> Path:
    """cup_handover as a RealSense .db3 that plays back at 1 frame a second (36 s: the session is still running when
    the signal comes)."""
    require_pyrealsense2()
    from massviz.io.formats.realsense_write import write_realsense
    from massviz.io.recording import open_recording

    root = tmp_path_factory.mktemp("db3")
    rec = shutil.copytree(samples_dir / "cup_handover", root / "slow")
    meta = json.loads((rec / "meta.json").read_text())
    (rec / "meta.json").write_text(json.dumps({**meta, "id": "slow", "fps": 1}))
    return write_realsense(open_recording(rec), root / "slow.db3", pace=True)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Lines:
    """What a stream of a process writes, read by a thread as it comes (a full pipe would stall the process)."""

    def __init__(self, stream):
        self.lines: list[str] = []
        self._thread = threading.Thread(target=lambda: self.lines.extend(stream), daemon=True)
        self._thread.start()

    def text(self) -> str:
        return "".join(self.lines)

    def wait_for(self, marker: str, proc: subprocess.Popen, timeout: float = START_S) -> str:
        t0 = time.monotonic()
        while marker not in self.text():
            assert proc.poll() is None, f"exited ({proc.returncode}) before {marker!r}"
            assert time.monotonic() - t0 < timeout, f"no {marker!r} within {timeout} s"
            time.sleep(0.1)
        return self.text()

    def rest(self) -> str:
        self._thread.join(10)
        return self.text()


def commands(kind: str, request) -> tuple[list, str, str, str | None]:
    """(massviz's arguments, the stream that says where the page is, the pattern of the page's URL, the pattern of
    the port a page keeps a connection open to, if any)."""
    if kind == "serve":
        return (["serve", request.getfixturevalue("served")], "stdout", r"web viewer:\s+(\S+)",
                r"catalog server:\s+rerun\+http://127\.0\.0\.1:(\d+)")
    if kind == "view":
        return ["view", request.getfixturevalue("served") / "cup_handover.rrd"], "stdout", \
            r"open in a browser: (\S+)", None
    db3, weights = request.getfixturevalue("slow_db3"), request.getfixturevalue("weights")
    return (["live", "--file", db3, "--detector", "depth", "--weights", weights, "--no-cache", "--quiet",
             "--serve-web", "--web-port", free_port(), "--grpc-port", free_port()], "stderr",
            r"web viewer at (\S+)", r"url=rerun%2Bhttp%3A%2F%2F127\.0\.0\.1%3A(\d+)")


def connected_from_elsewhere(port: int, own: set[int]) -> list:
    """Established connections to 127.0.0.1:``port`` from processes other than ``own`` (the page's)."""
    import psutil

    return [c for c in psutil.net_connections("tcp") if c.status == psutil.CONN_ESTABLISHED and c.raddr
            and c.raddr.port == port and c.pid not in own]


@pytest.mark.parametrize("kind, signum", [("serve", signal.SIGTERM), ("serve", signal.SIGINT),
                                          ("view", signal.SIGTERM), ("view", signal.SIGINT),
                                          ("live", signal.SIGTERM)],
                         ids=["serve-SIGTERM", "serve-SIGINT", "view-SIGTERM", "view-SIGINT", "live-SIGTERM"])
def test_a_server_stops_on_its_signal_while_a_page_is_open(kind, signum, browser, request):
    import psutil

    args, where, page_re, held_re = commands(kind, request)
    env = {k: v for k, v in os.environ.items() if k not in (*CLEARED_ENV, "RUST_LOG")}
    proc = subprocess.Popen([sys.executable, "-m", "massviz", *map(str, args)], cwd=ROOT, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    out, err = Lines(proc.stdout), Lines(proc.stderr)
    context = browser.new_context(viewport={"width": 1280, "height": 800})
    try:
        said = (out if where == "stdout" else err).wait_for("Ctrl-C", proc)
        url = re.search(page_re, said).group(1)
        page = context.new_page()
        page.goto(url)
        tree = [psutil.Process(proc.pid), *psutil.Process(proc.pid).children(recursive=True)]
        children = tree[1:]
        assert children, "the web viewer runs in a child process"
        if held_re:  # the page holds its connection before the signal comes
            port, t0 = int(re.search(held_re, said).group(1)), time.monotonic()
            while not connected_from_elsewhere(port, {p.pid for p in tree}):
                assert time.monotonic() - t0 < 90, f"the page opened no connection to port {port}"
                time.sleep(0.5)
        else:
            page.wait_for_timeout(3000)
        assert proc.poll() is None, err.text()
        t0 = time.monotonic()
        proc.send_signal(signum)
        try:
            code = proc.wait(STOP_S)
        except subprocess.TimeoutExpired:
            pytest.fail(f"massviz {kind} still runs {STOP_S} s after {signal.Signals(signum).name} with a page open")
        took = time.monotonic() - t0
    finally:
        context.close()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    stderr = err.rest()
    print(f"massviz {kind}: exit {code} {took:.1f} s after {signal.Signals(signum).name}")
    assert code == 0, stderr[-2000:]
    assert "Traceback" not in stderr
    stopped = f"stopped: interrupted ({signal.Signals(signum).name})" if kind == "live" else f"massviz {kind}: stopped"
    assert stopped in stderr, stderr[-2000:]
    _, alive = psutil.wait_procs(children, timeout=1)
    assert not [p for p in alive if p.status() != psutil.STATUS_ZOMBIE], alive
