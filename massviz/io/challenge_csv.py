"""Writer for the CORSMAL challenge prediction CSV (the format of the paper's result files).

One row per recording, the 20 columns of :data:`COLUMNS` in that order; this project estimates only the container
mass, so every other task's column is ``-1`` (not estimated), except ``Execution time`` (seconds).
"""
from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from massviz.io.atomic import atomic_path
from massviz.io.untrusted import csv_writer

#: The challenge CSV header, in order (the CORSMAL challenge format; shared/ccm/README.md in the reference data).
COLUMNS = (
    "Configuration ID", "Container capacity", "Container mass", "Filling mass", "None", "Pasta", "Rice", "Water",
    "Filling type", "Empty", "Half-full", "Full", "Filling level", "Width at the top", "Width at the bottom",
    "Height", "Object safety", "Distance", "Angle difference", "Execution time",
)
#: The value the challenge reads as "not estimated".
NOT_ESTIMATED = -1


def _field(row: Any, name: str) -> Any:
    return row[name] if isinstance(row, Mapping) else getattr(row, name)


def _mass_text(mass_g: float | None, exact: bool) -> str:
    if mass_g is None or mass_g < 0:
        return str(NOT_ESTIMATED)
    if not math.isfinite(mass_g):
        raise ValueError(f"mass {mass_g!r} is not a finite number (use -1 for 'not estimated')")
    return f"{mass_g:.2f}" if exact else str(int(mass_g))


def write_challenge_csv(path: str | Path, rows: Iterable[Any], *, exact: bool = False) -> Path:
    """Write ``rows`` as a CORSMAL challenge prediction CSV at ``path`` (atomically: temp file, then rename).

    Each row is a mapping or an object with ``config_id`` (the recording id: an int for CCM recordings; a massviz
    folder without a numeric ``config_id`` in its meta.json is written by name, which ``massviz score`` cannot
    match against CCM annotations), ``mass_g`` (grams; ``-1``, any
    negative value or ``None`` means not estimated) and ``exec_time_s`` (seconds, written with 2 decimals;
    negative or None: not measured, written ``-1``).

    Faithful to the paper's code, which writes ``int(pred)``: an estimated mass is written *truncated* to an integer
    (``12.9`` → ``12``), a not-estimated one as ``-1``. ``exact=True`` writes the mass with 2 decimals instead.
    Rows are written in the order given; a repeated ``config_id`` or a non-finite mass raises ``ValueError``.
    Returns ``path``.
    """
    lines = []
    seen: set[str] = set()
    for row in rows:
        config_id = str(_field(row, "config_id")).strip()
        if config_id.lstrip("-").isdigit():
            config_id = str(int(config_id))
        elif not config_id or any(c in config_id for c in "\n\r\x00"):  # commas and quotes are quoted
            raise ValueError(f"recording id {config_id!r} cannot be written in a CSV field")
        if config_id in seen:
            raise ValueError(f"recording {config_id} appears twice")
        seen.add(config_id)
        values = {name: str(NOT_ESTIMATED) for name in COLUMNS}
        values["Configuration ID"] = str(config_id)  # written "=cmd" -> "'=cmd" (csv_writer); matching uses the raw id
        values["Container mass"] = _mass_text(_field(row, "mass_g"), exact)
        seconds = _field(row, "exec_time_s")
        values["Execution time"] = (str(NOT_ESTIMATED) if seconds is None or float(seconds) < 0
                                    else f"{float(seconds):.2f}")
        lines.append([values[name] for name in COLUMNS])
    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        writer = csv_writer(f, lineterminator="\n")
        writer.writerow(COLUMNS)
        writer.writerows(lines)
    return path
