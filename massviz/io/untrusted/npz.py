""".npz arrays: declared and inflated sizes bounded before anything is inflated, never unpickled."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

#: most bytes of arrays an .npz (trace, replay, cache entry) may inflate to, all members together.
MAX_NPZ_BYTES = 1 << 29  # 512 MiB: a trace of an hour-long recording is far below
#: a member inflating to more than MAX_NPZ_SMALL bytes must compress at most this well (massviz's own traces: < 30:1;
#: a deflate bomb: ~1000:1).
MAX_NPZ_RATIO = 200
MAX_NPZ_SMALL = 1 << 20


def load_npz_checked(path: str | Path, max_bytes: int = MAX_NPZ_BYTES) -> dict[str, np.ndarray]:
    """The arrays of an .npz file, never unpickling and never allocating what the file only *declares*: the
    inflated sizes the zip directory declares must total at most ``max_bytes`` and each large member must compress
    at most MAX_NPZ_RATIO:1 (a deflate bomb is refused before anything is inflated); each member's .npy header
    (shape x item size) must fit in the member's size; members are read with bounded reads (never more than the
    declared size). ``ValueError`` (or ``zipfile.BadZipFile``/``OSError``) otherwise."""
    import zipfile

    total = 0
    with zipfile.ZipFile(path) as z:
        infos = z.infolist()
        names = [i.filename for i in infos]
        if len(set(names)) != len(names):
            raise ValueError("it holds two members of the same name")
        for info in infos:
            name = info.filename[:-4] if info.filename.endswith(".npy") else info.filename
            if not info.filename.endswith(".npy"):
                raise ValueError(f"member {name!r} is not a .npy array")
            total += info.file_size
            if total > max_bytes:
                raise ValueError(f"its arrays inflate to more than {max_bytes} bytes")
            if info.file_size > MAX_NPZ_SMALL and info.file_size > MAX_NPZ_RATIO * max(info.compress_size, 1):
                raise ValueError(f"array {name} inflates {info.compress_size} bytes to {info.file_size} (more than "
                                 f"{MAX_NPZ_RATIO}:1; a compression bomb?)")
            with z.open(info) as fh:
                version = np.lib.format.read_magic(fh)
                read = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                        else np.lib.format.read_array_header_2_0)
                shape, _, dtype = read(fh)
            if dtype.hasobject:
                raise ValueError(f"array {name} holds Python objects")
            declared = math.prod(shape) * dtype.itemsize
            if declared > info.file_size:
                raise ValueError(f"array {name} declares {declared} bytes but holds {info.file_size}")
        out = {}
        for info in infos:
            with z.open(info) as fh:  # ZipExtFile stops at the declared size and checks the CRC
                out[info.filename[:-4]] = np.lib.format.read_array(fh, allow_pickle=False)
        return out
