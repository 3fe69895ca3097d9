"""Live mode: the running estimate of offline traces, the one-frame buffer, and ``massviz live`` on RealSense files
played back in real time and on a ``software_device`` fed from a thread (a stand-in camera): the .rrd holds the
documented entities and the running estimate, the trace equals the offline one of the same frames, the saved folder
replays in ``massviz log``; a slow detector drops frames, counts them, and memory stays flat; bad sources are one
clear line, exit 2, nothing written.
"""
from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from fakes import (
    DETECTIONS,
    PLAYED,
    SAMPLE,
    FastModel,
    ListDetector,
    live_pipeline,
    realsense_bad_files,
    scene,
    session_args,
    software_camera_stream,
    write_recording,
)
from massviz.core.pipeline import FramePipeline, run
from massviz.core.selection import estimate_mass, select_k_nearest
from massviz.core.trace import Trace
from massviz.core.types import Frame, Intrinsics, RecordingInfo
from massviz.errors import MassvizError
from massviz.io.recording import open_recording
from massviz.io.trace_file import load_trace, save_trace
from massviz.runners.camera_loop import LatestSlot
from support import CLEARED_ENV, ROOT
from support import run_massviz as massviz


class SlowDetector:
    """Test-only: another detector that takes ``seconds`` per frame (slower than the camera)."""

    def __init__(self, inner, seconds: float):
        self.inner, self.seconds = inner, seconds
        self.name, self.threshold = inner.name, inner.threshold

    def settings(self) -> dict:
        return self.inner.settings()

    def detect(self, frame):
        time.sleep(self.seconds)
        return self.inner.detect(frame)


# ------------------------------------------------------------------------------------------- offline: no camera
@pytest.fixture(scope="module")
def scene_trace(tmp_path_factory):
    rgbs, depths = scene()
    rec = open_recording(write_recording(tmp_path_factory.mktemp("live_scene") / "scene", rgbs, depths))
    fp = FramePipeline(ListDetector(DETECTIONS, threshold=0.4), FastModel(), k=3, recording=rec.info())
    steps = [fp.step(frame).running_estimate for frame in rec.frames()]
    return fp.finish(), steps


def brute_running(trace: Trace) -> list[float]:
    dets, out = trace.detections, []
    for f in trace.frames:
        score = np.where(dets.frame <= f, dets.score, -1.0)  # only the frames processed so far
        sel = select_k_nearest(dets.d, score, trace.k, trace.threshold, trace.excluded)
        out.append(estimate_mass(dets.pred, sel))
    return out


def test_running_estimate_is_the_estimate_over_the_frames_so_far(scene_trace):
    trace, steps = scene_trace
    running = trace.running_estimate()
    assert running.tolist() == steps == brute_running(trace)  # the live step, the trace, a selection per frame
    assert running[-1] == trace.estimate and len(set(running.tolist())) > 2
    other = trace.reselect(k=2, threshold=0.6, exclude=[int(trace.selection[0])])
    assert other.running_estimate().tolist() == brute_running(other)
    assert other.running_estimate()[-1] == other.estimate


def test_settled_after_counts_frames_to_within_tolerance(scene_trace):
    trace, _ = scene_trace
    running, final = trace.running_estimate(), trace.estimate
    n = trace.settled_after(0.10)
    assert 1 <= n <= len(running)
    assert np.all(np.abs(running[n - 1:] - final) <= 0.10 * final)
    assert n == 1 or abs(running[n - 2] - final) > 0.10 * final or running[n - 2] < 0
    changes = np.flatnonzero(running != final)  # tolerance 0: settled after the last change
    assert trace.settled_after(0.0) == (int(changes[-1]) + 2 if len(changes) else 1)


def test_frame_timings_are_kept_per_frame_and_saved(scene_trace, tmp_path):
    trace, _ = scene_trace
    assert set(trace.frame_timings) == {"read", "detect", "features", "predict", "select"}
    assert all(len(v) == len(trace.frames) for v in trace.frame_timings.values())
    back = load_trace(save_trace(trace, tmp_path / "t.npz"))
    assert {k: v.tolist() for k, v in back.frame_timings.items()} == \
        {k: np.asarray(v).tolist() for k, v in trace.frame_timings.items()}
    assert back.running_estimate().tolist() == trace.running_estimate().tolist()


