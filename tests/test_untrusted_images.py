"""Image bombs by content: every image massviz reads from a user's folder (an RGB frame, a depth frame, a
ground-truth instance mask, a replayed detection's mask) goes through one reader
(``massviz.io.untrusted.decode_image``) that tells the format by its first bytes, refuses formats a recording does
not use and checks the size its header declares, all before decoding.

The bombs are generated: for each image kind, a file named as that kind's files are (``.png``) holding a bomb in
each format OpenCV or PIL decodes (PNG, JPEG, TIFF, GIF, BMP, WebP, Radiance HDR, PNM, PFM, OpenEXR, Sun raster,
JPEG 2000), each declaring about 10000x10000 pixels in a few KB (a few MB for the PNG and HDR ones, whose pixel data
really inflates to that size). Each is read in a child forked from a small
interpreter (``os.wait4`` gives the child's own peak resident memory): refused with massviz's error naming the
file, the child's peak under 300 MB.
"""
from __future__ import annotations

import json
import struct
import subprocess
import sys
import textwrap
import zlib
from pathlib import Path

import numpy as np
import pytest

from support import ROOT

#: the peak resident memory a child that refuses a bomb may reach (the interpreter with OpenCV and massviz's readers:
#: ~100 MB; one bomb decoded: 300 MB to several GB)
MAX_RSS_MB = 300
SIDE = 10000
KINDS = ("rgb", "depth", "ground-truth", "replay-mask")


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def png_bomb(channels_type: int = 2, depth: int = 8) -> bytes:
    """A PNG declaring SIDE x SIDE pixels whose pixel data (zeros, deflated) really inflates to that size."""
    row = 1 + SIDE * {0: 1, 2: 3, 6: 4}[channels_type] * depth // 8
    packer = zlib.compressobj(9)
    block = bytes(row * 100)
    data = b"".join(packer.compress(block) for _ in range(SIDE // 100)) + packer.flush()
    return (b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", struct.pack(">IIBBBBB", SIDE, SIDE, depth, channels_type, 0, 0, 0))
            + _chunk(b"IDAT", data) + _chunk(b"IEND", b""))


def jpeg_bomb() -> bytes:
    """A small JPEG whose start-of-frame says SIDE x SIDE."""
    import cv2

    data = bytearray(cv2.imencode(".jpg", np.zeros((16, 16, 3), np.uint8))[1].tobytes())
    sof = data.index(b"\xff\xc0")
    data[sof + 5:sof + 9] = struct.pack(">HH", SIDE, SIDE)
    return bytes(data)


def gif_bomb() -> bytes:
    import io

    from PIL import Image

    buf = io.BytesIO()
    Image.new("L", (16, 16)).save(buf, "GIF")
    data = bytearray(buf.getvalue())
    data[6:10] = struct.pack("<HH", SIDE, SIDE)
    desc = data.index(b"\x2c")
    data[desc + 5:desc + 9] = struct.pack("<HH", SIDE, SIDE)
    return bytes(data)


def bmp_bomb() -> bytes:
    header = struct.pack("<IiiHHIIiiII", 40, SIDE, SIDE, 1, 24, 0, 0, 2835, 2835, 0, 0)
    pixels = bytes(1024)
    return b"BM" + struct.pack("<IHHI", 14 + len(header) + len(pixels), 0, 0, 14 + len(header)) + header + pixels


def tiff_bomb() -> bytes:
    """An uncompressed 8-bit TIFF declaring SIDE x SIDE in one strip."""
    entries = [(256, 4, 1, SIDE), (257, 4, 1, SIDE), (258, 3, 1, 8), (259, 3, 1, 1), (262, 3, 1, 1),
               (273, 4, 1, 8 + 2 + 12 * 9 + 4), (277, 3, 1, 1), (278, 4, 1, SIDE), (279, 4, 1, SIDE * SIDE)]
    ifd = struct.pack("<H", len(entries)) + b"".join(
        struct.pack("<HHII", tag, kind, count, value) if kind == 4 else struct.pack("<HHIHH", tag, kind, count,
                                                                                     value, 0)
        for tag, kind, count, value in entries) + struct.pack("<I", 0)
    return b"II*\x00" + struct.pack("<I", 8) + ifd + bytes(4096)


def webp_bomb() -> bytes:
    """A lossy WebP whose VP8 frame header says 16383 x 16383 (the most it can)."""
    import cv2

    data = bytearray(cv2.imencode(".webp", np.zeros((16, 16, 3), np.uint8), [cv2.IMWRITE_WEBP_QUALITY, 50])[1])
    start = data.index(b"\x9d\x01\x2a")
    data[start + 3:start + 7] = struct.pack("<HH", 16383, 16383)
    return bytes(data)


def hdr_bomb() -> bytes:
    """A Radiance HDR of SIDE x SIDE float pixels in run-length-encoded scanlines: ~6 MB that decode to 1.2 GB."""
    runs = b"".join(bytes((128 + n, 128)) for n in [127] * (SIDE // 127) + [SIDE % 127])
    line = bytes((2, 2, SIDE >> 8, SIDE & 255)) + runs * 4
    return b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y %d +X %d\n" % (SIDE, SIDE) + line * SIDE


BOMBS = {
    "png": png_bomb,
    "png-16bit-grey": lambda: png_bomb(0, 16),
    "jpeg": jpeg_bomb,
    "tiff": tiff_bomb,
    "gif": gif_bomb,
    "bmp": bmp_bomb,
    "webp": webp_bomb,
    "radiance-hdr": hdr_bomb,
    "pnm": lambda: b"P6\n%d %d\n255\n" % (SIDE, SIDE) + bytes(4096),
    "pfm": lambda: b"PF\n%d %d\n-1.0\n" % (SIDE, SIDE) + bytes(4096),
    "openexr": lambda: b"v/1\x01" + bytes(4096),
    "sun-raster": lambda: struct.pack(">8I", 0x59A66A95, SIDE, SIDE, 24, SIDE * SIDE * 3, 1, 0, 0) + bytes(4096),
    "jpeg-2000": lambda: b"\x00\x00\x00\x0cjP  \r\n\x87\n" + bytes(4096),
}

#: run in a fresh interpreter: for each case, a forked child reads the file as its kind and exits 0 when massviz
#: refused it (its message in the case's .out file), 1 when it was read; the parent prints one JSON line per case
#: with the child's exit code and peak resident memory (``os.wait4``'s ``ru_maxrss``, KiB)
READER = textwrap.dedent("""
    import json, os, sys
    import cv2
    from massviz.errors import MassvizError
    from massviz.io.formats.common import read_depth_png, read_rgb
    from massviz.io.ground_truth import read_instance_image
    from massviz.detect.saved import ReplayDetector

    def read(kind, path):
        if kind == "rgb":
            return read_rgb(path)  # a recording's first frame: no size known yet
        if kind == "depth":
            return read_depth_png(path, 480, 270)
        if kind == "ground-truth":
            return read_instance_image(str(path), (480, 270))
        return ReplayDetector(path)

    for line in sys.stdin:
        kind, path = json.loads(line)
        pid = os.fork()
        if pid == 0:
            try:
                read(kind, path)
                code = 1
            except MassvizError as err:
                with open(path + ".out", "w") as fh:
                    fh.write(str(err))
                code = 0
            os._exit(code)
        _, status, usage = os.wait4(pid, 0)
        print(json.dumps([kind, path, os.waitstatus_to_exitcode(status), usage.ru_maxrss]), flush=True)
""")


def place(kind: str, data: bytes, folder: Path) -> Path:
    """The bomb where a file of ``kind`` is read from; the path the reader is given."""
    folder.mkdir(parents=True)
    if kind != "replay-mask":
        (folder / "000000.png").write_bytes(data)
        return folder / "000000.png"
    (folder / "m.png").write_bytes(data)
    (folder / "replay.json").write_text(json.dumps(
        {"detections": [{"frame": 0, "box": [10, 10, 60, 60], "score": 0.9, "class": "cup", "mask": "m.png"}]}))
    return folder / "replay.json"


@pytest.mark.slow
def test_image_bombs_in_every_format_are_refused_before_decoding_for_every_image_kind(tmp_path):
    """Every (kind, format) pair: one ``MassvizError`` naming the file, the reading child's peak under 300 MB."""
    cases = {}
    for fmt, make in BOMBS.items():
        data = make()
        assert len(data) < 8 << 20, (fmt, len(data))
        for kind in KINDS:
            path = place(kind, data, tmp_path / fmt / kind)
            cases[str(path)] = (kind, fmt, path.parent / ("m.png" if kind == "replay-mask" else "000000.png"))
    requests = "".join(json.dumps([kind, p]) + "\n" for p, (kind, _, _) in cases.items())
    run = subprocess.run([sys.executable, "-c", READER], input=requests, capture_output=True, text=True,
                         cwd=ROOT, env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"}, timeout=300)
    assert run.returncode == 0, run.stderr
    results = [json.loads(line) for line in run.stdout.splitlines()]
    assert len(results) == len(cases)
    bad = []
    for kind, path, code, maxrss_kb in results:
        _, fmt, image = cases[path]
        message = Path(path + ".out").read_text() if code == 0 else ""
        if code != 0 or str(image) not in message or maxrss_kb / 1024 > MAX_RSS_MB or "\n" in message:
            bad.append((kind, fmt, code, f"{maxrss_kb / 1024:.0f} MB", message[-150:]))
    assert bad == [], "\n".join(map(str, bad))


def test_a_radiance_hdr_named_png_is_refused_by_its_content_as_a_ground_truth_mask(tmp_path):
    """The first case of the class, in this process: a Radiance HDR declaring 10000x10000 float pixels named
    ``.png`` is a ``DataError`` naming it and saying what it is, never decoded."""
    from massviz.errors import DataError
    from massviz.io.ground_truth import read_instance_image

    path = place("ground-truth", BOMBS["radiance-hdr"](), tmp_path / "gt")
    with pytest.raises(DataError, match="Radiance HDR") as info:
        read_instance_image(str(path), (480, 270))
    assert info.value.path == str(path)


@pytest.mark.parametrize("fmt", ["png", "jpeg"])
def test_the_formats_a_recording_uses_still_read(fmt, tmp_path):
    """A real RGB frame in PNG or JPEG reads through the same reader (the checks refuse only what they must)."""
    import cv2

    from massviz.io.formats.common import read_rgb

    frame = np.random.default_rng(0).integers(0, 255, (27, 48, 3), dtype=np.uint8)
    path = tmp_path / f"000000.{'jpg' if fmt == 'jpeg' else 'png'}"
    cv2.imwrite(str(path), frame)
    assert read_rgb(path, 48, 27).shape == (27, 48, 3)
