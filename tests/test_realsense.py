"""RealSense recordings (massviz.io.formats.realsense_*): .db3 files built from the bundled samples with pyrealsense2's
``software_device`` + ``recorder`` read back exactly (frames, depth in mm, intrinsics, frame numbers, timestamps),
librealsense's align is used when depth is not registered to colour, ``massviz estimate`` on the .db3 equals the
sample folder's estimate, and every bad file is one clear line (exit 2, nothing written).

pyrealsense2 is in the test extra: without it these tests are skipped, and under CI=true they fail.
"""
from __future__ import annotations

import csv
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from fakes import SAMPLE, realsense_bad_files
from massviz.core.types import Intrinsics
from massviz.errors import MassvizError, RecordingError
from massviz.io.recording import open_recording
from support import run_massviz as massviz


@pytest.fixture(scope="module")
def sample():
    return open_recording(SAMPLE)


@pytest.fixture(scope="module")
def cup_db3(rs, sample, tmp_path_factory) -> Path:
    from massviz.io.formats.realsense_write import write_realsense

    return write_realsense(sample, tmp_path_factory.mktemp("rs") / "cup_handover_rs.db3")


def test_a_written_db3_plays_back_like_a_camera(cup_db3, sample):
    """``write_realsense(rec, "x.db3")`` (README's recipe, the default): the recorder stamps messages with the clock
    of writing, a burst; the file's frames are stamped 1/fps apart, and its real-time playback delivers them over the
    recording's duration (a burst made ``massviz live --file`` process 3 frames of 32)."""
    import sqlite3
    import time

    from massviz.io.formats.realsense_live import open_file_stream

    fps, n = float(sample.fps), sample.num_frames
    with sqlite3.connect(cup_db3) as db:
        rows = db.execute("SELECT t.name, m.timestamp FROM messages m JOIN topics t ON m.topic_id = t.id "
                          "WHERE t.name LIKE '%/image/data/%' ORDER BY m.timestamp").fetchall()
    for topic in {name for name, _ in rows}:
        stamps = np.array([ts for name, ts in rows if name == topic], np.float64) / 1e9
        assert len(stamps) == n and np.allclose(np.diff(stamps), 1 / fps, atol=0.005), (topic, np.diff(stamps))
    arrivals = []
    stream = open_file_stream(cup_db3)
    stream.start(lambda c, d: arrivals.append(time.perf_counter()))
    try:
        t0 = time.perf_counter()
        while not stream.finished() and time.perf_counter() - t0 < 30:
            time.sleep(0.02)
    finally:
        stream.stop()
    assert len(arrivals) == n
    assert arrivals[-1] - arrivals[0] >= 0.9 * (n - 1) / fps, arrivals[-1] - arrivals[0]



# --------------------------------------------------------------------------------------------------- round trip
def test_db3_reads_back_the_sample_exactly(cup_db3, sample):
    rec = open_recording(cup_db3)
    assert rec.kind == "realsense" and rec.num_frames == sample.num_frames == 36
    assert rec.intrinsics == sample.intrinsics  # float32 in the file, read back as the JSON's decimals
    assert (rec.width, rec.height, rec.fps) == (sample.width, sample.height, sample.fps)
    rs_meta = rec.meta["realsense"]
    assert rs_meta["frame_numbers"] == list(range(36))
    assert np.allclose(rs_meta["timestamps_ms"], np.arange(36) * 1000 / 30)
    assert rs_meta["depth_scale"] == pytest.approx(0.001)
    assert rs_meta["depth_to_colour"].startswith("registered")
    n = 0
    for a, b in zip(rec.frames(), sample.frames(), strict=True):
        assert a.index == b.index
        assert a.rgb.dtype == np.uint8 and np.array_equal(a.rgb, b.rgb), a.index
        assert a.depth.dtype == np.uint16 and np.array_equal(a.depth, b.depth), a.index
        n += 1
    assert n == 36
    assert [f.index for f in rec.frames(stride=10)] == [0, 10, 20, 30]
    assert np.array_equal(rec.read_frame(17).depth, sample.read_frame(17).depth)
    assert rec.info().to_dict()["kind"] == "realsense"


def test_depth_units_other_than_millimetres(rs, sample, tmp_path):
    """0.1 mm units (as a D405): z16 = 10 x mm in the file, read back in mm through the device's depth scale."""
    from massviz.io.formats.realsense_file import open_realsense
    from massviz.io.formats.realsense_write import SoftwareRig

    rig = SoftwareRig(rs, sample.intrinsics, 30, depth_units=0.0001)
    path = tmp_path / "units.db3"
    frames = list(sample.frames(indices=[0, 20]))
    with rig.record(path):
        for i, frame in enumerate(frames):
            rig.push(frame, i, i * 33.3)
    rec = open_realsense(path)
    assert rec.meta["realsense"]["depth_scale"] == pytest.approx(0.0001)
    for got, want in zip(rec.frames(), frames, strict=True):
        assert np.array_equal(got.depth, want.depth)


