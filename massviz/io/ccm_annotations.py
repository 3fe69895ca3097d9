"""The CCM annotation CSV (``id``, ``container id``, ``container mass``, the container's sizes, ...): its one reader,
``read_annotations``, and ``annotation_of``, one recording's row as a typed ``CcmAnnotation``. The checked CSV table
reader under it (``read_table``, ``column_values``, ...) also reads the challenge's prediction files
(``massviz.evaluation.metrics.read_predictions``). Every problem is a ``DataError`` naming the file, row and column.
"""
from __future__ import annotations

import math
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import pandas as pd

from massviz.errors import DataError

#: Recording id, container id and empty container mass (g) columns of the CCM annotation CSV.
ANN_ID, ANN_CONTAINER, ANN_MASS = "id", "container id", "container mass"
#: Size columns of the CCM annotation CSV read as numbers (mm, mL; -1: not given).
ANN_WIDTH_TOP, ANN_WIDTH_BOTTOM, ANN_HEIGHT, ANN_DEPTH, ANN_CAPACITY = (
    "width at the top", "width at the bottom", "height", "depth", "container capacity")
ANN_SIZES = (ANN_WIDTH_TOP, ANN_WIDTH_BOTTOM, ANN_HEIGHT, ANN_DEPTH, ANN_CAPACITY)


class _Row(NamedTuple):
    number: int  # 1-based data row (the header is not counted)
    line: int  # line in the file
    fields: list[str]


_RAGGED = re.compile(r"Expected (\d+) fields in line (\d+), saw (\d+)")


def read_table(path: Path, required: Sequence[str]) -> tuple[list[str], list[_Row]]:
    """Header and data rows of a CSV file (``pandas.read_csv``, every field as text), checking it is UTF-8 text,
    has the ``required`` columns and a rectangular shape. Blank lines are skipped; rows keep their line numbers."""
    try:
        # header=None: the header is read as row 0, so its length is what every row must have (pandas then names
        # the line of a longer row); shorter rows come back padded with NaN
        frame = pd.read_csv(path, dtype=str, keep_default_na=False, skip_blank_lines=False, encoding="utf-8-sig",
                            header=None, engine="python", on_bad_lines="error")
    except UnicodeDecodeError:
        raise DataError("not a CSV file (not UTF-8 text)", path) from None
    except pd.errors.EmptyDataError:
        raise DataError("empty file: no header row", path) from None
    except pd.errors.ParserError as err:
        m = _RAGGED.search(str(err))
        if m is None:
            raise DataError(f"not a valid CSV file ({str(err).splitlines()[0]})", path) from None
        n_header, line, n_fields = (int(g) for g in m.groups())
        number = _data_row_number(path, line)
        raise DataError(f"row {number} (line {line}): {n_fields} fields, but the header has only {n_header}",
                        path) from None
    except OSError as err:
        raise DataError(f"cannot read the file ({err.strerror})", path) from None
    header = [str(name).strip() for name in frame.iloc[0].fillna("")]
    frame = frame.iloc[1:]
    if not any(header):
        raise DataError("empty file: no header row", path)
    seen = set()
    for name in header:
        if name in seen and name:
            raise DataError(f"header: column '{name[:60]}' appears twice (which one holds the values?)", path)
        seen.add(name)
    for name in required:
        if name not in header:
            raise DataError(f"header: missing column '{name}' (expected a CSV with columns "
                            f"{', '.join(repr(n) for n in required)})", path)
    rows: list[_Row] = []
    missing = frame.isna().to_numpy()
    values = frame.to_numpy()
    for i in range(len(frame)):
        if missing[i].all():
            continue  # a blank line
        row = _Row(len(rows) + 1, i + 2, [str(v) for v, m in zip(values[i], missing[i]) if not m])
        if missing[i].any():
            first = int(missing[i].argmax())
            raise DataError(f"row {row.number} (line {row.line}), column '{header[first]}': missing "
                            f"(the row has {len(row.fields)} fields, the header {len(header)})", path)
        rows.append(row)
    return header, rows


def _data_row_number(path: Path, line: int) -> int:
    """The data-row number (blank lines not counted) of file line ``line``."""
    with open(path, encoding="utf-8-sig", errors="replace") as f:
        lines = f.read().splitlines()[1:line]
    return sum(1 for text in lines if text.strip())


#: largest recording / container id read from a CSV (ids are indices, never near this).
MAX_ID = 2**31 - 1


def parse_id(text: str) -> int:
    """A recording or container id: an integer in [0, MAX_ID] (``1e30`` would overflow the int64 columns)."""
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"{text!r} is not an integer" if text else "empty value") from None
    if not value.is_integer():
        raise ValueError(f"{text!r} is not an integer")
    if not 0 <= value <= MAX_ID:
        raise ValueError(f"{text!r} must be >= 0 and <= {MAX_ID}")
    return int(value)


#: largest magnitude of a mass (g) or size (mm, mL) read from a CSV (a container is far below: 1e9 g is 1000 t).
MAX_QUANTITY = 1e9
#: smallest true mass (g): ε divides by it (a 1e-300 g container would make ε overflow).
MIN_TRUE_MASS_G = 1e-3