def test_latest_slot_keeps_only_the_newest_and_counts_drops():
    slot = LatestSlot()
    assert slot.take(timeout=0.01) is None
    for i in range(5):
        slot.put(i)
        assert len(slot) == 1
    assert slot.take(timeout=0.01) == 4 and slot.take(timeout=0.01) is None
    assert (slot.arrived, slot.dropped) == (5, 4)



LIVE_ENTITIES = {"/camera", "/camera/rgb", "/camera/depth", "/camera/detections", "/camera/masks", "/patches/0",
                 "/predictions/running_estimate", "/predictions/estimate", "/latency/total", "/latency/overhead",
                 "/latency/read", "/latency/detect", "/latency/predict", "/latency/log", "/log", "/summary",
                 "/timings"}


def offline(detector, recording_path: Path):
    return run(open_recording(recording_path), detector, FastModel(), k=5)


def summary_line(stderr: str, name: str) -> str:
    """The one line ``NAME: ESTIMATE ...`` a session (or ``massviz log``) ends with, found by its content: other lines
    (a flag warning after ``massviz log``'s summary, a Python warning) may come after it."""
    lines = [line for line in stderr.splitlines() if line.startswith(f"{name}: ")]
    assert len(lines) == 1, stderr
    return lines[0]


@pytest.mark.slow
def test_live_file_in_real_time(rs, played_db3, played, depth_detector, tmp_path, capsys):
    from massviz.commands.live import run_session
    from massviz.io.formats.realsense_live import open_file_stream
    from rrd_reader import rrd_entities

    p = live_pipeline(depth_detector, tmp_path)
    args = session_args(file=str(played_db3), rrd=str(tmp_path / "live.rrd"), save=str(tmp_path / "rec"))
    t0 = time.perf_counter()
    assert run_session(args, p, open_file_stream(played_db3), "played") == 0
    assert time.perf_counter() - t0 >= 1.0  # real time: the 12 frames were recorded over 1.2 s
    last = summary_line(capsys.readouterr().err, "played")
    assert last.startswith("played: ") and last.split()[1] != "not"
    assert LIVE_ENTITIES <= rrd_entities(tmp_path / "live.rrd")
    saved = open_recording(tmp_path / "rec")
    live_meta = saved.meta["live"]
    trace = p.cache.load(saved, {"name": depth_detector.name, **depth_detector.settings()}, 1, 0.4)
    assert trace is not None and len(trace.frames) == saved.num_frames == live_meta["processed"] >= 2
    # the saved frames are the played ones, exactly (frame numbers name the frame of the file)
    source = list(open_recording(played).frames())
    for frame, number in zip(saved.frames(), live_meta["frame_numbers"], strict=True):
        assert np.array_equal(frame.rgb, source[number].rgb) and np.array_equal(frame.depth, source[number].depth)
    assert trace.estimate == offline(depth_detector, tmp_path / "rec").estimate
    if live_meta["dropped"] == 0 and live_meta["frame_numbers"] == list(range(len(PLAYED))):
        assert trace.estimate == offline(depth_detector, played).estimate
    assert f"{trace.estimate:.1f} g" in last


@pytest.mark.slow
def test_live_software_camera_stand_in(rs, played, depth_detector, tmp_path, capsys):
    from massviz.commands.live import run_session
    from rrd_reader import rrd_entities

    rec = open_recording(played)
    stream = software_camera_stream(list(rec.frames()), rec.intrinsics, fps=10)
    p = live_pipeline(depth_detector, tmp_path)
    args = session_args(rrd=str(tmp_path / "cam.rrd"), save=str(tmp_path / "cam_rec"), duration=2.5)
    assert run_session(args, p, stream, "camera-sw") == 0
    err = capsys.readouterr().err
    assert "stopped: duration 2.5 s" in err
    assert LIVE_ENTITIES <= rrd_entities(tmp_path / "cam.rrd")
    saved = open_recording(tmp_path / "cam_rec")
    trace = p.cache.load(saved, {"name": depth_detector.name, **depth_detector.settings()}, 1, 0.4)
    assert trace.estimate == offline(depth_detector, tmp_path / "cam_rec").estimate >= 0
    if saved.meta["live"]["dropped"] == 0 and saved.num_frames == len(PLAYED):
        assert trace.estimate == offline(depth_detector, played).estimate
    assert summary_line(err, "camera-sw").startswith(f"camera-sw: {trace.estimate:.1f} g")