def test_unregistered_depth_goes_through_librealsense_align(rs, sample, tmp_path):
    """A depth stream at twice the colour resolution: frames come out at the colour size, aligned by
    librealsense (same field of view: the aligned depth matches the sample's where both have depth)."""
    from massviz.io.formats.realsense_file import open_realsense
    from massviz.io.formats.realsense_write import SoftwareRig

    i = sample.intrinsics
    di = Intrinsics(2 * i.fx, 2 * i.fy, 2 * i.cx + 0.5, 2 * i.cy + 0.5, 2 * i.width, 2 * i.height)
    rig = SoftwareRig(rs, i, 30, depth_intrinsics=di)
    path = tmp_path / "big_depth.db3"
    frames = list(sample.frames(indices=[0, 25]))
    with rig.record(path):
        for n, frame in enumerate(frames):
            rig.push(frame, n, n * 33.3, depth=cv2.resize(frame.depth, (di.width, di.height),
                                                         interpolation=cv2.INTER_NEAREST))
    rec = open_realsense(path)
    assert rec.meta["realsense"]["depth_to_colour"] == "librealsense align"
    assert rec.intrinsics == i
    for got, want in zip(rec.frames(), frames, strict=True):
        assert got.depth.shape == want.depth.shape and np.array_equal(got.rgb, want.rgb)
        both = (got.depth > 0) & (want.depth > 0)
        assert both.mean() > 0.95
        assert np.median(np.abs(got.depth[both].astype(int) - want.depth[both])) == 0



@pytest.fixture(scope="module")
def bad_files(rs, tmp_path_factory, cup_db3, sample):
    return realsense_bad_files(rs, tmp_path_factory.mktemp("rs_bad"), cup_db3, sample)


def test_bad_files_are_one_clear_recording_error(bad_files):
    for case, (path, what) in bad_files.items():
        with pytest.raises(RecordingError) as err:
            open_recording(path)
        msg = str(err.value)
        assert "\n" not in msg and str(path) in msg and what in msg, (case, msg)


def test_without_pyrealsense2_one_line_says_what_to_install(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "pyrealsense2", None)  # import fails as when it is not installed
    path = tmp_path / "x.db3"
    path.write_bytes(b"whatever")
    with pytest.raises(MassvizError, match=r"pip install 'massviz\[realsense\]'"):
        open_recording(path)


def test_write_refuses_bag_and_recordings_without_intrinsics(rs, sample, tmp_path):
    import dataclasses

    from massviz.io.formats.realsense_write import write_realsense

    with pytest.raises(MassvizError, match="only as ROS2 .db3"):
        write_realsense(sample, tmp_path / "x.bag")
    with pytest.raises(RecordingError, match="no intrinsics"):
        write_realsense(dataclasses.replace(sample, intrinsics=None), tmp_path / "x.db3")
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------------------------------------- command line
@pytest.mark.slow
def test_estimate_on_db3_equals_the_sample_folder(weights, cup_db3, tmp_path):
    """(every 3rd frame, to keep the test quick on 2 cores: 12 frames of each)"""
    out = tmp_path / "preds.csv"
    r = massviz("estimate", SAMPLE, cup_db3, "--detector", "depth", "--weights", weights, "--exact", "--quiet",
                "--stride", 3, "--cache", tmp_path / "cache", "--out", out)
    assert r.returncode == 0, r.stderr
    rows = list(csv.DictReader(out.open()))
    assert len(rows) == 2
    masses = [float(row["Container mass"]) for row in rows]
    assert masses[0] > 0 and masses[0] == masses[1]
    # and massviz log takes the .db3 too (its trace comes from the cache the estimate filled)
    rrd = tmp_path / "cup.rrd"
    r = massviz("log", cup_db3, "--detector", "depth", "--weights", weights, "--quiet", "--stride", 3,
                "--cache", tmp_path / "cache", "--rrd", rrd)
    assert r.returncode == 0, r.stderr
    from rrd_reader import rrd_entities

    assert {"/camera/rgb", "/camera/depth", "/camera/detections", "/predictions/running_estimate",
            "/latency/detect"} <= rrd_entities(rrd)


@pytest.mark.slow
def test_cli_bad_files_exit_2_one_line_nothing_written(bad_files, tmp_path):
    for case, (path, what) in bad_files.items():
        out = tmp_path / f"{path.stem}.csv"
        r = massviz("estimate", path, "--detector", "depth", "--no-cache", "--out", out)
        lines = [line for line in r.stderr.splitlines() if line.strip()]
        assert r.returncode == 2 and len(lines) == 1, (case, r.stderr)
        assert str(path) in lines[0] and what in lines[0] and "Traceback" not in r.stderr, (case, lines)
        assert not out.exists()
