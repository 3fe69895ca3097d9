"""massviz.io.recording: the two layouts, streaming, stride, and every malformed input as one RecordingError.

Recordings are built in tmp_path from numpy arrays, so every expected pixel is known. ``write_recording`` and
``write_video`` are also used by test_selection / test_pipeline / test_cli.
"""
from __future__ import annotations

import re
import types
from pathlib import Path

import cv2
import numpy as np
import pytest

from fakes import OPEN_ERRORS, H, W, bad_missing_depth, corrupt_middle_depth, depth_frames, rgb_frames, write_recording
from massviz.errors import RecordingError
from massviz.io.recording import find_recordings, open_recording

INTR = {"fx": 30.0, "fy": 31.0, "cx": 16.0, "cy": 12.0, "width": W, "height": H}


@pytest.fixture
def folder(tmp_path) -> Path:
    return write_recording(tmp_path / "rec", rgb_frames(5), depth_frames(5), intrinsics=INTR,
                           meta={"id": "cup1", "fps": 15, "config_id": 7, "container": {"mass_g": 12.5}})


# ------------------------------------------------------------------------------------------------------ good inputs
def test_folder_of_pngs(folder):
    rec = open_recording(folder)
    assert (rec.kind, rec.id, rec.config_id) == ("folder", "cup1", "7")
    assert (rec.width, rec.height, rec.num_frames, rec.fps) == (W, H, 5, 15.0)
    assert rec.intrinsics.to_dict() == INTR
    assert rec.meta["container"]["mass_g"] == 12.5
    frames = list(rec.frames())
    assert [f.index for f in frames] == [0, 1, 2, 3, 4]
    for f, rgb, depth in zip(frames, rgb_frames(5), depth_frames(5), strict=False):
        np.testing.assert_array_equal(f.rgb, rgb)  # RGB order, lossless
        assert f.depth.dtype == np.uint16
        np.testing.assert_array_equal(f.depth, depth)


def test_stride_and_read_frame(folder):
    rec = open_recording(folder)
    assert [f.index for f in rec.frames(stride=2)] == [0, 2, 4]
    assert [f.index for f in rec.frames(stride=3)] == [0, 3]
    assert [f.index for f in rec.frames(indices=[3, 1, 3])] == [1, 3]
    frame = rec.read_frame(3)
    np.testing.assert_array_equal(frame.rgb, rgb_frames(5)[3])
    np.testing.assert_array_equal(frame.depth, depth_frames(5)[3])
    with pytest.raises(RecordingError, match="past the end"):
        rec.read_frame(5)
    with pytest.raises(ValueError):
        next(rec.frames(stride=0))


def test_frames_are_streamed(folder, monkeypatch):
    """Frames are read one at a time as the generator advances, never all up front."""
    import massviz.io.formats.folder as R

    rec = open_recording(folder)
    reads = []
    real = R.read_depth_png
    monkeypatch.setattr(R, "read_depth_png", lambda p, w, h, **kw: reads.append(Path(p).name) or real(p, w, h, **kw))
    gen = rec.frames()
    assert isinstance(gen, types.GeneratorType) and reads == []
    first = next(gen)
    assert first.index == 0 and reads == ["000000.png"]
    next(gen)
    assert reads == ["000000.png", "000001.png"]


def test_video_folder(tmp_path):
    rgbs = [np.full((48, 64, 3), c, np.uint8) for c in ((200, 30, 30), (30, 200, 30), (30, 30, 200), (120, 120, 0))]
    rec = open_recording(write_recording(tmp_path / "v", rgbs, depth_frames(4, 64, 48), video=True))
    assert (rec.kind, rec.id, rec.num_frames, rec.width, rec.height) == ("folder", "v", 4, 64, 48)
    assert rec.rgb_video == tmp_path / "v" / "rgb.mp4" and rec.intrinsics is None
    got = list(rec.frames(stride=2))
    assert [f.index for f in got] == [0, 2]
    for f in got:  # mp4v is lossy, flat colours survive within a few levels (and in RGB order)
        assert np.abs(f.rgb.astype(int) - rgbs[f.index]).max() <= 12
        np.testing.assert_array_equal(f.depth, depth_frames(4, 64, 48)[f.index])
    assert np.abs(rec.read_frame(3).rgb.astype(int) - rgbs[3]).max() <= 12


def test_ccm_layout(shared_dir):
    root = shared_dir / "ccm_real"
    rec = open_recording(root / "view1" / "rgb" / "000000.mp4")
    assert (rec.kind, rec.id, rec.config_id) == ("ccm", "000000", "0")
    assert (rec.num_frames, rec.width, rec.height) == (2, 1280, 720)
    k = rec.intrinsics
    assert k.fx == pytest.approx(923.62, abs=0.01) and k.fy == pytest.approx(923.54, abs=0.01)
    assert k.cx == pytest.approx(649.79, abs=0.01) and k.cy == pytest.approx(361.16, abs=0.01)
    assert (k.width, k.height) == (1280, 720)
    frames = list(rec.frames())
    assert [f.index for f in frames] == [0, 1]
    lossless = [cv2.cvtColor(cv2.imread(str(root / n)), cv2.COLOR_BGR2RGB) for n in ("frame_1_rgb.png",
                                                                                        "frame_20_rgb.png")]
    for i, f in enumerate(frames):
        np.testing.assert_array_equal(f.depth, cv2.imread(str(root / "view1/depth/000000" / f"{i:04d}.png"),
                                                          cv2.IMREAD_UNCHANGED))
        err = [np.abs(f.rgb.astype(int) - ref).mean() for ref in lossless]
        assert err[i] < 5 and err[i] < err[1 - i]  # decoded frame i is the i-th lossless frame, in RGB order
    assert find_recordings(root, view=1) == [root / "view1" / "rgb" / "000000.mp4"]



@pytest.mark.parametrize("build", OPEN_ERRORS, ids=lambda f: f.__name__[4:])
def test_bad_recording_is_one_clear_error(tmp_path, build):
    path, culprit, what = build(tmp_path / "rec")
    with pytest.raises(RecordingError) as info:
        open_recording(path)
    msg = str(info.value)
    assert "\n" not in msg
    assert msg.startswith(f"{culprit}: "), msg  # names the file ...
    assert re.search(what, msg), msg  # ... and what is wrong with it


def test_corrupt_depth_in_the_middle_raises_while_streaming(tmp_path):
    path, culprit, what = corrupt_middle_depth(tmp_path / "rec")
    rec = open_recording(path)
    gen = rec.frames()
    assert [next(gen).index, next(gen).index] == [0, 1]
    with pytest.raises(RecordingError, match=what) as info:
        next(gen)
    assert str(info.value).startswith(f"{culprit}: ")


def test_find_recordings_points_at_the_broken_recording(tmp_path):
    """A recording folder without depth is still found as a recording, so opening it says what is missing."""
    path, culprit, what = bad_missing_depth(tmp_path / "rec")
    assert find_recordings(path) == [path]
    parent = tmp_path / "many"
    write_recording(parent / "b", rgb_frames(1), depth_frames(1))
    write_recording(parent / "a", rgb_frames(1), depth_frames(1), video=True)
    assert find_recordings(parent) == [parent / "a", parent / "b"]
