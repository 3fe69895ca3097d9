"""Servers: ``massviz serve`` listens on 127.0.0.1 only (the catalog server and the web viewer: every listening
socket of its process tree is listed), and a hostile .rrd in the served folder (garbage, empty, cut off in its
header, a folder named ``x.rrd``, a link to a device) is one warning line naming it while the rest is served."""
from __future__ import annotations

import os
import re
import shutil
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

    from massviz.views.web_viewer import WebViewer

    web, grpc = _free_port(), _free_port()
    server = WebViewer(port=web, grpc_port=grpc)
    try:
        proc = psutil.Process(server.proc.pid)
        tree = [proc, *proc.children(recursive=True)]
        listening = [c.laddr for p in tree for c in p.net_connections(kind="inet") if c.status == psutil.CONN_LISTEN]
    finally:
        server.stop()
    assert {a.port for a in listening} >= {web, grpc}, listening
    assert {a.ip for a in listening} == {"127.0.0.1"}, listening
    assert not proc.is_running() or proc.status() == psutil.STATUS_ZOMBIE


# ------------------------------------------------------------------------------ every .rrd not served is named
def small_rrd(path: Path, recording_id: str, frames: int = 40) -> Path:
    """A Rerun recording of ``frames`` messages (a scalar and a text per frame) with a property, closed properly."""
    import rerun as rr

    stream = rr.RecordingStream("massviz", recording_id=recording_id)
    stream.save(path)
    stream.send_property("massviz", rr.AnyValues(id=recording_id))
    for i in range(frames):
        stream.set_time("frame", sequence=i)
        stream.log("/value", rr.Scalars(float(i)))
        stream.log("/log", rr.TextLog(f"frame {i} of {recording_id}"))
    stream.flush()
    stream.disconnect()
    return path


def message_starts(data: bytes) -> list[int]:
    """Where each message of an .rrd stream starts (after the 12-byte header: a little-endian u64 kind and u64
    length, then the payload), up to the end-of-stream message (kind 0) that precedes the footer."""
    import struct

    starts, pos = [], 12
    while pos + 16 <= len(data):
        starts.append(pos)
        kind, length = struct.unpack_from("<QQ", data, pos)
        if kind == 0:
            break
        pos += 16 + length
    return starts