def parse_number(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"{text!r} is not a number" if text else "empty value") from None
    if not math.isfinite(value):
        raise ValueError(f"{text!r} is not a finite number")
    if abs(value) > MAX_QUANTITY:
        raise ValueError(f"{text[:40]!r} is beyond +-{MAX_QUANTITY:g}")
    return value


def positive_mass(text: str) -> float:
    value = parse_number(text)
    if value <= 0:
        raise ValueError(f"the true mass must be > 0 g (ε divides by it), got {text[:40]}")
    if value < MIN_TRUE_MASS_G:
        raise ValueError(f"the true mass must be >= {MIN_TRUE_MASS_G:g} g (ε divides by it), got {text[:40]}")
    return value


def column_values(path: Path, header: list[str], rows: list[_Row], name: str, parse: Callable[[str], Any]) -> list:
    """The values of column ``name`` parsed with ``parse``; a failure names the file, row and column."""
    index = header.index(name)
    values = []
    for row in rows:
        try:
            values.append(parse(row.fields[index].strip()))
        except ValueError as err:
            raise DataError(f"row {row.number} (line {row.line}), column '{name}': {err}", path) from None
    return values


def check_unique(path: Path, rows: list[_Row], name: str, ids: list[int]) -> None:
    first: dict[int, int] = {}
    for row, value in zip(rows, ids):
        if value in first:
            raise DataError(f"row {row.number} (line {row.line}), column '{name}': recording {value} already "
                            f"appears in row {first[value]} (one row per recording)", path)
        first[value] = row.number


def read_annotations(path: str | Path) -> pd.DataFrame:
    """Read a CCM annotation CSV (``id``, ``container id``, ..., ``container mass``, ...) into a frame.

    ``id`` and ``container id`` are ints in [0, 2^31), ``container mass`` (g) a finite float > 0, the size columns
    (:data:`ANN_SIZES`, mm / mL; -1 = not given) finite floats; every other column is kept, numeric where all its
    values parse as numbers. Raises ``DataError`` (naming file, row and column) for an unreadable or
    non-CSV file, a missing column, a ragged row, a non-numeric value, a mass ≤ 0, a repeated id or no data rows.
    """
    path = Path(path)
    header, rows = read_table(path, (ANN_ID, ANN_CONTAINER, ANN_MASS))
    if not rows:
        raise DataError("no annotated recordings (only a header)", path)
    parsers = {ANN_ID: parse_id, ANN_CONTAINER: parse_id, ANN_MASS: positive_mass,
               **{name: parse_number for name in ANN_SIZES}}
    data = {}
    for name in header:
        if name in parsers:
            data[name] = column_values(path, header, rows, name, parsers[name])
        else:
            text = pd.Series([row.fields[header.index(name)] for row in rows])
            try:
                data[name] = pd.to_numeric(text)
            except ValueError:
                data[name] = text
    check_unique(path, rows, ANN_ID, data[ANN_ID])
    return pd.DataFrame(data)


@dataclass(frozen=True)
class CcmAnnotation:
    """One recording's row of a CCM annotation table: its id, container id, empty mass (g) and sizes as the file
    gives them (mm, mL; -1 where the file says "not given", NaN where the file has no such column)."""

    config_id: int
    container_id: int
    mass_g: float
    width_top_mm: float = math.nan
    width_bottom_mm: float = math.nan
    height_mm: float = math.nan
    depth_mm: float = math.nan
    capacity_ml: float = math.nan


#: ``CcmAnnotation`` size field -> annotation column.
SIZE_FIELDS = {"width_top_mm": ANN_WIDTH_TOP, "width_bottom_mm": ANN_WIDTH_BOTTOM, "height_mm": ANN_HEIGHT,
               "depth_mm": ANN_DEPTH, "capacity_ml": ANN_CAPACITY}


def annotation_of(table: pd.DataFrame, config_id) -> CcmAnnotation | None:
    """The row of recording ``config_id`` (its integer configuration id) in a ``read_annotations`` table, or None
    when the table has none."""
    rows = table[table[ANN_ID] == int(config_id)]
    if rows.empty:
        return None
    row = rows.iloc[0]
    sizes = {name: float(row[column]) if column in row.index else math.nan for name, column in SIZE_FIELDS.items()}
    return CcmAnnotation(config_id=int(row[ANN_ID]), container_id=int(row[ANN_CONTAINER]),
                         mass_g=float(row[ANN_MASS]), **sizes)


__all__ = ["ANN_ID", "ANN_CONTAINER", "ANN_MASS", "ANN_WIDTH_TOP", "ANN_WIDTH_BOTTOM", "ANN_HEIGHT", "ANN_DEPTH",
           "ANN_CAPACITY", "ANN_SIZES", "MAX_ID", "MAX_QUANTITY", "MIN_TRUE_MASS_G", "read_table", "column_values",
           "check_unique", "parse_id", "parse_number", "positive_mass", "read_annotations", "CcmAnnotation",
           "SIZE_FIELDS", "annotation_of"]