def test_a_live_session_sets_the_faithful_flags_once(rs, played, depth_detector, monkeypatch):
    """The faithful settings (IEEE fp32, deterministic cuDNN) are entered once for the whole session, as a run enters
    them once: torch's flags are written when the session starts and restored when it ends, not around every frame
    (the stage is made to ask for them as on a CUDA GPU; each step's own entering only counts a user)."""
    import massviz.core.device as device
    from massviz.runners.camera_loop import run_live

    writes = []
    real_write = device._write_flags
    monkeypatch.setattr(device, "_write_flags", lambda *a: (writes.append(a), real_write(*a))[1])
    rec = open_recording(played)
    stream = software_camera_stream(list(rec.frames()), rec.intrinsics, fps=30, loops=100)
    info = RecordingInfo(id="flags", kind="live", width=rec.width, height=rec.height, fps=30,
                         intrinsics=rec.intrinsics)
    fp = FramePipeline(depth_detector, FastModel(), k=5, recording=info)
    fp.stage.faithful = lambda: device.faithful_fp32("cuda")
    result = run_live(stream, fp, max_frames=6)
    assert result.stats.processed == 6, result.stats
    assert len(writes) == 2 and writes[0][:2] == (True, False), writes  # set once at the start, restored at the end
    assert device.faithful_users() == 0

@pytest.mark.slow
def test_slow_detector_drops_frames_counts_them_and_memory_stays_flat(rs, depth_detector, tmp_path):
    """A 640x480 stand-in camera at 60 fps and a detector taking 0.15 s: most frames are dropped, each counted,
    and resident memory does not grow with the frames that arrived (a queue would hold ~1.5 MB per frame)."""
    from massviz.runners.camera_loop import run_live
    from massviz.views.rerun.live_logger import LiveLogger

    sample = open_recording(SAMPLE)
    i = sample.intrinsics
    big = Intrinsics(i.fx * 640 / i.width, i.fy * 480 / i.height, i.cx * 640 / i.width, i.cy * 480 / i.height,
                     640, 480)
    frames = [Frame(f.index, cv2.resize(f.rgb, (640, 480)), cv2.resize(f.depth, (640, 480),
                                                                        interpolation=cv2.INTER_NEAREST))
              for f in sample.frames(indices=PLAYED)]
    stream = software_camera_stream(frames, big, fps=60, loops=100)
    info = RecordingInfo(id="slow", kind="live", width=640, height=480, fps=60, intrinsics=big)
    fp = FramePipeline(SlowDetector(depth_detector, 0.15), FastModel(), k=5, recording=info)
    logger = LiveLogger(name="slow", k=5, intrinsics=big, rrd=tmp_path / "slow.rrd")
    result = run_live(stream, fp, logger=logger, duration=4.0)
    s = result.stats
    assert s.dropped > 5 * s.processed > 0, s.summary()
    assert s.arrived - 1 <= s.processed + s.dropped <= s.arrived  # every frame processed or dropped (one in flight)
    assert f"{s.dropped} dropped" in s.summary()
    growth = s.rss_mb[-1] - s.rss_mb[2]
    queued = (s.dropped * 640 * 480 * 5) / 2**20  # what holding the dropped frames would have cost
    assert growth < max(25.0, 0.1 * queued), (growth, queued, s.rss_mb)
    from rrd_reader import rrd_entities

    assert "/log" in rrd_entities(tmp_path / "slow.rrd")


