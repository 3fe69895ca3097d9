"""Servers: ``massviz serve`` listens on 127.0.0.1 only (the catalog server and the web viewer: every listening
socket of its process tree is listed), and a hostile .rrd in the served folder (garbage, empty, cut off in its
header, a folder named ``x.rrd``, a link to a device) is one warning line naming it while the rest is served."""
from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from fakes import copy_sample

ROOT = Path(__file__).resolve().parents[1]

HOSTILE_RRDS = {
    "garbage": lambda p: p.write_bytes(os.urandom(3000)),
    "empty": lambda p: p.write_bytes(b""),
    "folder": lambda p: p.mkdir(),
    "header-only": lambda p: p.write_bytes(b"RRF2"),
    "link-to-dev-zero": lambda p: p.symlink_to("/dev/zero"),
}


@pytest.fixture(scope="module")
def dataset(base, tmp_path_factory) -> Path:
    from massviz import cli

    root = tmp_path_factory.mktemp("served")
    out = root / "out"
    code = cli.main(["log", str(copy_sample(root / "rec")), "--rrd-dir", str(out), "--detector", "replay", "--replay",
                     str(base.replay), "--weights", str(base.weights), "--no-cache", "--quiet"])
    assert code == 0 and (out / "cup_handover.rrd").is_file()
    for name, make in HOSTILE_RRDS.items():
        make(out / f"{name}.rrd")
    return out


@pytest.mark.slow
@pytest.mark.parametrize("web", [True, False], ids=["with-web-viewer", "catalog-only"])
def test_serve_listens_on_localhost_only_and_skips_hostile_rrds_with_one_line_each(web, dataset):
    import psutil

    env = {k: v for k, v in os.environ.items() if k not in ("MASSVIZ_DEBUG", "RUST_LOG")}
    env["PYTHONPATH"] = str(ROOT)
    argv = [sys.executable, "-m", "massviz", "serve", str(dataset), *([] if web else ["--no-web-viewer"])]
    proc = subprocess.Popen(argv, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        lines, t0 = [], time.monotonic()
        while time.monotonic() - t0 < 120 and not any("Ctrl-C" in line for line in lines):
            lines.append(proc.stdout.readline())
            assert lines[-1] or proc.poll() is None, proc.stderr.read()
        time.sleep(0.5)
        tree = [psutil.Process(proc.pid), *psutil.Process(proc.pid).children(recursive=True)]
        listening = [c.laddr for p in tree for c in p.net_connections(kind="inet") if c.status == psutil.CONN_LISTEN]
    finally:
        proc.send_signal(signal.SIGTERM)
        code = proc.wait(30)
    err = proc.stderr.read()
    assert listening and {a.ip for a in listening} == {"127.0.0.1"}, listening
    assert len(listening) == (2 if web else 1), listening
    assert re.search(r"dataset 'out': 1 recording\(s\)", "".join(lines)), lines
    warnings = [line for line in err.splitlines() if "warning" in line]
    named = sorted(re.match(r"massviz: warning: (\S+): .*; not served$", line).group(1) for line in warnings)
    assert named == sorted(str(dataset / f"{n}.rrd") for n in HOSTILE_RRDS), err
    assert code == 0 and "Traceback" not in err


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_live_serve_web_listens_on_localhost_only():
    """``massviz live --serve-web``'s server (Rerun's binary: gRPC and the web viewer): every socket it listens on is
    127.0.0.1, and it is gone once stopped."""
    import psutil

    from massviz.commands.live import _WebServer

    web, grpc = _free_port(), _free_port()
    server = _WebServer(web, grpc)
    try:
        proc = psutil.Process(server.proc.pid)
        tree = [proc, *proc.children(recursive=True)]
        listening = [c.laddr for p in tree for c in p.net_connections(kind="inet") if c.status == psutil.CONN_LISTEN]
    finally:
        server.stop()
    assert {a.port for a in listening} >= {web, grpc}, listening
    assert {a.ip for a in listening} == {"127.0.0.1"}, listening
    assert not proc.is_running() or proc.status() == psutil.STATUS_ZOMBIE
