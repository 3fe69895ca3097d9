"""The patch set: what ``massviz extract`` writes and ``massviz train`` reads (this module owns the format).

``PATCHES/images/<recording>_<rank>.png`` (the RGB crops of a recording's K selected patches, nearest first) and
``PATCHES/index.csv`` (one row per patch, :data:`INDEX_COLUMNS`), every patch labelled with its recording's
annotation (:func:`annotation_for`: a CCM annotation CSV row, else the recording's ``meta.json``). Written atomically
(:func:`write_patch_set`), read back checked as untrusted data (:func:`read_index`). No torch here: the format
needs none (``massviz.training.train`` re-exports these names beside the training code, which does).
"""
from __future__ import annotations

import io
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import pandas as pd
from PIL import Image

from massviz.core.types import GroundTruth
from massviz.errors import DataError, MassvizError
from massviz.io.atomic import atomic_dir, check_replaceable
from massviz.io.ccm_annotations import SIZE_FIELDS, annotation_of
from massviz.io.untrusted import check_image_size, confined, safe_filename, text_id, write_csv

#: file name of a patch set's index, inside the PATCHES folder.
INDEX_NAME = "index.csv"
#: sub-folder of a patch set holding the PNG crops.
IMAGES_DIR = "images"
#: what a patch set folder holds (relative paths): all ``--force`` may replace.
PATCH_SET_FILES = (INDEX_NAME, IMAGES_DIR, f"{IMAGES_DIR}/*.png")
#: columns of ``index.csv``: the image (relative to the patch set), where it came from, its features and its label.
#: ``container_id`` is -1 and a dimension NaN when the annotation does not give it.
INDEX_COLUMNS = ("file", "recording", "config_id", "rank", "frame", "a", "b", "d", "mass_g", "container_id",
                 "width_top_mm", "width_bottom_mm", "height_mm", "depth_mm", "capacity_ml", "class", "score",
                 "x1", "y1", "x2", "y2", "source", "flagged", "cues")
#: container dimensions: the index columns, named as ``CcmAnnotation``'s fields and meta.json's ``container`` keys.
DIMENSIONS = tuple(SIZE_FIELDS)


@dataclass(frozen=True)
class Annotation:
    """What a recording's patches are labelled with: empty mass (g), container id (-1 unknown), dimensions."""

    mass_g: float
    container_id: int = -1
    dims: tuple[tuple[str, float], ...] = ()


def annotation_for(recording, table: pd.DataFrame | None, path: str | Path | None = None) -> Annotation:
    """The annotation of ``recording``: its row in a CCM annotation ``table`` (read from ``path`` with
    :func:`massviz.io.ccm_annotations.read_annotations`, matched on ``id`` = the recording's integer configuration id), or,
    with no table, its ``meta.json`` ``container`` (``mass_g``, optional ``id`` and dimensions).
    Raises :class:`DataError` naming the file when the recording is not annotated."""
    if table is None:
        gt = GroundTruth.from_meta(recording.meta)
        if gt is None or gt.mass_g is None:
            where = Path(recording.path)
            if where.is_dir():  # a massviz recording folder: its meta.json
                raise DataError("no container.mass_g in meta.json (pass --annotations ANN.csv for CCM recordings)",
                                where / "meta.json")
            # a CCM video (or another single file): there is no meta.json to name, the mass comes from --annotations
            raise DataError("no container mass for this recording: pass --annotations ANN.csv (the CCM annotation "
                            "file)", where)
        dims = tuple((col, math.nan if getattr(gt, col) is None else float(getattr(gt, col))) for col in DIMENSIONS)
        return Annotation(gt.mass_g, gt.container_id, dims)
    try:
        rec_id = int(recording.config_id)
    except ValueError:
        raise DataError(f"recording {recording.id} has no integer id to look up in the annotations",
                        path) from None
    row = annotation_of(table, rec_id)
    if row is None:
        raise DataError(f"no annotation for recording {recording.id} (id {rec_id}; {recording.path})", path)
    return Annotation(row.mass_g, row.container_id, tuple((col, getattr(row, col)) for col in DIMENSIONS))


