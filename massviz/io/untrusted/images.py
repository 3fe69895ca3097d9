"""Images checked from their header: the size they declare bounded before anything is decoded."""
from __future__ import annotations

from pathlib import Path

from massviz.errors import MassvizError

#: largest image side and pixel count massviz decodes (any RGB-D camera frame is below: 4096x3072 is 12.6 Mpixel); a
#: file declaring more is refused from its header, before a decoder allocates anything.
MAX_IMAGE_SIDE = 16384
MAX_IMAGE_PIXELS = 1 << 24  # 16.8 Mpixel: at most 48 MiB decoded as 8-bit RGB, 32 MiB as 16-bit depth


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
    if size is None:
        return
    w, h = size
    if expected is not None and (w, h) != tuple(expected):
        raise error(f"{what} declares {w}x{h} pixels but {of} are {expected[0]}x{expected[1]}; not decoded", path)
    if w > MAX_IMAGE_SIDE or h > MAX_IMAGE_SIDE or w * h > MAX_IMAGE_PIXELS:
        raise error(f"{what} declares {w}x{h} pixels (at most {MAX_IMAGE_SIDE} per side and {MAX_IMAGE_PIXELS} "
                    "pixels); not decoded", path)
