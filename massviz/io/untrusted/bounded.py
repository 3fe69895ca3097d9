"""The one bounded read of an untrusted file: its size checked before anything is read."""
from __future__ import annotations

import os
from pathlib import Path

from massviz.errors import DataError


def read_bounded(path: str | Path, limit: int, what: str, error=DataError, *, hint: str = "",
                 with_stats: bool = False):
    """The bytes of the untrusted file ``path``, at most ``limit``: the size is checked from the open file before
    anything is read (a sparse 2 TiB file is refused at once) and at most ``limit + 1`` bytes are read (a file that
    grows past the bound while read is refused too). ``error`` naming ``path`` for any failure, in one line: missing
    or unreadable (``cannot read WHAT (reason)``), a directory, too big (``hint``: added to the bound, e.g. what such
    files usually weigh). The one bounded read of massviz: frame files, JSON, calibration pickles.

    ``with_stats``: (bytes, ``os.stat_result`` of the open file before and after it was read): the caller can
    tell a file that changed while it was read (the bytes may be a mix of two versions)."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            before = os.fstat(fh.fileno())
            if before.st_size > limit:
                raise error(f"{what} is {before.st_size} bytes (at most {limit}{'; ' + hint if hint else ''}); not "
                            "read", path)
            data = fh.read(limit + 1)
            after = os.fstat(fh.fileno()) if with_stats else None
    except IsADirectoryError:
        raise error(f"{what} is a directory, not a file", path) from None
    except OSError as err:
        raise error(f"cannot read {what} ({err.strerror or err})", path) from None
    if len(data) > limit:
        raise error(f"{what} is larger than {limit} bytes; not read", path)
    return (data, before, after) if with_stats else data
