"""One pass: an uncached ``massviz log`` reads each RGB and depth file of the recording exactly once. The
frames are logged as the pipeline processes them (its ``on_frame`` observer), from the bytes the reader read; the
trace-dependent overlays afterwards read no frame. Opens are counted with an audit hook (``open`` events) in a
subprocess; frame files are never read with ``cv2.imread`` (which raises no audit event), checked in the source.

With the trace cache on and nothing cached (a cold cache), ``log`` and ``estimate`` read each frame file once too:
the trace is keyed by the digests of the bytes the run read (``TraceCache.watch``), not by hashing every file
first; a re-run opens none (``estimate``) or each once to log it (``log``), and a changed file is never a stale hit."""
from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CUP = ROOT / "data_samples" / "cup_handover"

#: runs ``massviz ARGS`` with an audit hook that records every file opened under ROOT_DIR, written to OUT as JSON
COUNTING = """
import collections, json, os, sys
root, out = os.path.realpath(sys.argv[1]), sys.argv[2]
opened = collections.Counter()
def hook(event, args):
    if event == "open" and isinstance(args[0], (str, bytes, os.PathLike)):
        path = os.path.realpath(os.fsdecode(args[0]))
        if path.startswith(root + os.sep):
            opened[os.path.relpath(path, root)] += 1
sys.addaudithook(hook)
sys.argv = ["massviz", *sys.argv[3:]]
from massviz.cli import main
try:
    code = main()
finally:
    json.dump(dict(opened), open(out, "w"))
sys.exit(code)
"""


def count_opens(rec: Path, tmp_path: Path, *args) -> tuple[dict, subprocess.CompletedProcess]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    env.pop("MASSVIZ_DEBUG", None)
    out = tmp_path / "opened.json"
    r = subprocess.run([sys.executable, "-c", COUNTING, str(rec), str(out), *map(str, args)], capture_output=True,
                       text=True, timeout=900, cwd=ROOT, env=env)
    assert r.returncode == 0, r.stderr
    return json.loads(out.read_text()), r


@pytest.fixture
def cold_cup(tmp_path):
    rec = tmp_path / "cup_handover"
    shutil.copytree(CUP, rec)  # a new path: nothing of it is in any cache
    return rec


def frame_files(rec: Path) -> list[str]:
    return sorted(str(p.relative_to(rec)) for sub in ("rgb", "depth") for p in (rec / sub).iterdir())


@pytest.mark.slow
def test_uncached_log_opens_each_frame_file_once(cold_cup, tmp_path, shared_dir):
    weights = shared_dir / "weights" / "corsmal_visual" / "Encoder_pool_aug_158.torch"
    opened, r = count_opens(cold_cup, tmp_path, "log", cold_cup, "--detector", "depth", "--weights", weights,
                            "--no-cache", "--rrd", tmp_path / "cup.rrd", "--quiet")
    files = frame_files(cold_cup)
    assert len(files) == 72
    # open_recording checks the first RGB and depth frame when it opens the folder; the reader keeps those bytes
    # for the frame loop, so they too are opened once
    expected = {f: 1 for f in files}
    assert {f: opened.get(f, 0) for f in files} == expected
    from rrd_reader import rrd_contents

    contents = rrd_contents(tmp_path / "cup.rrd")
    assert "EncodedImage:blob" in contents["/camera/rgb"] and "EncodedDepthImage:blob" in contents["/camera/depth"]
    assert {"/camera/detections", "/camera/masks", "/patches/0", "/predictions/estimate"} <= set(contents)


def test_no_frame_file_is_read_with_cv2_imread():
    # cv2.imread raises no audit event, so the count above would miss it: frame readers decode bytes instead
    offenders = [str(p.relative_to(ROOT)) for p in (ROOT / "massviz").rglob("*.py")
                 if {"io", "views", "core"} & set(p.relative_to(ROOT / "massviz").parts[:-1])
                 and p.name != "ground_truth.py"  # masks, not frames
                 and re.search(r"cv2\.imread\(", p.read_text())]
    assert offenders == []


# -- a cold trace cache -----------------------------------------------------------------------------------------------
def _under(tmp_path: Path, files: list[str], rec: Path) -> list[str]:
    return [str((rec / f).relative_to(tmp_path)) for f in files]


def _frame_opens(opened: dict, frames: list[str]) -> dict:
    return {f: opened.get(f, 0) for f in frames}


def _cache_reads(opened: dict) -> list[str]:
    """Cached traces and indexes opened (not the temporaries an entry is written through)."""
    return [f for f in opened if f.startswith("cache/traces/") and Path(f).name[0] in "ti"]


