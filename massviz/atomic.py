"""Atomic file output: write to a temporary file beside the target, then rename it into place.

A reader never sees a half-written file, and an interrupted run leaves the previous file (if any) untouched.
"""
from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from massviz.errors import MassvizError


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path in ``path``'s folder (same suffix); on success rename it to ``path``.

    Write the whole file to the yielded path inside the ``with`` block. If the block raises, the temporary file is
    removed and ``path`` is left as it was. The new file gets the usual permissions (0666 minus the umask), not
    ``mkstemp``'s private 0600. A missing parent folder is a ``MassvizError``.
    """
    path = Path(path)
    if not path.parent.is_dir():
        raise MassvizError(f"cannot write: folder {path.parent} does not exist", path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
