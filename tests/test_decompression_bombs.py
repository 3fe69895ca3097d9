"""Hostile inputs, files a dataset brings: decompression bombs (images, masks, videos that decode to gigabytes)
are refused from their header, before anything is decoded; smaller cases (a RealSense file whose duration is not a
number, a checkpoint of complex tensors) give massviz's one line and nothing else.

Each bomb case runs ``massviz`` in a process of its own (so it is ``slow``) and is held to
``hostile_runs.check_promise`` (one line naming the file, exit 2, nothing written) with a tighter memory bound:
:data:`BOMB_MEM_MB`.
"""
from __future__ import annotations

import json
import struct
import zlib
from pathlib import Path
from typing import Callable

import pytest

from fakes import Base, copy_sample, cup_box
from hostile_runs import Case, check_promise, folder_state, pipeline_argv, run_massviz

#: peak resident memory a run that meets a bomb may add to a clean run of the same command (the imports alone take
#: 0.5-0.8 GB, depending on the libraries installed; the bombs decoded before they were refused added 0.5-2.5 GB).
BOMB_EXTRA_MB = 100
#: ... and the bound below which any run passes.
BOMB_MEM_MB = 700


@pytest.fixture(scope="module")
def clean_peak_mb(base, tmp_path_factory) -> float:
    """Peak memory of a clean ``estimate`` of the 3-frame sample, run the way every case is."""
    work = tmp_path_factory.mktemp("clean_peak") / "w"
    work.mkdir()
    (work / "home").mkdir()
    argv = pipeline_argv(work, base, "estimate", copy_sample(work / "rec"), "--out", work / "p.csv", cache=False)
    run = run_massviz(argv, work)
    assert run.code == 0, run.stderr
    return run.peak_mb


def png_bomb(path: Path, width: int, height: int, depth: int = 16, color: int = 6) -> Path:
    """A real PNG of ``width`` x ``height`` zero pixels (``depth`` bits, PNG colour type ``color``: 0 grey, 2 RGB,
    6 RGBA): a few hundred KB that decode to gigabytes."""
    channels = {0: 1, 2: 3, 4: 2, 6: 4}[color]
    row = b"\0" * (1 + width * channels * depth // 8)
    z = zlib.compressobj(9)
    body = b"".join(z.compress(row) for _ in range(height)) + z.flush()

    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, depth, color, 0, 0, 0))
                     + chunk(b"IDAT", body) + chunk(b"IEND", b""))
    return path


def _replay_with_mask(work: Path, rec: Path, mask: Path) -> Path:
    replay = work / "replay.json"
    replay.write_text(json.dumps({"detections": [{"frame": 1, "box": cup_box(1), "score": 0.9, "class": "cup",
                                                  "mask": mask.name}]}))
    return replay


def video_bomb(path: Path, width: int, height: int) -> Path:
    """An MJPEG video (named as given: the container is probed, not the name) of one black ``width`` x ``height``
    frame: a few hundred KB that decode to ``3 * width * height`` bytes."""
    import cv2
    import numpy as np

    tmp = path.with_suffix(".avi")
    writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (width, height))
    writer.write(np.zeros((height, width, 3), np.uint8))
    writer.release()
    tmp.replace(path)
    return path


def bomb_case(where: str, size: tuple[int, int], depth: int = 16, color: int = 6) -> Callable[[Path, Base], Case]:
    def build(work: Path, b: Base) -> Case:
        rec = copy_sample(work / "rec", video=where == "video")
        w, h = size
        replay = None
        if where == "video":
            culprit = video_bomb(rec / "rgb.mp4", w, h)
            what = rf"video declares {w}x{h} frames \(at most"
        elif where in ("depth", "rgb", "rgb-first", "gt"):
            sub = {"rgb-first": "rgb"}.get(where, where)
            frame = 0 if where == "rgb-first" else 1
            culprit = png_bomb(rec / sub / f"{frame:06d}.png", w, h, depth, color)
            what = (rf"declares {w}x{h} pixels \(at most" if where == "rgb-first"
                    else rf"declares {w}x{h} pixels but the recording's frames are 480x270; not decoded")
        else:  # a replay mask: bigger than massviz decodes, or a full frame of another size than the recording's
            mask = png_bomb(work / "mask.png", w, h, depth, color)
            replay = _replay_with_mask(work, rec, mask)
            culprit = mask if where == "mask" else replay
            what = "declares" if where == "mask" else r"its mask is a \d+x\d+ image, neither its box nor a 480x270"
        out = work / "p.csv"
        argv = pipeline_argv(work, b, "estimate", rec, "--out", out, replay=replay, cache=False)
        return Case("", argv, culprit, what, [out])
    return build