@pytest.mark.slow
def test_cold_cached_log_opens_each_frame_file_once_and_a_rerun_logs_the_cached_trace(cold_cup, tmp_path, weights):
    from rrd_reader import rrd_contents

    frames = _under(tmp_path, frame_files(cold_cup), cold_cup)
    assert len(frames) == 72
    runs = []
    for name in ("cold", "warm"):
        opened, r = count_opens(tmp_path, tmp_path, "log", cold_cup, "--detector", "depth", "--weights", weights,
                                "--cache", tmp_path / "cache", "--rrd", tmp_path / f"{name}.rrd", "--quiet")
        runs.append((opened, r))
        # cold: read once by the run (its content key is of those bytes); warm: once more only to log the frames
        assert _frame_opens(opened, frames) == {f: 1 for f in frames}, name
    (cold, cold_run), (warm, warm_run) = runs
    assert _cache_reads(cold) == [] and any(f.endswith(".npz") for f in _cache_reads(warm))  # served from the cache
    assert len(list((tmp_path / "cache" / "traces").glob("*/t*.npz"))) == 1  # the re-run added no entry
    estimate = [line for line in cold_run.stderr.splitlines() if line.startswith("cup_handover: ")]
    assert estimate and estimate[0].split(";")[0] == \
        next(line for line in warm_run.stderr.splitlines() if line.startswith("cup_handover: ")).split(";")[0]
    cold_rrd, warm_rrd = rrd_contents(tmp_path / "cold.rrd"), rrd_contents(tmp_path / "warm.rrd")
    assert "/timings/cache" in warm_rrd  # the stage timings say the trace came from the cache; all else is the same
    untimed = lambda contents: {k: v for k, v in contents.items() if not k.startswith("/timings/")}  # noqa: E731
    assert untimed(cold_rrd) == untimed(warm_rrd) and "EncodedDepthImage:blob" in warm_rrd["/camera/depth"]


@pytest.mark.slow
def test_cold_cached_estimate_opens_each_frame_file_once_a_rerun_none_and_a_change_no_stale_hit(cold_cup, tmp_path,
                                                                                                weights):
    frames = _under(tmp_path, frame_files(cold_cup), cold_cup)
    args = ("estimate", cold_cup, "--detector", "depth", "--weights", weights, "--cache", tmp_path / "cache",
            "--quiet", "--exec-time", "none")
    cold, _ = count_opens(tmp_path, tmp_path, *args, "--out", tmp_path / "cold.csv", "--report", tmp_path / "c.json")
    assert _frame_opens(cold, frames) == {f: 1 for f in frames}
    warm, _ = count_opens(tmp_path, tmp_path, *args, "--out", tmp_path / "warm.csv")
    assert _frame_opens(warm, frames) == {f: 0 for f in frames} and _cache_reads(warm)  # from the cache alone
    assert (tmp_path / "warm.csv").read_bytes() == (tmp_path / "cold.csv").read_bytes()
    assert json.loads((tmp_path / "c.json").read_text())["recordings"][0]["status"] == "done"

    # one depth frame edited after the run (same size, modification time set back): recomputed, never a stale hit
    depth = cold_cup / "depth" / "000030.png"
    st = depth.stat()
    _edit_keeping_size(depth)
    os.utime(depth, ns=(st.st_atime_ns, st.st_mtime_ns))
    changed, _ = count_opens(tmp_path, tmp_path, *args, "--out", tmp_path / "changed.csv", "--report",
                             tmp_path / "r.json")
    assert json.loads((tmp_path / "r.json").read_text())["recordings"][0]["status"] == "done"
    # an entry of this recording exists, so the lookup needs the key: the changed file is hashed (its new bytes may
    # be cached), then the run reads every frame once; the others' digests are remembered
    expected = {f: 1 for f in frames}
    expected[str(depth.relative_to(tmp_path))] = 2
    assert _frame_opens(changed, frames) == expected
    assert len(list((tmp_path / "cache" / "traces").glob("*/t*.npz"))) == 2


def _edit_keeping_size(png: Path) -> None:
    """Another 16-bit depth PNG of the same size in bytes: one pixel changed, padded (a tEXt chunk) to the size."""
    import cv2
    import numpy as np

    size = png.stat().st_size
    depth = cv2.imdecode(np.frombuffer(png.read_bytes(), np.uint8), cv2.IMREAD_UNCHANGED)
    depth[0, 0] = depth[0, 0] + 1
    data = cv2.imencode(".png", depth, [cv2.IMWRITE_PNG_COMPRESSION, 9])[1].tobytes()
    assert len(data) + 16 <= size, "the edited frame must not be larger"
    import struct
    import zlib

    text = b"x" * (size - len(data) - 12 - 4)
    chunk = struct.pack(">I", len(text) + 4) + b"tEXt" + b"pad\0" + text
    chunk += struct.pack(">I", zlib.crc32(chunk[4:]) & 0xFFFFFFFF)
    data = data[:-12] + chunk + data[-12:]  # before IEND
    assert len(data) == size
    png.write_bytes(data)


def _no_hashing(monkeypatch):
    """Any file hashed by reading it (``filehash.file_digest``) fails the test."""
    import massviz.io.filehash as filehash

    def refuse(path):
        raise AssertionError(f"{path} was read again to hash it")

    monkeypatch.setattr(filehash, "file_digest", refuse)


