"""A run folder (``massviz log DATASET --rrd-dir OUT``: ``index.csv``, ``patches.csv``, one .rrd per recording) read
as untrusted input, for making its traces again: where each recording's ``source`` is now (``locate_source``) and the
settings its ``index.csv`` records per recording (``row_settings``: detector, precision, threshold, K, stride), every
value checked (numbers by ``massviz.io.untrusted.number``, threshold, K and stride by ``Selection.check``), each
refusal one line naming the ``index.csv`` and the recording (the folder may come from someone else). The tables
themselves are read by ``massviz.evaluation.browser.read_dataset``.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from massviz.core.selection import Selection
from massviz.detect import DETECTORS
from massviz.errors import MassvizError
from massviz.io.untrusted import number

INDEX_NAME = "index.csv"
PATCHES_NAME = "patches.csv"
#: the detectors a run folder's ``detector`` column may name: ``massviz log``'s, ``auto`` resolved to one of them
#: (every detector but ``auto``), then its precision when it records one (``maskrcnn bf16``)
FOLDER_DETECTORS = tuple(d for d in DETECTORS if d != "auto")


def row_error(index_path: Path, rid: str, message: str) -> MassvizError:
    """The one line that refuses recording ``rid`` of a run folder: ``<index.csv>: recording 'rid': message``."""
    return MassvizError(f"recording {rid!r}: {message}", index_path)


def locate_source(source: str, folder: str | Path) -> list[Path]:
    """Where a run folder's ``source`` (a recording's path as ``massviz log`` was given it) is now: an absolute
    path that exists; a relative one that exists from the current directory; else relative to ``folder`` or a folder
    above it, every distinct place it exists (one: found; none: not found; several: ambiguous)."""
    path = Path(source).expanduser()
    if path.is_absolute() or path.exists():
        return [path.resolve()] if path.exists() else []
    found = []
    for base in (Path(folder).resolve(), *Path(folder).resolve().parents):
        if (base / path).exists() and (base / path).resolve() not in found:
            found.append((base / path).resolve())
    return found


def row_settings(row, index_path: Path, rid: str) -> dict:
    """The pipeline settings a run folder's row records (detector, threshold, k, stride; ``precision`` when the
    detector column names one), checked."""
    words = str(row.get("detector", "")).split() if isinstance(row.get("detector"), str) else []
    if not 1 <= len(words) <= 2 or words[0] not in FOLDER_DETECTORS:
        raise row_error(index_path, rid, f"column 'detector': {row.get('detector')!r} is not one of "
                        f"{', '.join(FOLDER_DETECTORS)} (with a precision)")
    out = {"detector": words[0]}
    if len(words) == 2:
        out["precision"] = words[1]
    for name in ("threshold", "k", "stride"):
        what = f"recording {rid!r}: column {name!r}"
        number(row.get(name), what, index_path, error=MassvizError)  # a finite number
        try:
            out[name] = Selection.check(name, row.get(name), what)
        except ValueError as err:
            raise MassvizError(str(err), index_path) from None
    return out


@dataclass
class FolderRow:
    """One recording of a run folder, checked: its ``recording`` (opened from its source) and the ``settings``
    (``PipelineOptions`` fields: detector, threshold, k, stride) its row records."""

    recording: object
    settings: dict


def read_rows(recordings, folder: str | Path, ids, *, precision: str, allow_partial: bool = False) -> dict:
    """{id: ``FolderRow``} of the recordings ``ids`` of a run folder's ``recordings`` table (its ``index.csv``,
    indexed by id), in that order: each ``source`` found (``locate_source``) and opened as the recording of that id,
    each row's settings read (``row_settings``) and its precision the command's ``precision``. ``MassvizError``
    naming the folder's ``index.csv`` and the recording when not, for the first recording that fails."""
    from massviz.io.recording import open_recording

    folder = Path(folder)
    index_path = folder / INDEX_NAME
    out = {}
    for rid in ids:
        row = recordings.loc[rid]
        source = row.get("source")
        found = locate_source(source, folder) if isinstance(source, str) and source.strip() else []
        if len(found) != 1:
            where = (f"found at {' and at '.join(str(f) for f in found)} (ambiguous)" if found else
                     "not found (absolute, from the current directory, nor from the folder or a folder above it)")
            raise row_error(index_path, rid, f"its source {source!r} is {where}")
        try:
            rec = open_recording(found[0], allow_partial=allow_partial)
        except MassvizError as err:
            raise row_error(index_path, rid, f"its source {source!r} does not open ({err})") from None
        if rec.id != rid:
            raise row_error(index_path, rid, f"its source {source!r} ({found[0]}) is the recording {rec.id!r}")
        settings = row_settings(row, index_path, rid)
        if settings.pop("precision", precision) != precision:
            raise row_error(index_path, rid, f"made with --precision {row['detector'].split()[1]}, the command "
                            f"gives {precision}")
        out[rid] = FolderRow(rec, settings)
    return out


__all__ = ["INDEX_NAME", "PATCHES_NAME", "FOLDER_DETECTORS", "FolderRow", "locate_source", "row_settings",
           "read_rows", "row_error"]