def flag_columns(trace, detection: int) -> dict:
    """``flagged`` (the trace's flags say the chosen patch is probably not the container) and ``cues`` (the kinds of
    its cues, ``ground truth`` when ground-truth masks decided; comma-separated) of one chosen detection."""
    flag = trace.flags.of(detection)
    if flag is None or not flag.flagged:
        return {"flagged": False, "cues": ""}
    return {"flagged": True, "cues": ",".join([*flag.cue_kinds, *(["ground truth"] if flag.by_ground_truth else [])])}


def patch_rows(trace, annotation: Annotation) -> list[tuple[str, np.ndarray, dict]]:
    """(image file name, RGB patch, index row) for each of a trace's selected patches, nearest first."""
    info = trace.recording
    selected = trace.selected
    out = []
    for rank in range(len(selected)):
        patch = selected.patches[rank]
        if patch is None:
            raise MassvizError(f"recording {info.id}: the trace kept no patch for its rank-{rank} detection "
                               "(K larger than the patches a cached trace keeps); rerun with --no-cache")
        name = f"{IMAGES_DIR}/{safe_filename(info.id)}_{rank}.png"  # an id from meta.json is text, not a path
        x1, y1, x2, y2 = (int(v) for v in selected.xyxy[rank])
        row = {"file": name, "recording": info.id, "config_id": info.config_id, "rank": rank,
               "frame": int(selected.frame[rank]), "a": float(selected.a[rank]), "b": float(selected.b[rank]),
               "d": float(selected.d[rank]), "mass_g": annotation.mass_g, "container_id": annotation.container_id,
               **dict(annotation.dims), "class": selected.class_names()[rank],
               "score": round(float(selected.score[rank]), 4), "x1": x1, "y1": y1, "x2": x2, "y2": y2,
               "source": info.path, **flag_columns(trace, int(trace.selection[rank]))}
        out.append((name, patch, row))
    return out


@dataclass(frozen=True)
class ExtractResult:
    """What :func:`write_patch_set` wrote (for ``massviz extract`` and ``massviz.training.train.extract_patches``):
    the patch set folder, its number of patches and the recordings that gave none (no detection with depth)."""

    out: Path
    n_patches: int
    n_recordings: int
    empty: tuple[str, ...]


def check_extract(recordings: Sequence, out: str | Path, annotations: pd.DataFrame | None = None,
                  annotations_path: str | Path | None = None, force: bool = False) -> list[Annotation]:
    """The cheap checks to make before anything runs: ``out`` is free (or, with ``force``, holds only a patch set:
:func:`massviz.io.atomic.check_replaceable`), recording ids are unique and every recording is annotated
    (:func:`annotation_for`). Returns the recordings' annotations, in order."""
    if os.path.lexists(out) and not force:
        raise MassvizError("already exists (pass --force to replace it)", out)
    if force:
        check_replaceable(out, PATCH_SET_FILES, "patch set")
    ids = [r.id for r in recordings]
    if dup := sorted({i for i in ids if ids.count(i) > 1}):
        raise MassvizError(f"recording id {dup[0]} appears more than once; extract each dataset on its own")
    names = {}
    for r in recordings:
        other = names.setdefault(safe_filename(r.id), r.id)
        if other != r.id:
            raise MassvizError(f"recording ids {other!r} and {r.id!r} give the same image file names "
                               f"({safe_filename(r.id)}_*.png); extract them separately", r.path)
    return [annotation_for(r, annotations, annotations_path) for r in recordings]


def patch_files(trace, annotation: Annotation) -> list[tuple[str, bytes, dict]]:
    """:func:`patch_rows` with each patch encoded as the PNG file the patch set stores (small, picklable: what a
    dataset worker sends back)."""
    out = []
    for name, patch, row in patch_rows(trace, annotation):
        buf = io.BytesIO()
        Image.fromarray(patch).save(buf, format="PNG")
        out.append((name, buf.getvalue(), row))
    return out