BOMBS = {
    "bomb-depth-png-8000x8000-rgba16": bomb_case("depth", (8000, 8000)),
    "bomb-rgb-png-8000x8000-rgba16": bomb_case("rgb", (8000, 8000)),
    "bomb-rgb-first-frame-8000x8000-rgba16": bomb_case("rgb-first", (8000, 8000)),
    "bomb-ground-truth-mask-8000x8000-rgba16": bomb_case("gt", (8000, 8000)),
    "bomb-replay-mask-8000x8000-rgba16": bomb_case("mask", (8000, 8000)),
    "bomb-replay-mask-full-frame-4000x3000-grey": bomb_case("mask-frame", (4000, 3000), 8, 0),
    "bomb-depth-png-16000x4000-grey16": bomb_case("depth", (16000, 4000), 16, 0),
    "bomb-ground-truth-mask-4000x3000-grey": bomb_case("gt", (4000, 3000), 8, 0),
    "bomb-video-12000x12000": bomb_case("video", (12000, 12000)),
}


@pytest.mark.slow  # a massviz process: its peak memory is measured
@pytest.mark.parametrize("name", list(BOMBS))
def test_a_decompression_bomb_is_refused_from_its_header(name, base, clean_peak_mb, tmp_path):
    work = tmp_path / "w"
    work.mkdir()
    (work / "home").mkdir()
    case = BOMBS[name](work, base)
    case.name = name
    before = folder_state(work, tuple(work / w for w in ("cache", "usercache", "xdg", "home", "tmpdir")))
    run = run_massviz(case.argv, work)
    check_promise(case, run, work, before)
    bound = max(BOMB_MEM_MB, clean_peak_mb + BOMB_EXTRA_MB)
    assert run.peak_mb < bound, f"{name}: peak memory {run.peak_mb:.0f} MB (a clean run: {clean_peak_mb:.0f} MB)"


# ====================================================================================== checkpoints of complex numbers
COMPLEX = {"complex64-linear": ("linear3.weight", "complex64"), "complex128-bn-mean": ("bn1.running_mean", "complex128"),
           "complex64-conv": (None, "complex64")}


@pytest.mark.parametrize("name", list(COMPLEX))
def test_a_checkpoint_of_complex_tensors_is_massviz_s_one_line(name, base, tmp_path, capsys):
    """Loading complex weights into MassNet drops their imaginary parts with a UserWarning of torch's: refused,
    one line naming the file and the parameter, and no warning printed besides."""
    import warnings

    import torch

    from massviz import cli

    key, dtype = COMPLEX[name]
    payload = torch.load(base.weights, weights_only=True)
    key = key or next(k for k in payload["state_dict"] if k.endswith(".weight") and payload["state_dict"][k].ndim == 4)
    payload["state_dict"][key] = payload["state_dict"][key].to(getattr(torch, dtype))
    ckpt = tmp_path / "ckpt.torch"
    torch.save(payload, ckpt)
    out = tmp_path / "p.csv"
    argv = pipeline_argv(tmp_path, base, "estimate", copy_sample(tmp_path / "rec"), "--out", out, weights=ckpt)
    capsys.readouterr()
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        code = cli.main([str(a) for a in argv])
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert code == 2 and len(err) == 1 and not out.exists(), err
    assert err[0].startswith(f"massviz estimate: error: {ckpt}: parameter {key} holds complex numbers ({dtype})"), err
    assert [str(w.message) for w in seen] == []


# ====================================================================================== RealSense timing that is no number
REALSENSE_TIMES = {"nan": lambda i: float("nan"), "inf": lambda i: float("inf"), "minus-inf": lambda i: float("-inf"),
                   "backwards": lambda i: 1000.0 - 100.0 * i}


@pytest.mark.parametrize("command", ["live", pytest.param("estimate", marks=pytest.mark.slow)])
@pytest.mark.parametrize("times", [pytest.param(n, marks=() if i == 0 else pytest.mark.slow)
                                   for i, n in enumerate(REALSENSE_TIMES)])
def test_a_realsense_file_whose_duration_is_no_number_is_one_line(command, times, base, tmp_path, capsys):
    """Frames stamped NaN, inf or going backwards: the duration ``live --file`` plays in real time is not a number
    (it played and exited 0); one line naming the file, exit 2, nothing written."""
    pytest.importorskip("pyrealsense2")
    from massviz import cli
    from massviz.io.formats.realsense_decode import import_rs
    from massviz.io.formats.realsense_write import SoftwareRig
    from massviz.io.recording import open_recording

    sample = open_recording(Path(__file__).resolve().parents[1] / "data_samples" / "cup_handover")
    db3 = tmp_path / "cam.db3"
    rig = SoftwareRig(import_rs(), sample.intrinsics, 30.0)
    with rig.record(db3):
        for i, frame in enumerate(sample.frames(indices=range(3))):
            rig.push(frame, i, REALSENSE_TIMES[times](i))
    work = tmp_path / "w"
    work.mkdir()
    if command == "live":
        argv = ["live", "--file", db3, "--rrd", work / "o.rrd", "--save", work / "rec", "--no-cache", "--quiet",
                "--detector", "replay", "--replay", base.replay, "--weights", base.weights]
    else:
        argv = pipeline_argv(work, base, "estimate", db3, "--out", work / "p.csv", cache=False)
    capsys.readouterr()
    code = cli.main([str(a) for a in argv])
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert code == 2 and len(err) == 1 and err[0].startswith(f"massviz {command}: error: {db3}: frame "), err
    assert "not a playable RealSense recording" in err[0]
    assert list(work.iterdir()) == []
