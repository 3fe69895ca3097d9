"""Every network service massviz connects to — a Ray cluster (``--ray-address``), a running Rerun viewer or server
(``massviz live --connect``) — and a RealSense camera (``--camera``) get a bounded wait: where nothing answers, one
line naming the option and the address, exit 2, nothing written, within seconds (Ray itself retried for ever).
"""
from __future__ import annotations

import socket
import time

import pytest

from fakes import run_cli_as_user
from massviz.errors import MassvizError
from massviz.io.endpoint import host_port, reach, reach_grpc
from support import SAMPLES, WEIGHTS, run_massviz


def error_lines(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if line.strip()]


@pytest.fixture
def silent_port():
    """A port on 127.0.0.1 that accepts connections and never says anything (not a gRPC server)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(8)
        yield s.getsockname()[1]


@pytest.fixture
def closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]  # closed when the block ends: nothing listens there


def test_host_port_reads_addresses_and_urls_and_names_the_option_when_not():
    assert host_port("127.0.0.1:6379", "--ray-address") == ("127.0.0.1", 6379)
    assert host_port("rerun+http://127.0.0.1:9876/proxy", "--connect") == ("127.0.0.1", 9876)
    assert host_port("ray://head:10001", "--ray-address") == ("head", 10001)
    assert host_port("[::1]:5", "--x") == ("::1", 5)
    for bad in ("head", "127.0.0.1:99999", "rerun+http:///proxy"):
        with pytest.raises(MassvizError, match=r"^--connect .*: not an address"):
            host_port(bad, "--connect")


def test_a_closed_port_is_one_line_at_once(closed_port):
    t0 = time.monotonic()
    with pytest.raises(MassvizError) as err:
        reach_grpc("--ray-address", f"127.0.0.1:{closed_port}", "127.0.0.1", closed_port, timeout=5)
    assert time.monotonic() - t0 < 2
    assert str(err.value).startswith(f"--ray-address 127.0.0.1:{closed_port}: cannot connect to ")
    assert "\n" not in str(err.value)


def test_a_port_that_never_answers_gives_up_after_the_timeout(silent_port):
    t0 = time.monotonic()
    with pytest.raises(MassvizError, match=r"accepts connections but no gRPC server answered there within 1\.5 s"):
        reach_grpc("--connect", f"127.0.0.1:{silent_port}", "127.0.0.1", silent_port, timeout=1.5)
    assert 1.0 < time.monotonic() - t0 < 4
    assert reach("--connect", "x", "127.0.0.1", silent_port, timeout=1.5) > 0  # TCP alone does connect


def test_a_grpc_server_answers():
    rr = pytest.importorskip("rerun")
    server = rr.server.Server(host="127.0.0.1")
    try:
        host, port = host_port(server.url(), "--connect")
        reach_grpc("--connect", server.url(), host, port, timeout=5)
    finally:
        server.shutdown()


@pytest.mark.slow
def test_estimate_with_a_ray_address_where_nothing_answers(samples_dir, shared_dir, closed_port, tmp_path):
    """``--ray-address 127.0.0.1:PORT`` with nothing there: one line naming the option and the address, exit 2 and
    no CSV within seconds (Ray's own ``ray.init`` retried it for as long as it was left running)."""
    pytest.importorskip("ray")
    address = f"127.0.0.1:{closed_port}"
    t0 = time.monotonic()
    run = run_massviz("estimate", samples_dir, "--detector", "depth", "--engine", "ray", "--ray-address", address,
                      "--out", tmp_path / "x.csv", "--quiet", "--no-cache", timeout=120,
                      env={"MASSVIZ_WEIGHTS": shared_dir / WEIGHTS})
    seconds = time.monotonic() - t0
    assert run.returncode == 2, run.stderr
    [line] = error_lines(run.stderr)
    assert line.startswith(f"massviz estimate: error: --ray-address {address}: cannot connect to "), line
    assert "ray start --head" in line
    assert not (tmp_path / "x.csv").exists()
    assert seconds < 60, seconds


@pytest.mark.slow
def test_live_connect_where_no_viewer_listens(closed_port, weights, tmp_path):
    """``massviz live --connect URL`` with nothing at URL: one line naming --connect and the URL before the session
    starts (Rerun's sink retried in the background, then dropped the session's data)."""
    from fakes import need_realsense

    need_realsense()
    from massviz.io.formats.realsense_write import write_realsense
    from massviz.io.recording import open_recording

    sample = open_recording(SAMPLES / "cup_handover")
    db3 = write_realsense(sample, tmp_path / "cup.db3", pace=False)
    url = f"rerun+http://127.0.0.1:{closed_port}/proxy"
    run = run_massviz("live", "--file", db3, "--connect", url, "--detector", "depth", "--no-cache", "--quiet",
                      "--weights", weights, "--rrd", tmp_path / "live.rrd", timeout=120)
    assert run.returncode == 2, run.stderr
    [line] = error_lines(run.stderr)
    assert line.startswith(f"massviz live: error: --connect {url}: cannot connect to 127.0.0.1:{closed_port}"), \
        run.stderr
    assert not (tmp_path / "live.rrd").exists()


@pytest.mark.slow
def test_a_silent_camera_is_one_line_naming_the_option(monkeypatch, weights, tmp_path, capsys):
    """A camera that delivers no frame: the session ends after ``SILENCE_S`` with one line naming ``--camera`` and
    the serial, nothing written (a stand-in camera: librealsense's ``software_device`` that is never fed)."""
    from fakes import need_realsense

    need_realsense()
    from massviz.cli import main
    from massviz.core.types import Intrinsics
    from massviz.io.formats import realsense_live as realsense

    cam = realsense.SoftwareCamera([], Intrinsics(300.0, 300.0, 80.0, 60.0, 160, 120), fps=10, serial="4242")

    def open_camera(serial, width, height, fps):
        assert serial == "4242"
        return realsense.open_device_stream(cam.device, "stand-in camera #4242")

    monkeypatch.setattr(realsense, "open_camera", open_camera)
    code = main(["live", "--camera", "4242", "--detector", "depth", "--weights", str(weights), "--no-cache",
                 "--quiet", "--rrd", str(tmp_path / "live.rrd"), "--save", str(tmp_path / "rec")])
    err = capsys.readouterr().err
    assert code == 2, err
    last = error_lines(err)[-1]
    assert last == "massviz live: error: --camera 4242: stand-in camera #4242: no frame arrived in 5 s", err
    assert "Traceback" not in err
    assert not (tmp_path / "live.rrd").exists() and not (tmp_path / "rec").exists()


# ------------------------------------------------------------------------------------------------- massviz view
def test_view_bad_input_is_one_line(tmp_path):
    not_rrd = tmp_path / "notes.rrd"
    not_rrd.write_text("hello")
    for path, why in ((tmp_path / "missing.rrd", "no such .rrd file"), (not_rrd, "not a Rerun .rrd file")):
        run = run_cli_as_user("view", path)
        assert run.returncode == 2 and error_lines(run.stderr) == [f"massviz view: error: {path}: {why}"
                                                                  + (" (make one with: massviz log REC --rrd OUT.rrd)"
                                                                     if "not a" in why else "")], run.stderr


@pytest.mark.slow
def test_view_serves_on_localhost_only_and_ends_whole_on_sigterm(tmp_path):
    """``massviz view OUT.rrd``: two listening sockets (the web viewer, the file), both on 127.0.0.1; the file is
    readable by the viewer's page only (CORS); SIGTERM ends it with exit 0 and no process of it left."""
    import os
    import re
    import signal
    import subprocess
    import sys
    import urllib.parse
    import urllib.request

    import psutil
    import rerun as rr

    rrd = tmp_path / "x.rrd"
    stream = rr.RecordingStream("massviz")
    stream.save(rrd)
    stream.log("/a", rr.Scalars(1.0))
    stream.flush()
    stream.disconnect()
    env = {k: v for k, v in os.environ.items() if k != "MASSVIZ_DEBUG"}
    proc = subprocess.Popen([sys.executable, "-m", "massviz", "view", str(rrd)], cwd=SAMPLES.parent,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        lines = []
        while not any("Ctrl-C" in line for line in lines):
            lines.append(proc.stdout.readline())
            assert lines[-1] or proc.poll() is None, proc.stderr.read()
        page = re.search(r"open in a browser: (\S+)", "".join(lines)).group(1)
        tree = [psutil.Process(proc.pid), *psutil.Process(proc.pid).children(recursive=True)]
        listening = [c.laddr for p in tree for c in p.net_connections(kind="inet") if c.status == psutil.CONN_LISTEN]
        file_url = urllib.parse.parse_qs(urllib.parse.urlsplit(page).query)["url"][0]
        with urllib.request.urlopen(file_url) as r:
            assert r.read() == rrd.read_bytes()
            origin = r.headers["Access-Control-Allow-Origin"]
    finally:
        proc.send_signal(signal.SIGTERM)
        code = proc.wait(30)
    assert len(listening) == 2 and {a.ip for a in listening} == {"127.0.0.1"}, listening
    assert origin == page.split("?")[0].rstrip("/"), (origin, page)
    assert code == 0 and "massviz view: stopped" in proc.stderr.read()
    time.sleep(0.5)
    assert not [p for p in tree if p.is_running() and p.status() != psutil.STATUS_ZOMBIE], tree