@pytest.mark.parametrize("stride", [1, 3])
def test_the_key_of_the_bytes_a_run_read_is_the_key_of_the_files(cold_cup, tmp_path, monkeypatch, stride):
    from massviz.io.cache import TraceCache
    from massviz.io.filehash import FileHasher
    from massviz.io.recording import open_recording

    hashed = open_recording(cold_cup).fingerprint(FileHasher())  # every file read and hashed
    rec = open_recording(cold_cup)
    cache = TraceCache(tmp_path / "cache")
    with cache.watch(rec) as read:
        for _ in rec.frames(stride=stride):
            pass
    assert len(read) == 2 * len(range(0, rec.num_frames, stride))  # an RGB and a depth file per frame read
    for _ in rec.frames(stride=stride):  # outside the block nothing is watched
        pass
    assert len(read) == 2 * len(range(0, rec.num_frames, stride))
    if stride == 1:
        _no_hashing(monkeypatch)  # every frame file was read by the run: none is read again
    assert rec.fingerprint(cache.hasher, known=read) == hashed
    monkeypatch.undo()
    _no_hashing(monkeypatch)  # the digests are remembered: a warm key reads no file
    assert open_recording(cold_cup).fingerprint(FileHasher(tmp_path / "cache" / "hashes"), read=False) == hashed


def test_a_file_changed_after_or_while_the_run_read_it_is_never_keyed_by_its_new_bytes(cold_cup, tmp_path):
    from massviz.io.cache import TraceCache
    from massviz.io.filehash import FileHasher
    from massviz.io.recording import open_recording

    rec = open_recording(cold_cup)
    cache = TraceCache(tmp_path / "cache")
    with cache.watch(rec) as read:
        for _ in rec.frames():
            pass
    as_read = rec.fingerprint(FileHasher(), known=read)
    depth = cold_cup / "depth" / "000030.png"
    st = depth.stat()
    _edit_keeping_size(depth)
    os.utime(depth, ns=(st.st_atime_ns, st.st_mtime_ns))
    # changed after the run read it: the run's trace is keyed by the bytes it read, which are not remembered as
    # the file's now (a lookup hashes the new bytes: another key, a miss)
    assert rec.fingerprint(cache.hasher, known=read) == as_read
    assert FileHasher(tmp_path / "cache" / "hashes").digests([depth], str(cold_cup.resolve()), read=False) is None
    now = open_recording(cold_cup).fingerprint(FileHasher())
    assert now != as_read and rec.fingerprint(cache.hasher) == now
    # changed while the run read it (read_bytes gives no digest): no key, the trace is not cached
    read[os.path.abspath(depth)] = None
    assert rec.fingerprint(cache.hasher, known=read) is None and cache.entry(rec, {}, 1, read) is None


def test_a_lookup_without_an_entry_of_the_recording_computes_no_key(cold_cup, tmp_path, monkeypatch):
    from massviz.io.cache import TraceCache
    from massviz.io.recording import open_recording

    rec = open_recording(cold_cup)
    cache = TraceCache(tmp_path / "cache")
    (cache.dir / "other_recording-0123456789abcdef").mkdir(parents=True)
    _no_hashing(monkeypatch)
    assert cache.lookup(rec, {"name": "depth"}, 1, 0.5) is None and cache.load_index(rec, {}, 1, 0.5) is None
    (cache.dir / "cup_handover-0123456789abcdef").mkdir()  # an entry of this id: the key decides (hashed)
    with pytest.raises(AssertionError, match="read again to hash it"):
        cache.lookup(rec, {"name": "depth"}, 1, 0.5)


def test_a_recording_opened_for_a_run_is_remembered_after_it_from_the_bytes_read(cold_cup, tmp_path, monkeypatch):
    from massviz.io.cache import TraceCache
    from massviz.io.identity import LocatedRecording, locate, open_remembered, settle

    cache = TraceCache(tmp_path / "cache")
    _no_hashing(monkeypatch)  # on a cold cache, nothing is read to hash it: before, during or after the run
    rec = open_remembered(cold_cup, cache.root, defer=True)
    assert locate(cold_cup, cache.root) is None  # its fingerprint would need every frame file read: not yet
    with cache.watch(rec) as read:
        for _ in rec.frames():
            pass
    key = cache.entry(rec, {"name": "depth"}, 1, read)  # what save does after the run
    settle(rec, cache.hasher)
    found = locate(cold_cup, cache.root)
    assert isinstance(found, LocatedRecording) and found.fingerprint() == rec.fingerprint(cache.hasher, read=False)
    assert cache.entry(found, {"name": "depth"}, 1) == key  # a warm run finds the entry the cold run wrote

    # a file changed during the run: the recording is not remembered as it was opened
    other = TraceCache(tmp_path / "cache2")
    again = open_remembered(cold_cup, other.root, defer=True)
    with other.watch(again) as read:
        for _ in again.frames():
            pass
    other.entry(again, {}, 1, read)
    assert again.fingerprint(other.hasher, read=False) is not None  # known without reading: settle could write
    (cold_cup / "meta.json").write_text((cold_cup / "meta.json").read_text() + " ")
    settle(again, other.hasher)
    assert locate(cold_cup, other.root) is None
