"""CSV cells a spreadsheet will not run as formulas: the one rule for every CSV massviz writes."""
from __future__ import annotations


#: first characters that make a spreadsheet read a CSV cell as a formula (OWASP "CSV injection").
_FORMULA_START = ("=", "+", "-", "@", "\t", "\r")


def csv_cell(value):
    """``value`` as a CSV cell a spreadsheet will not run: text starting with ``= + - @`` (or tab/CR), that is not a
    number, gets a leading ``'``. Numbers and other text are returned unchanged (matching uses the raw id; only
    what is written is neutralised)."""
    if not isinstance(value, str) or not value.startswith(_FORMULA_START):
        return value
    try:
        float(value)
        return value  # "-1", "+2.5": a number, not a formula
    except ValueError:
        return "'" + value


def csv_safe(frame):
    """A copy of the pandas ``frame`` with :func:`csv_cell` applied to every text cell (and header): the one
    guard every CSV massviz writes goes through (``frame.to_csv``) or, for ``csv.writer`` rows, ``csv_cell``."""
    out = frame.copy()
    for col in out.columns:
        if out[col].dtype == object or str(out[col].dtype).startswith("string"):
            out[col] = out[col].map(csv_cell)
    out.columns = [csv_cell(c) for c in out.columns]
    return out
