"""CSV cells a spreadsheet will not run as formulas: the one rule for every CSV massviz writes.

Every CSV goes through :func:`write_csv` (a pandas table) or :func:`csv_writer` (rows written one at a time): a text
cell starting with ``= + - @`` (or tab/CR) that is not a number gets a leading ``'`` (OWASP "CSV injection").
"""
from __future__ import annotations

import csv
from pathlib import Path

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
    """A copy of the pandas ``frame`` with :func:`csv_cell` applied to every text cell (object and string columns,
    pandas' ``str`` dtype included) and to the header."""
    from pandas.api.types import is_object_dtype, is_string_dtype

    out = frame.copy()
    for col in out.columns:
        if is_object_dtype(out[col].dtype) or is_string_dtype(out[col].dtype):
            out[col] = out[col].map(csv_cell).astype(object)
    out.columns = [csv_cell(c) for c in out.columns]
    return out


def write_csv(frame, path: str | Path, **options) -> None:
    """Write the pandas ``frame`` to ``path`` as CSV (no index column unless ``index=True``), every text cell through
    :func:`csv_cell`: the one way massviz writes a table. ``options``: ``DataFrame.to_csv``'s (``float_format`` ...)."""
    options.setdefault("index", False)
    csv_safe(frame).to_csv(path, **options)


class _SafeWriter:
    def __init__(self, writer):
        self._writer = writer

    def writerow(self, row):
        return self._writer.writerow([csv_cell(v) for v in row])

    def writerows(self, rows):
        for row in rows:
            self.writerow(row)


def csv_writer(fh, **options) -> _SafeWriter:
    """``csv.writer(fh, **options)`` whose rows go through :func:`csv_cell` (``writerow``/``writerows``)."""
    return _SafeWriter(csv.writer(fh, **options))
