"""Paths named inside a data file: relative, and inside the folder that file lives in."""
from __future__ import annotations

import os
import re
from pathlib import Path

from massviz.errors import DataError
from massviz.io.untrusted.text import _control, _short


def confined(base: str | Path, name, source: str | Path, what: str, error=DataError) -> Path:
    """``base / name`` for a relative path ``name`` read from the data file ``source``; ``error`` (naming
    ``source``) when it is not a non-empty relative path or leads outside ``base`` (``..``). The check is on the
    path as written: symlinks inside ``base`` are the file system's arrangement (frames linked to another disk) and
    are followed."""
    if not isinstance(name, str) or not name or "\x00" in name:
        raise error(f"{what} must be a relative file path, got {_short(name)}", source)
    if _control(name):
        raise error(f"{what} {name!r} contains control characters", source)
    rel = Path(name)
    if rel.is_absolute() or rel.drive or name.startswith(("/", "\\")):
        raise error(f"{what} {name!r} is an absolute path; paths in a data file must be relative to its folder "
                    f"({base})", source)
    norm = Path(os.path.normpath(rel))
    if norm.parts[:1] == ("..",) or str(norm) == ".":
        raise error(f"{what} {name!r} leads outside {base}; paths in a data file must stay inside its folder",
                    source)
    return Path(base) / norm


def frame_path(pattern, base: str | Path, frame: int, source, what: str, error=DataError) -> Path:
    """The file of ``frame`` for a per-frame path pattern read from a data file (e.g. meta.json's
    ``"gt/{frame:06d}.png"``): the only field allowed is ``{frame}`` or ``{frame:0Nd}`` (no attribute or index
    access, no huge widths), and the path must stay inside ``base`` (:func:`confined`)."""
    import string

    if not isinstance(pattern, str) or not pattern:
        raise error(f"{what} must be a path pattern such as \"gt/{{frame:06d}}.png\", got {_short(pattern)}", source)
    try:
        fields = [(f, spec, conv) for _, f, spec, conv in string.Formatter().parse(pattern) if f is not None]
    except ValueError as e:
        raise error(f"{what} {_short(pattern)} is not a format pattern ({e})", source) from None
    for name, spec, conv in fields:
        if name != "frame" or conv or not re.fullmatch(r"(0?[1-9]?d)?", spec or ""):
            raise error(f"{what} {_short(pattern)}: the only field allowed is {{frame}} or {{frame:0Nd}} "
                        "(N one digit)", source)
    return confined(base, pattern.format(frame=int(frame)), source, what, error)
