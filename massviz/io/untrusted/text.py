"""Text from data files: ids (bounded, no control characters), terminal escaping, file names."""
from __future__ import annotations

import re
import unicodedata

from massviz.errors import DataError

#: largest id (recording id, config id) taken from a data file, in characters.
MAX_ID_CHARS = 200

_CONTROL = re.compile(r"[\x00-\x1f\x7f-\x9f\u2028\u2029\u200e\u200f\u202a-\u202e\u2066-\u2069]")


def _control(text: str) -> bool:
    return bool(_CONTROL.search(text))


def text_id(value, what: str, source, error=DataError) -> str:
    """An id read from a data file as text: a string (or an integer), 1..MAX_ID_CHARS characters, no control or
    bidirectional-override characters (they would rewrite the terminal line or the CSV row it is printed in)."""
    if isinstance(value, bool) or not isinstance(value, (str, int)):
        raise error(f"{what} must be a string, got {type(value).__name__} {_short(value)}", source)
    text = str(value)
    if not text.strip():
        raise error(f"{what} is empty", source)
    if len(text) > MAX_ID_CHARS:
        raise error(f"{what} is {len(text)} characters long (at most {MAX_ID_CHARS})", source)
    if _control(text):
        raise error(f"{what} {text!r} contains control characters", source)
    return text


#: every character that is not printable ASCII: those ``printable`` looks at
_NOT_ASCII_PRINTABLE = re.compile(r"[^\x20-\x7e]")


def _unprintable(c: str) -> bool:
    """A control (C0, DEL, C1), format (bidirectional marks and overrides, zero-width), surrogate, private-use or
    unassigned character, or a line or paragraph separator."""
    category = unicodedata.category(c)
    return category[0] == "C" or category in ("Zl", "Zp")


def printable(text, keep: str = "", max_chars: int | None = None) -> str:
    """``text`` (its first ``max_chars`` characters, when given) safe to print on a terminal and to write in a CSV
    cell: every control, format (bidirectional override, zero-width), surrogate, private-use, unassigned, line- or
    paragraph-separator character except those in ``keep`` (e.g. ``"\\n\\r\\t"`` for whole progress output) is
    written as its escape (``\\n``, ``\\x1b``, ``\\u202e``), so a name from a data file or a device cannot move
    the cursor, retitle the window or clear the screen."""
    text = str(text) if max_chars is None else str(text)[:max_chars]

    def escape(m: re.Match) -> str:
        c = m.group()
        if c in keep or not _unprintable(c):
            return c
        return c.encode("unicode_escape").decode("ascii")

    return _NOT_ASCII_PRINTABLE.sub(escape, text)


def safe_filename(text: str, max_chars: int = 100) -> str:
    """``text`` as one file-name component: letters, digits and ``_.-`` kept, any run of anything else (``/``,
    ``\\``, ``..``, spaces, ``:``) replaced by one ``_``, leading/trailing ``._`` stripped; never empty, never
    ``.``/``..`` or hidden (``../../x/y`` -> ``x_y``)."""
    text = unicodedata.normalize("NFKC", str(text))
    safe = re.sub(r"[^A-Za-z0-9_.-]+", "_", text)
    safe = re.sub(r"_{2,}", "_", re.sub(r"\.{2,}", "_", safe)).strip("._")[:max_chars]
    return safe or "_"



def _short(value, n: int = 60) -> str:
    if hasattr(value, "item") and getattr(value, "shape", None) == ():  # a numpy scalar: 2.5, not np.float64(2.5)
        value = value.item()
    text = repr(value)
    return text if len(text) <= n else text[:n] + "..."


def _first_line(err: BaseException) -> str:
    lines = str(err).splitlines()
    return lines[0][:200] if lines else type(err).__name__
