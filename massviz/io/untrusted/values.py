"""Numbers from data files and options: finite, in range, integral where they must be; JSON without NaN."""
from __future__ import annotations

import math
import numbers

import numpy as np

from massviz.errors import DataError
from massviz.io.untrusted.text import _short

#: largest integer a file may give for a frame index or a pixel coordinate.
MAX_INDEX = 2**31 - 1


def json_safe(value):
    """``value`` (dicts, lists, numbers) with every non-finite float replaced by None: JSON has no NaN/Infinity
    and massviz writes none (``json.dumps(..., allow_nan=False)`` then cannot fail)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, np.floating):
        return json_safe(float(value))
    return value



def number(value, what: str, source=None, *, lo: float | None = None, hi: float | None = None,
           lo_open: bool = False, hi_open: bool = False, integral: bool = False, error=DataError):
    """``value`` (from a file or an option) as a float — an int when ``integral`` — checked: a real number (not a
    bool, not text), finite, integral when asked, within [lo, hi] (``lo_open``: > lo, ``hi_open``: < hi). A float
    zero is +0.0 (``-0`` is read as 0). ``error`` names ``source``."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise error(f"{what} must be a number, got {_short(value)}", source)
    try:
        f = float(value)
    except OverflowError:
        f = math.inf
    if not math.isfinite(f):
        raise error(f"{what} must be a finite number{_range(lo, hi, lo_open, hi_open)}, got {_short(value)}", source)
    if integral:
        if isinstance(value, numbers.Integral):
            out = int(value)
        elif f.is_integer():
            out = int(f)
        else:
            raise error(f"{what} must be an integer, got {_short(value)}", source)
    else:
        out = f + 0.0  # -0.0 + 0.0 is +0.0
    if lo is not None and (out <= lo if lo_open else out < lo):
        raise error(f"{what} must be {'>' if lo_open else '>='} {lo:g}, got {_short(value)}", source)
    if hi is not None and (out >= hi if hi_open else out > hi):
        raise error(f"{what} must be {'<' if hi_open else '<='} {hi:g}, got {_short(value)}", source)
    return out


def _range(lo, hi, lo_open: bool, hi_open: bool) -> str:
    """`` in [lo, hi)`` (or `` > lo``, `` <= hi``) for a message; empty without bounds."""
    if lo is not None and hi is not None:
        return f" in {'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
    if lo is not None:
        return f" {'>' if lo_open else '>='} {lo:g}"
    if hi is not None:
        return f" {'<' if hi_open else '<='} {hi:g}"
    return ""