# ---------------------------------------------------------------------------------------------- command line
@pytest.mark.slow
def test_cli_live_file_then_massviz_log_replays_the_session(weights, rs, played_db3, tmp_path):
    common = ["--detector", "depth", "--weights", weights, "--cache", tmp_path / "cache", "--quiet"]
    r = massviz("live", "--file", played_db3, "--rrd", tmp_path / "live.rrd", "--save", tmp_path / "rec", *common)
    assert r.returncode == 0, r.stderr
    last = summary_line(r.stderr, "played")
    assert last.startswith("played: ") and " g (K=" in last
    estimate = last.split()[1]
    r = massviz("log", tmp_path / "rec", "--rrd", tmp_path / "replay.rrd", *common)
    assert r.returncode == 0, r.stderr
    assert summary_line(r.stderr, "played").startswith(f"played: {estimate} g")


@pytest.mark.slow
def test_cli_bad_sources_one_line_exit_2_nothing_written(rs, tmp_path):
    sample = open_recording(SAMPLE)
    db3 = tmp_path / "ok.db3"
    from massviz.io.formats.realsense_write import write_realsense

    write_realsense(sample, db3)
    bad = realsense_bad_files(rs, tmp_path, db3, sample)
    cases = {name: ("--file", path) for name, (path, _) in bad.items() if name in ("truncated", "no depth",
                                                                                  "no colour")}
    if not len(rs.context().query_devices()):
        cases["no camera"] = ("--camera",)
        cases["unknown serial"] = ("--camera", "000000000000")
    for name, src in cases.items():
        out, rec = tmp_path / f"{name}.rrd", tmp_path / f"{name}_rec"
        r = massviz("live", *src, "--detector", "depth", "--no-cache", "--rrd", out, "--save", rec)
        lines = [line for line in r.stderr.splitlines() if line.strip()]
        assert r.returncode == 2 and len(lines) == 1 and "Traceback" not in r.stderr, (name, r.stderr)
        assert not out.exists() and not rec.exists(), name
        if name in ("no camera", "unknown serial"):
            assert "no RealSense camera connected" in lines[0]
        else:
            assert str(src[1]) in lines[0]


def test_unknown_serial_names_the_connected_ones(monkeypatch):
    from massviz.io.formats import realsense_live as realsense

    class Dev:
        def __init__(self, serial):
            self.serial = serial

        def supports(self, info):
            return True

        def get_info(self, info):
            return self.serial

    class FakeRS:
        class camera_info:
            serial_number, name = "serial", "name"

        class context:
            def query_devices(self):
                return [Dev("111"), Dev("222")]

    monkeypatch.setattr(realsense, "import_rs", lambda: FakeRS)
    with pytest.raises(MassvizError, match=r"no RealSense camera with serial 333 \(connected: 111, 222\)"):
        realsense.open_camera("333")


@pytest.mark.slow
def test_cli_without_pyrealsense2_says_what_to_install(tmp_path):
    fake = tmp_path / "fake"
    fake.mkdir()
    (fake / "pyrealsense2.py").write_text("raise ImportError('No module named pyrealsense2')\n")
    env = {"PYTHONPATH": os.pathsep.join([str(fake), str(ROOT), os.environ.get("PYTHONPATH", "")])}
    r = massviz("live", "--file", tmp_path / "x.db3", "--no-cache", env=env)
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0, r.stderr
    assert "pip install 'massviz[realsense]'" in r.stderr


@pytest.mark.slow
def test_ctrl_c_ends_the_session_cleanly(rs, played, depth_detector, tmp_path):
    import signal
    import threading

    from massviz.runners.camera_loop import run_live
    from massviz.views.rerun.live_logger import LiveLogger

    rec = open_recording(played)
    stream = software_camera_stream(list(rec.frames()), rec.intrinsics, fps=15, loops=100)
    info = RecordingInfo(id="ctrl-c", kind="live", width=rec.width, height=rec.height, fps=15,
                         intrinsics=rec.intrinsics)
    fp = FramePipeline(depth_detector, FastModel(), k=5, recording=info)
    logger = LiveLogger(name="ctrl-c", k=5, intrinsics=rec.intrinsics, rrd=tmp_path / "c.rrd")
    timer = threading.Timer(2.0, os.kill, (os.getpid(), signal.SIGINT))
    timer.start()
    try:
        result = run_live(stream, fp, logger=logger, save=tmp_path / "c_rec")
    finally:
        timer.cancel()
    assert result.stats.stopped == "interrupted" and result.stats.processed > 0
    assert (tmp_path / "c.rrd").stat().st_size > 0
    assert open_recording(tmp_path / "c_rec").num_frames == result.stats.processed == len(result.trace.frames)
    assert signal.getsignal(signal.SIGINT) is not None  # the previous handler is back