def write_patch_set(out: str | Path, found: Sequence[tuple[str, Sequence[tuple[str, bytes, dict]]]],
                    n_recordings: int | None = None) -> ExtractResult:
    """Write a patch set from ``(recording id, patch_files(...))`` pairs, in order, atomically (``atomic_dir``).
    ``n_recordings``: recordings of the run (default ``len(found)``; more when some failed)."""
    out = Path(out)
    with atomic_dir(out) as tmp:
        (tmp / IMAGES_DIR).mkdir()
        rows, empty = [], []
        for rec_id, files in found:
            if not files:
                empty.append(rec_id)
            for name, png, row in files:
                (tmp / name).write_bytes(png)
                rows.append(row)
        write_csv(pd.DataFrame(rows, columns=list(INDEX_COLUMNS)), tmp / INDEX_NAME)
    return ExtractResult(out, len(rows), len(found) if n_recordings is None else n_recordings, tuple(empty))


def read_index(patches: str | Path) -> pd.DataFrame:
    """The ``index.csv`` of a patch set, checked: columns, at least one row, finite a/b/d/mass and every image
    present. Problems raise :class:`DataError` naming the file."""
    patches = Path(patches)
    if not patches.is_dir():
        raise DataError("not a patch set folder (make one with massviz extract)", patches)
    path = patches / INDEX_NAME
    if not path.is_file():
        raise DataError(f"missing {INDEX_NAME} (make the patch set with massviz extract)", path)
    try:
        table = pd.read_csv(path, dtype={"file": str, "recording": str, "config_id": str})
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as e:
        raise DataError(f"not a readable CSV ({str(e).splitlines()[0] if str(e) else type(e).__name__})",
                        path) from None
    required = ("file", "recording", "a", "b", "d", "mass_g", "container_id")
    if missing := [c for c in required if c not in table.columns]:
        raise DataError(f"missing column(s) {', '.join(missing)} (expected the columns massviz extract writes)", path)
    if table.empty:
        raise DataError("no patches (only a header): no recording gave a patch", path)
    for col in ("a", "b", "d", "mass_g"):
        values = pd.to_numeric(table[col], errors="coerce")
        if not np.isfinite(values).all():
            bad = int(np.flatnonzero(~np.isfinite(values))[0])
            raise DataError(f"row {bad + 1}, column '{col}': not a finite number ({table[col].iloc[bad]!r})", path)
        table[col] = values.astype(np.float64)
    ids = pd.to_numeric(table["container_id"], errors="coerce")
    bad = ~(ids.isna() | (np.isfinite(ids) & (ids == ids.round()) & (ids >= -1) & (ids <= 2**31 - 1)))
    if bad.any():
        i = int(np.flatnonzero(bad.to_numpy())[0])
        raise DataError(f"row {i + 1}, column 'container_id': {table['container_id'].iloc[i]!r} is not an integer "
                        "id >= -1", path)
    table["container_id"] = ids.fillna(-1).astype(np.int64)
    if "flagged" in table.columns:  # patch sets made before massviz flagged patches have no such column
        given = table["flagged"].astype(object)  # an all-empty column is float64 NaN: no False filled into it
        # empty: not flagged; 1 and 0 (and 1.0, 0.0) are the keys True and False
        flagged = given.where(given.notna(), False).map({True: True, False: False, "True": True, "False": False})
        if flagged.isna().any():
            i = int(np.flatnonzero(flagged.isna().to_numpy())[0])
            raise DataError(f"row {i + 1}, column 'flagged': {table['flagged'].iloc[i]!r} is not True or False", path)
        table["flagged"] = flagged.astype(bool)
    else:
        table["flagged"] = False
    for i, recording_id in enumerate(table["recording"]):
        text_id(recording_id if isinstance(recording_id, str) else "", f"row {i + 1}, column 'recording'", path)
    for i, name in enumerate(table["file"]):  # a path from a data file: it must stay inside the patch set
        image = confined(patches, name if isinstance(name, str) else None, path, f"row {i + 1}, column 'file'")
        if not image.is_file():
            raise DataError(f"row {i + 1}: image {name} is missing", image)
        check_image_size(image, DataError, "patch image")
    return table


__all__ = ["INDEX_NAME", "IMAGES_DIR", "INDEX_COLUMNS", "DIMENSIONS", "Annotation", "annotation_for", "flag_columns",
           "patch_rows", "ExtractResult", "check_extract", "patch_files", "write_patch_set", "read_index"]