#: where a recording is cut (``data`` -> bytes kept): in its header, in its first message's header, half-way, at a
#: message boundary half-way, right before the end-of-stream message (a writer killed between two messages) and in
#: the footer.
CUTS = {
    "in-header": lambda d: 6,
    "in-first-message-header": lambda d: 12 + 8,
    "half-way": lambda d: len(d) // 2,
    "at-a-message-boundary": lambda d: message_starts(d)[len(message_starts(d)) // 2],
    "before-the-end-message": lambda d: message_starts(d)[-1],
    "in-the-footer": lambda d: len(d) - 4,
}


def hostile_folder(root: Path) -> tuple[Path, dict[str, str], dict[str, str]]:
    """A folder of good recordings and of every kind of .rrd file that must not be served: (folder, good file ->
    recording id, bad file -> what its warning must say). Each cut recording has an id of its own (served, its
    part would be one more segment)."""
    import cv2
    import numpy as np

    folder = root / "served"
    folder.mkdir()
    good = {f"good_{i}.rrd": f"good-{i}" for i in range(3)}
    for name, rid in good.items():
        small_rrd(folder / name, rid)
    bad = {}
    for where, cut in CUTS.items():
        data = small_rrd(root / f"{where}.rrd", f"cut-{where}").read_bytes()
        (folder / f"cut_{where}.rrd").write_bytes(data[:cut(data)])
        bad[f"cut_{where}.rrd"] = "cut off"
    (folder / "empty.rrd").write_bytes(b"")
    bad["empty.rrd"] = "is empty"
    (folder / "random.rrd").write_bytes(np.random.default_rng(7).bytes(5000))
    (folder / "image.rrd").write_bytes(cv2.imencode(".png", np.full((8, 8, 3), 200, np.uint8))[1].tobytes())
    (folder / "notes.rrd").write_text("a text file renamed .rrd\n")
    bad.update(dict.fromkeys(["random.rrd", "image.rrd", "notes.rrd"], "not a Rerun .rrd file"))
    (folder / "damaged.rrd").write_bytes(b"RRF2" + np.random.default_rng(8).bytes(5000))
    bad["damaged.rrd"] = "cut off or damaged"
    shutil.copy(folder / "good_0.rrd", folder / "zz_copy_of_good_0.rrd")
    bad["zz_copy_of_good_0.rrd"] = "holds recording 'good-0' as good_0.rrd does, which is served"
    return folder, good, bad


def test_every_rrd_that_rerun_cannot_read_whole_is_refused_with_its_reason(tmp_path):
    """The check ``massviz serve`` and ``massviz view`` put every .rrd through: a good recording gives its id; each
    cut, empty, foreign or damaged file is one ``MassvizError`` line naming it with its reason."""
    from massviz.errors import MassvizError
    from massviz.views.rerun_serve import rrd_recordings

    folder, good, bad = hostile_folder(tmp_path)
    for name, rid in good.items():
        assert rrd_recordings(folder / name) == [rid]
    for name, why in bad.items():
        if name.startswith("zz_copy"):
            continue  # (a whole recording: refused only beside the file it copies, by serve)
        with pytest.raises(MassvizError) as err:
            rrd_recordings(folder / name)
        line = str(err.value)
        assert line.startswith(f"{folder / name}: ") and why in line and "\n" not in line, (name, line)


@pytest.mark.slow
def test_serve_names_every_rrd_it_does_not_serve_with_its_reason(tmp_path):
    """A folder of good recordings and of cut (at several points), empty, foreign and damaged .rrd files, and a copy
    of a good one: ``massviz serve`` serves exactly the good ones (the catalog's segment table and its storage URLs),
    names every other file in one warning line with its reason, counts them in its first line, and exits 0 when
    stopped; a folder of only such files is one error line, exit 2."""
    from rerun.catalog import CatalogClient

    folder, good, bad = hostile_folder(tmp_path)
    env = {k: v for k, v in os.environ.items() if k not in ("MASSVIZ_DEBUG", "RUST_LOG")}
    proc = subprocess.Popen([sys.executable, "-m", "massviz", "serve", str(folder), "--no-web-viewer"], cwd=ROOT,
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        lines, t0 = [], time.monotonic()
        while time.monotonic() - t0 < 120 and not any("Ctrl-C" in line for line in lines):
            lines.append(proc.stdout.readline())
            assert lines[-1] or proc.poll() is None, proc.stderr.read()
        text = "".join(lines)
        url = re.search(r"native viewer:\s+rerun (rerun\+http://127\.0\.0\.1:\d+)", text).group(1)
        client = CatalogClient(url)  # (kept while its DataFrame runs)
        table = client.get_dataset("served").segment_table().to_pandas()
    finally:
        proc.send_signal(signal.SIGTERM)
        code = proc.wait(30)
    err = proc.stderr.read()
    assert code == 0 and "Traceback" not in err, err
    assert sorted(table["rerun_segment_id"]) == sorted(good.values()), table["rerun_segment_id"]
    stored = [Path(u.removeprefix("file://")) for urls in table["rerun_storage_urls"] for u in urls]
    assert sorted(p.name for p in stored if p.parent == folder) == sorted(good), stored  # (and each one's link)
    assert f"{len(good)} recording(s) from {folder}; {len(bad)} .rrd file(s) not served" in text, text
    warned = {}
    for line in err.splitlines():
        m = re.fullmatch(r"massviz: warning: (\S+): (.*); not served", line)
        if m:
            assert m.group(1) not in warned, f"named twice: {line}"
            warned[m.group(1)] = m.group(2)
    assert sorted(warned) == sorted(str(folder / name) for name in bad), err
    for name, why in bad.items():
        assert why in warned[str(folder / name)], (name, warned[str(folder / name)])
    for name in good:
        (folder / name).unlink()
    (folder / "zz_copy_of_good_0.rrd").unlink()
    run = subprocess.run([sys.executable, "-m", "massviz", "serve", str(folder)], cwd=ROOT, env=env,
                         capture_output=True, text=True, timeout=120)
    errors = [line for line in run.stderr.splitlines() if "error" in line]
    assert run.returncode == 2 and errors == [f"massviz serve: error: {folder}: holds no readable .rrd file (make a "
                                              "dataset with: massviz log DATASET --rrd-dir OUT)"], run.stderr
    assert run.stderr.count("; not served") == len(bad) - 1, run.stderr