def free_ports(n: int) -> list[int]:
    import socket

    ports = []
    for _ in range(n):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            ports.append(s.getsockname()[1])
    return ports


def listeners(ports) -> list:
    """The processes listening on any of ``ports`` (any address): (pid, address) pairs."""
    import psutil

    return [(c.pid, c.laddr) for c in psutil.net_connections("tcp")
            if c.status == psutil.CONN_LISTEN and c.laddr.port in ports]


@pytest.mark.slow
def test_serve_web_serves_a_viewer_on_localhost_and_ends_with_the_session(rs, played_db3, depth_detector, tmp_path,
                                                                           capsys):
    """While the session runs the web viewer answers on 127.0.0.1 only; when it ends, its server process is gone and
    nothing listens on the ports (the server is Rerun's binary, a child of this process, not a wrapper's child)."""
    import re
    import threading
    import urllib.request

    import psutil

    from massviz.commands.live import run_session
    from massviz.io.formats.realsense_live import open_file_stream

    ports = free_ports(2)
    seen = {}
    before = {p.pid for p in psutil.Process().children(recursive=True)}  # other tests' children are not this one's

    def watch():  # during the session: the page, the listening sockets, the server process
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and "status" not in seen:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{ports[0]}/", timeout=2) as page:
                    seen["status"] = page.status
                seen["listening"] = listeners(ports)
                seen["children"] = [p for p in psutil.Process().children(recursive=True) if p.pid not in before]
                seen["servers"] = [p.name() for p in seen["children"]
                                   if p.pid in {pid for pid, _ in seen["listening"]}]
            except OSError:
                time.sleep(0.05)

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    args = session_args(file=str(played_db3), serve_web=True, web_port=ports[0], grpc_port=ports[1])
    assert run_session(args, live_pipeline(depth_detector, tmp_path), open_file_stream(played_db3), "played") == 0
    watcher.join(5)
    err = capsys.readouterr().err
    url = re.search(r"web viewer at (\S+)", err).group(1)
    assert url.startswith(f"http://127.0.0.1:{ports[0]}/")
    assert seen.get("status") == 200, (seen, err)
    assert {addr.port for _, addr in seen["listening"]} == set(ports)
    assert all(addr.ip == "127.0.0.1" for _, addr in seen["listening"]), seen["listening"]
    assert seen["servers"] == ["rerun"], seen  # Rerun's binary itself, a child of this process
    # the session is over: the server has ended, nothing listens, no child of ours is left, and the user is told
    assert listeners(ports) == []
    assert not any(p.is_running() and p.status() != psutil.STATUS_ZOMBIE for p in seen["children"])
    assert "stopped the web viewer's server" in err and "kill" not in err


@pytest.mark.slow
def test_cli_serve_web_server_dies_with_a_killed_massviz(rs, played_db3, weights, tmp_path):
    """``massviz live --serve-web`` killed mid-session (SIGKILL: no handler runs): its server still ends."""
    import signal

    import psutil

    ports = free_ports(2)
    env = {k: v for k, v in os.environ.items() if k not in CLEARED_ENV}
    proc = subprocess.Popen([sys.executable, "-m", "massviz", "live", "--file", played_db3, "--detector", "depth",
                             "--weights", weights, "--no-cache", "--serve-web", "--web-port", str(ports[0]),
                             "--grpc-port", str(ports[1])],
                            cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        lines = []
        for line in proc.stderr:
            lines.append(line)
            if "web viewer at" in line:
                break
        server = [p for p in psutil.Process(proc.pid).children(recursive=True) if p.name() == "rerun"]
        assert server and listeners(ports), lines
        proc.send_signal(signal.SIGKILL)
        assert proc.wait(30) == -signal.SIGKILL
        gone, alive = psutil.wait_procs(server, timeout=15)
        assert not alive and listeners(ports) == [], (alive, listeners(ports))
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait()
