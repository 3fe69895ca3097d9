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


def printable(text, keep: str = "") -> str:
    """``text`` safe to print on a terminal: every control, C1 or bidirectional-override character except those in
    ``keep`` (e.g. ``"\\n\\r\\t"`` for whole progress output) is written as its escape (``\\x1b``, ``\\u202e``), so
    a name from a data file cannot move the cursor, retitle the window or clear the screen."""
    text = str(text)

    def escape(m: re.Match) -> str:
        c = m.group()
        if c in keep:
            return c
        return f"\\x{ord(c):02x}" if ord(c) < 0x100 else f"\\u{ord(c):04x}"

    return _CONTROL.sub(escape, text)


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
