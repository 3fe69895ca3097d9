"""Images checked from their header: the format told by their first bytes, the size (and channels) they declare
bounded before anything is decoded; :func:`decode_image` is the one reader of an image from a user's folder."""
from __future__ import annotations

from pathlib import Path

from massviz.errors import MassvizError

#: largest image side and pixel count massviz decodes (any RGB-D camera frame is below: 4096x3072 is 12.6 Mpixel); a
#: file declaring more is refused from its header, before a decoder allocates anything.
MAX_IMAGE_SIDE = 16384
MAX_IMAGE_PIXELS = 1 << 24  # 16.8 Mpixel: at most 48 MiB decoded as 8-bit RGB, 32 MiB as 16-bit depth


#: the formats massviz reads a recording's images in, by their first bytes
FORMATS = {"PNG": (b"\x89PNG\r\n\x1a\n",), "JPEG": (b"\xff\xd8\xff",)}
#: other formats a decoder (OpenCV, PIL) would read by their content, named in the refusal
OTHER_FORMATS = {"GIF": (b"GIF87a", b"GIF89a"), "TIFF": (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"),
                 "BMP": (b"BM",), "Radiance HDR": (b"#?RADIANCE", b"#?RGBE"), "OpenEXR": (b"v/1\x01",),
                 "JPEG 2000": (b"\x00\x00\x00\x0cjP  \r\n", b"\xff\x4f\xff\x51"),
                 "PNM/PFM": tuple(b"P%d" % i for i in range(1, 8)) + (b"Pf", b"PF"), "Sun raster": (b"\x59\xa6\x6a\x95",),
                 "ICO": (b"\x00\x00\x01\x00",), "Photoshop": (b"8BPS",), "QOI": (b"qoif",)}
#: the most bytes an image may decode to (4096 x 4096 RGB at 8 bits: 48 MiB)
MAX_DECODED_BYTES = 64 << 20
#: PNG colour type -> channels it decodes to (a palette image decodes to 3)
_PNG_CHANNELS = {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}


def image_format(head: bytes) -> str | None:
    """The format of an image whose file starts with ``head`` (``PNG``, ``JPEG``, ``GIF``, ...); None: unknown."""
    for name, magics in (*FORMATS.items(), *OTHER_FORMATS.items()):
        if any(head.startswith(m) for m in magics):
            return name
    if head[:4] == b"RIFF" and head[8:12] == b"WEBP":
        return "WebP"
    return None


def png_header_size(head: bytes) -> tuple[int, int] | None:
    """(width, height) of the PNG whose first 24 bytes are ``head`` (its IHDR); None when it is not a PNG's start."""
    import struct

    if len(head) >= 24 and head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR":
        return struct.unpack(">II", head[16:24])
    return None


def image_header_size(path: str | Path, data: bytes | None = None) -> tuple[int, int] | None:
    """(width, height) an image file declares in its header, without decoding it; None when unknown. ``data``: the
    file's bytes when the caller has read them already (the file is then not opened again)."""
    import io
    import warnings

    if data is None:
        try:
            with open(path, "rb") as fh:
                head = fh.read(24)
        except OSError:
            return None
    else:
        head = data[:24]
    if (size := png_header_size(head)) is not None:
        return size
    from PIL import Image

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with Image.open(path if data is None else io.BytesIO(data)) as img:
                return img.size
    except Image.DecompressionBombError:  # PIL's own bound (> 179 Mpixel) is above ours
        return (MAX_IMAGE_PIXELS, MAX_IMAGE_PIXELS)
    except Exception:  # noqa: BLE001 - not an image PIL knows: the decoder reports it
        return None


def check_image_size(path: str | Path, error=MassvizError, what: str = "image", data: bytes | None = None,
                     expected: tuple[int, int] | None = None, of: str = "the recording's frames") -> None:
    """Refuse (``error`` naming ``path``) an image whose header declares another size than ``expected`` (width,
    height; ``of`` says whose size that is), or more than MAX_IMAGE_SIDE per side or MAX_IMAGE_PIXELS pixels, before
    it is decoded (a small file may declare gigabytes of pixels). ``data``: the file's bytes when already read."""
    size = image_header_size(path, data)
    if size is not None:
        _check_declared(size, path, error, what, expected, of)


def _check_declared(size: tuple[int, int], path, error, what: str, expected, of: str) -> None:
    w, h = size
    if expected is not None and (w, h) != tuple(expected):
        raise error(f"{what} declares {w}x{h} pixels but {of} are {expected[0]}x{expected[1]}; not decoded", path)
    if w > MAX_IMAGE_SIDE or h > MAX_IMAGE_SIDE or w * h > MAX_IMAGE_PIXELS:
        raise error(f"{what} declares {w}x{h} pixels (at most {MAX_IMAGE_SIDE} per side and {MAX_IMAGE_PIXELS} "
                    "pixels); not decoded", path)


def _declared_bytes(fmt: str, head: bytes, path, data: bytes) -> tuple[tuple[int, int] | None, int]:
    """((width, height), bytes per pixel) the image declares in its header; (None, 0) when it declares none."""
    import io
    import warnings

    if fmt == "PNG":
        size = png_header_size(head)
        if size is None or len(head) < 26:
            return None, 0
        depth, colour = head[24], head[25]
        return size, _PNG_CHANNELS.get(colour, 4) * (2 if depth == 16 else 1)
    from PIL import Image

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with Image.open(io.BytesIO(data), formats=[fmt]) as img:
                return img.size, max(len(img.getbands()), 1)
    except Image.DecompressionBombError:
        return (MAX_IMAGE_PIXELS, MAX_IMAGE_PIXELS), 1
    except Exception:  # noqa: BLE001 - no header PIL can read: refused by the caller
        return None, 0


def decode_image(path: str | Path, what: str, *, flags: int, formats: tuple[str, ...] = ("PNG", "JPEG"),
                 error=MassvizError, data: bytes | None = None, expected: tuple[int, int] | None = None,
                 of: str = "the recording's frames", max_bytes: int = 256 << 20):
    """The one reader of an image from a user's folder (frames, depth, masks): the file read with a bounded read
    (``data``: its bytes when already read), its format told by its first bytes and refused unless one of
    ``formats`` (a Radiance ``.hdr`` named ``.png`` is not decoded), its header's size checked as
    :func:`check_image_size` does (``expected``, ``of``) and what it decodes to (size x channels x bytes) bounded by
    :data:`MAX_DECODED_BYTES`, all before it is decoded with OpenCV (``flags``). Returns the array, or None when
    the file is empty, not an image format known by its first bytes or without a header declaring its size (it is
    then not decoded), or cannot be
    decoded (a truncated file); any refusal is ``error`` naming ``path``."""
    import cv2
    import numpy as np

    from massviz.io.untrusted.bounded import read_bounded

    if data is None:
        data = read_bounded(path, max_bytes, what, error)
    fmt = image_format(data[:32])
    if fmt is None:  # empty, or no format a decoder knows: nothing is decoded, the caller says it is not an image
        return None
    if fmt not in formats:
        raise error(f"{what} is a {fmt} image by its content, not {' or '.join(formats)}; not decoded", path)
    size, per_pixel = _declared_bytes(fmt, data[:32], path, data)
    if size is None:  # no header that declares a size (cut short): not decoded, the caller says it is unreadable
        return None
    _check_declared(size, path, error, what, expected, of)
    w, h = size
    if w * h * per_pixel > MAX_DECODED_BYTES:
        raise error(f"{what} declares {w}x{h} pixels of {per_pixel} bytes ({w * h * per_pixel} bytes decoded; at "
                    f"most {MAX_DECODED_BYTES}); not decoded", path)
    return cv2.imdecode(np.frombuffer(data, np.uint8), flags)
