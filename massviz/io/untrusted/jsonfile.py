"""JSON from a dataset or a user: size, nesting depth and integer digits bounded before parsing."""
from __future__ import annotations

import re
from pathlib import Path

from massviz.errors import DataError
from massviz.io.untrusted.bounded import read_bounded
from massviz.io.untrusted.text import _first_line

#: largest JSON file read from a dataset or a user (meta.json, intrinsics.json, ranges, class maps, exclusions).
MAX_JSON_BYTES = 16 << 20
#: deepest nesting of arrays/objects a JSON file may have (massviz's own files nest at most 4 deep).
MAX_JSON_DEPTH = 64
#: most digits of an integer in a JSON file (Python refuses > 4300 with a ValueError; no field needs > 20).
MAX_JSON_INT_DIGITS = 100


def _json_depth(text: str) -> int:
    """The deepest nesting of ``[``/``{`` in ``text``, brackets inside strings ignored; stops early once it
    exceeds MAX_JSON_DEPTH (the parser is never handed a document that would exhaust its recursion)."""
    depth = deepest = 0
    # strings (with their escapes) are removed first, so their brackets do not count
    for m in re.finditer(r'"(?:[^"\\]|\\.)*"|[\[\]{}]', text):
        tok = m.group()
        if tok in "[{":
            depth += 1
            if depth > deepest:
                deepest = depth
                if deepest > MAX_JSON_DEPTH:
                    break
        elif tok in "]}":
            depth -= 1
    return deepest


def _json_int(text: str) -> int:
    digits = len(text.lstrip("-"))
    if digits > MAX_JSON_INT_DIGITS:
        raise ValueError(f"an integer of {digits} digits (at most {MAX_JSON_INT_DIGITS})")
    return int(text)


def parse_json(text: str | bytes, source, what: str = "JSON file", error=DataError):
    """``text`` (from ``source``) parsed as JSON, untrusted: at most MAX_JSON_BYTES, nesting at most
    MAX_JSON_DEPTH deep (checked before parsing), integers of at most MAX_JSON_INT_DIGITS digits. ``error`` naming
    ``source`` otherwise — never ``RecursionError`` or Python's int-digits ``ValueError``."""
    import json

    if len(text) > MAX_JSON_BYTES:
        raise error(f"{what} is {len(text)} bytes; at most {MAX_JSON_BYTES} are read", source)
    if isinstance(text, bytes):
        try:
            text = text.decode("utf-8")
        except UnicodeDecodeError as err:
            raise error(f"cannot read {what}: not JSON (not UTF-8 text at byte {err.start})", source) from None
    if text.count("[") + text.count("{") > MAX_JSON_DEPTH and _json_depth(text) > MAX_JSON_DEPTH:
        raise error(f"cannot read {what}: it nests arrays/objects more than {MAX_JSON_DEPTH} deep", source)
    try:
        return json.loads(text, parse_int=_json_int)
    except json.JSONDecodeError as err:
        raise error(f"cannot read {what}: not valid JSON ({err.msg} at line {err.lineno} column {err.colno})",
                    source) from None
    except (ValueError, RecursionError, MemoryError) as err:
        raise error(f"cannot read {what}: not valid JSON ({_first_line(err)})", source) from None


def load_json(path: str | Path, what: str = "JSON file", error=DataError, max_bytes: int = MAX_JSON_BYTES):
    """The JSON document of the untrusted file ``path`` (see :func:`parse_json`); the size is checked before the
    file is read. ``error`` naming ``path`` for any failure (missing, unreadable, too big, malformed)."""
    path = Path(path)
    return parse_json(read_bounded(path, max_bytes, what, error), path, what, error)
