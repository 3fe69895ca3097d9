"""massviz.io.recording: the two layouts, streaming, stride, and every malformed input as one RecordingError.

Recordings are built in tmp_path from numpy arrays, so every expected pixel is known. ``write_recording`` and
``write_video`` are also used by test_selection / test_pipeline / test_cli.
"""
from __future__ import annotations

import json
import re
import types
from pathlib import Path

import cv2
import numpy as np
import pytest

from massviz.errors import RecordingError
from massviz.io.recording import find_recordings, open_recording

W, H = 32, 24


def rgb_frames(n: int, width: int = W, height: int = H) -> list[np.ndarray]:
    """n distinct RGB frames: flat colour per frame plus a gradient, so frames and channels are told apart."""
    out = []
    for i in range(n):
        img = np.zeros((height, width, 3), np.uint8)
        img[..., 0] = (40 * i + 10) % 256
        img[..., 1] = np.arange(width, dtype=np.uint8)[None, :] * 3
        img[..., 2] = 200 - 20 * i
        out.append(img)
    return out


def depth_frames(n: int, width: int = W, height: int = H) -> list[np.ndarray]:
    """n 16-bit depth maps (mm) with values above 255, so an 8-bit read would show."""
    return [np.full((height, width), 1000 + 100 * i, np.uint16) + np.arange(width, dtype=np.uint16)[None, :]
            for i in range(n)]


def write_video(path: Path, rgbs, fps: float = 30.0) -> Path:
    h, w = rgbs[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
    assert writer.isOpened()
    for rgb in rgbs:
        writer.write(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    writer.release()
    return path


def write_recording(root: Path, rgbs, depths, *, video: bool = False, intrinsics: dict | None = None,
                    meta: dict | None = None) -> Path:
    """A massviz recording folder: rgb/NNNNNN.png (or rgb.mp4), depth/NNNNNN.png, intrinsics.json, meta.json."""
    root.mkdir(parents=True, exist_ok=True)
    if video:
        write_video(root / "rgb.mp4", rgbs)
    else:
        (root / "rgb").mkdir()
        for i, rgb in enumerate(rgbs):
            assert cv2.imwrite(str(root / "rgb" / f"{i:06d}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    (root / "depth").mkdir()
    for i, depth in enumerate(depths):
        assert cv2.imwrite(str(root / "depth" / f"{i:06d}.png"), depth)
    if intrinsics is not None:
        (root / "intrinsics.json").write_text(json.dumps(intrinsics))
    if meta is not None:
        (root / "meta.json").write_text(json.dumps(meta))
    return root


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
    for f, rgb, depth in zip(frames, rgb_frames(5), depth_frames(5)):
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


# ------------------------------------------------------------------------------------------------------- bad inputs
def _png(path: Path, array) -> None:
    assert cv2.imwrite(str(path), array)


def bad_missing_depth(root: Path) -> tuple[Path, Path, str]:
    write_recording(root, rgb_frames(3), [])
    (root / "depth").rmdir()
    return root, root, r"no depth \(no depth/ folder\): massviz estimates mass from RGB-D: .* 'massviz log REC"


def bad_fewer_depth(root: Path):
    write_recording(root, rgb_frames(3), depth_frames(2))
    return root, root / "depth", "2 depth frames for 3 RGB frames"


def bad_depth_8bit(root: Path):
    write_recording(root, rgb_frames(2), depth_frames(2))
    _png(root / "depth" / "000000.png", np.full((H, W), 200, np.uint8))
    return root, root / "depth" / "000000.png", "16-bit.*8-bit"


def bad_depth_size(root: Path):
    write_recording(root, rgb_frames(2), depth_frames(2, W // 2, H // 2))
    return root, root / "depth" / "000000.png", f"depth image declares {W // 2}x{H // 2} pixels but the recording's frames are {W}x{H}; not decoded"


def bad_depth_rgb(root: Path):
    write_recording(root, rgb_frames(2), depth_frames(2))
    _png(root / "depth" / "000000.png", np.zeros((H, W, 3), np.uint16) + 1000)
    return root, root / "depth" / "000000.png", "single-channel.*3 channels"


def bad_video_garbage(root: Path):
    write_recording(root, rgb_frames(1), depth_frames(2), video=True)
    (root / "rgb.mp4").write_bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    return root, root / "rgb.mp4", "cannot decode video"


def bad_video_empty(root: Path):
    write_recording(root, rgb_frames(1), depth_frames(2), video=True)
    (root / "rgb.mp4").write_bytes(b"")
    return root, root / "rgb.mp4", "empty"


def bad_empty_folder(root: Path):
    root.mkdir()
    return root, root, "empty folder"


def bad_missing_path(root: Path):
    return root, root, "no such file or directory"


def bad_intrinsics_json(root: Path):
    write_recording(root, rgb_frames(2), depth_frames(2))
    (root / "intrinsics.json").write_text('{"fx": 30, "fy": ')
    return root, root / "intrinsics.json", "not valid JSON"


def bad_intrinsics_keys(root: Path):
    write_recording(root, rgb_frames(2), depth_frames(2), intrinsics={"fx": 30.0, "fy": 31.0})
    return root, root / "intrinsics.json", "intrinsics need"


def bad_meta_json(root: Path):
    write_recording(root, rgb_frames(2), depth_frames(2))
    (root / "meta.json").write_text("[1, 2")
    return root, root / "meta.json", "not valid JSON"


def bad_meta_fps(root: Path):
    write_recording(root, rgb_frames(2), depth_frames(2))
    (root / "meta.json").write_text('{"fps": "thirty"}')
    return root, root / "meta.json", "'fps' must be a number"


#: each builder writes a broken recording under a root and returns (path to open, file the error must name, what).
OPEN_ERRORS = [bad_missing_depth, bad_fewer_depth, bad_depth_8bit, bad_depth_size, bad_depth_rgb, bad_video_garbage,
               bad_video_empty, bad_empty_folder, bad_missing_path, bad_intrinsics_json, bad_intrinsics_keys,
               bad_meta_json, bad_meta_fps]


def corrupt_middle_depth(root: Path):
    """Opens fine (only the first depth frame is checked up front); frame 2's depth is not a PNG."""
    write_recording(root, rgb_frames(4), depth_frames(4))
    (root / "depth" / "000002.png").write_bytes(b"\x89PNG\r\n\x1a\n truncated")
    return root, root / "depth" / "000002.png", "cannot read depth image"


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
