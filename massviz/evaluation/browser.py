"""The failure browser's tables (notebook 04): every recording and every chosen patch of a dataset, from a dataset
folder (``massviz log DATASET --rrd-dir OUT``: ``index.csv``, ``patches.csv``) or from traces (the trace cache), the
same columns either way; ranking, filters and exclusions over them. pandas only; the widgets are
``massviz.views.failure_browser``.

* ``recording_properties(trace)`` — one recording's row (the .rrd's recording properties, see
  ``massviz.views.rerun_dataset``): id, container_class, gt_mass_g, estimate_g, rel_error, score, n_flagged, cues, …
* ``patch_rows(trace)`` — one row per chosen patch: recording, rank, detection, frame, track, class, score, d_mm, a, b,
  pred_g, flagged, severity, cues, box.
* ``tables_from_traces`` / ``read_dataset`` — (recordings, patches) tables.
* ``ranked`` — recordings ranked by relative error within each class (worst first), with the per-recording score;
  ``per_class`` — count, mean score and error per class.
* ``filter_patches`` — by flag, cue, class, track and the recording's error.
* ``patch_exclusions`` — ``massviz.exclusions/1`` entries (with tags as notes) for ``save_exclusions``, the file
  ``massviz estimate --exclude`` and ``massviz extract --exclude`` read.
* ``catalog_summary`` / ``pandas_summary`` — the same figures (flagged patches per recording, error, score) from a
  catalog server's segment table (DataFusion) and from the tables; ``compare_summaries`` puts them side by side.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np
import pandas as pd

from massviz.core.trace import Trace
from massviz.errors import DataError
from massviz.evaluation.failures import Exclusion
from massviz.io.run_folder import INDEX_NAME, PATCHES_NAME
from massviz.io.untrusted import confined, text_id

PATCH_COLUMNS = ("recording", "rank", "detection", "frame", "track", "class", "score", "d_mm", "a", "b", "pred_g",
                 "flagged", "severity", "cues", "x1", "y1", "x2", "y2")
#: the figures ``catalog_summary`` and ``pandas_summary`` both give, per recording.
SUMMARY_COLUMNS = ("n_flagged", "rel_error", "score", "estimate_g")


def best_frame(trace: Trace) -> int:
    """The frame a recording is opened at: that of the nearest chosen patch, else the first processed frame."""
    if len(trace.selection):
        return int(trace.detections.frame[int(trace.selection[0])])
    return int(trace.frames[0]) if len(trace.frames) else 0


def flag_cues(flag) -> list[str]:
    """The cue kinds of a flagged patch, ``ground truth`` when ground-truth masks decided; [] when not flagged."""
    if flag is None or not flag.flagged:
        return []
    return [*flag.cue_kinds, *(["ground truth"] if flag.by_ground_truth else [])]


def recording_properties(trace: Trace, *, source: str = "", view: int = 0, n_input_bytes: int = 0,
                         kind: str = "light") -> dict:
    """One recording's properties (``massviz.views.rerun_dataset`` lists them); unknown values are left out."""
    gt = trace.ground_truth
    true = trace.ground_truth_mass
    est = float(trace.estimate)
    flagged = trace.flags.flagged
    props = {"id": trace.recording.id, "container_class": (gt.cls if gt is not None else None) or "",
             "n_flagged": len(flagged), "cues": sorted({c for p in flagged for c in flag_cues(p)}),
             "flagged_ranks": [int(p.rank) for p in flagged],
             "detector": trace.detector.get("name", "?") + (f" {trace.detector['precision']}"
                                                            if "precision" in trace.detector else ""),
             "k": int(trace.k), "threshold": float(trace.threshold), "stride": int(trace.stride),
             "weights_id": trace.weights_id or "", "view": int(view), "source": source or trace.recording.path,
             "frames": len(trace.frames), "detections": len(trace.detections), "best_frame": best_frame(trace),
             "estimated": est >= 0, "input_bytes": int(n_input_bytes), "kind": kind}
    if est >= 0:
        props["estimate_g"] = est
    if true is not None and true > 0:
        props["gt_mass_g"] = float(true)
        props["score"] = math.exp(-abs(est - true) / true) if est >= 0 else 0.0
        if est >= 0:
            props["rel_error"] = abs(est - true) / true
    return props


#: the decimals a property keeps in the catalog (``rounded_properties``): grams to 0.01 g, ratios to 4 decimals
SHOWN_DIGITS = {"estimate_g": 2, "gt_mass_g": 2, "score": 4, "rel_error": 4, "threshold": 4}


def rounded_properties(props: dict) -> dict:
    """``props`` rounded as a table shows them (15-digit numbers are unreadable): grams to 0.01 g, ratios and the
    threshold to 4 decimals. For what is displayed (the catalog's properties); the tables keep full precision."""
    out = dict(props)
    for key, digits in SHOWN_DIGITS.items():
        if isinstance(out.get(key), float):
            out[key] = round(out[key], digits)
    return out


def patch_rows(trace: Trace) -> list[dict]:
    """One row per chosen patch of ``trace`` (``PATCH_COLUMNS``), nearest first."""
    dets = trace.detections
    names = dets.class_names()
    rows = []
    for rank, i in enumerate(int(i) for i in trace.selection):
        flag = trace.flags.of(i)
        x1, y1, x2, y2 = (int(v) for v in dets.xyxy[i])
        rows.append({"recording": trace.recording.id, "rank": rank, "detection": i, "frame": int(dets.frame[i]),
                     "track": int(dets.track[i]), "class": names[i], "score": float(dets.score[i]),
                     "d_mm": float(dets.d[i]), "a": float(dets.a[i]), "b": float(dets.b[i]),
                     "pred_g": float(dets.pred[i]), "flagged": bool(flag is not None and flag.flagged),
                     "severity": "none" if flag is None else flag.severity, "cues": ",".join(flag_cues(flag)),
                     "x1": x1, "y1": y1, "x2": x2, "y2": y2})
    return rows


def recordings_table(rows: Sequence[dict]) -> pd.DataFrame:
    """Recording rows (``recording_properties``, list values joined with commas) as a table indexed by id."""
    out = []
    for r in rows:
        r = dict(r)
        r["cues"] = ",".join(r.get("cues", [])) if isinstance(r.get("cues"), list) else (r.get("cues") or "")
        if isinstance(r.get("flagged_ranks"), list):
            r["flagged_ranks"] = ",".join(str(v) for v in r["flagged_ranks"])
        out.append(r)
    table = pd.DataFrame(out)
    for col in ("gt_mass_g", "estimate_g", "rel_error", "score"):
        if col not in table.columns:
            table[col] = np.nan
    table["cues"] = table["cues"].fillna("").astype(str)
    return table.set_index("id", drop=False).rename_axis(None)


def tables_from_traces(traces: Sequence[Trace]) -> tuple[pd.DataFrame, pd.DataFrame]:
    """(recordings, patches) of ``traces`` (the columns ``read_dataset`` gives, without files)."""
    recordings = recordings_table([recording_properties(t) for t in traces])
    patches = pd.DataFrame([r for t in traces for r in patch_rows(t)], columns=list(PATCH_COLUMNS))
    return recordings, patches


def read_dataset(folder: str | Path) -> tuple[pd.DataFrame, pd.DataFrame]:
    """(recordings, patches) of a dataset folder written by ``massviz log DATASET --rrd-dir``; ``DataError`` naming
    the file when one is missing or lacks a column, an id is not text or is there twice, a thumbnail path leads out
    of the folder, a flag is not True/False or a rank, frame or track is not an integer (the folder may come from
    someone else)."""
    folder = Path(folder)
    tables = []
    for name, key, required in ((INDEX_NAME, "id", ("id", "n_flagged", "rrd")),
                                (PATCHES_NAME, "recording", ("recording", "rank", "frame", "flagged", "thumb"))):
        path = folder / name
        if not path.is_file():
            raise DataError(f"missing (make the dataset with: massviz log DATASET --rrd-dir {folder})", path)
        try:
            table = pd.read_csv(path, dtype={key: str, "cues": str, "weights_id": str, "source": str},
                                keep_default_na=True)
        except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as err:
            raise DataError(f"not a readable CSV ({type(err).__name__})", path) from None
        if missing := [c for c in required if c not in table.columns]:
            raise DataError(f"missing column(s) {', '.join(missing)}", path)
        table["cues"] = table["cues"].fillna("") if "cues" in table.columns else ""
        tables.append(table)
    index_path, patches_path = folder / INDEX_NAME, folder / PATCHES_NAME
    for i, rid in enumerate(tables[0]["id"]):  # ids are text from a data file
        text_id(rid if isinstance(rid, str) else "", f"row {i + 1}, column 'id'", index_path)
    if tables[0]["id"].duplicated().any():
        i = int(np.flatnonzero(tables[0]["id"].duplicated().to_numpy())[0])
        raise DataError(f"row {i + 1}, column 'id': {tables[0]['id'].iloc[i]!r} is there twice", index_path)
    for i, (rid, thumb) in enumerate(zip(tables[1]["recording"], tables[1]["thumb"])):
        text_id(rid if isinstance(rid, str) else "", f"row {i + 1}, column 'recording'", patches_path)
        confined(folder, thumb if isinstance(thumb, str) else None, patches_path, f"row {i + 1}, column 'thumb'")
    recordings = tables[0].set_index("id", drop=False).rename_axis(None)
    patches = tables[1]
    flagged = patches["flagged"].map({True: True, False: False, "True": True, "False": False})
    if flagged.isna().any():
        i = int(np.flatnonzero(flagged.isna().to_numpy())[0])
        raise DataError(f"row {i + 1}, column 'flagged': {patches['flagged'].iloc[i]!r} is not True or False",
                        patches_path)
    patches["flagged"] = flagged.astype(bool)
    for col in ("rank", "frame", "track"):
        values = pd.to_numeric(patches[col], errors="coerce")
        if values.isna().any() or (values != values.round()).any():
            i = int(np.flatnonzero((values.isna() | (values != values.round())).to_numpy())[0])
            raise DataError(f"row {i + 1}, column '{col}': {patches[col].iloc[i]!r} is not an integer", patches_path)
        patches[col] = values.astype(np.int64)
    return recordings, patches


def ranked(recordings: pd.DataFrame) -> pd.DataFrame:
    """Recordings ranked by relative error within each class, worst first (not estimated first: error ∞), with the
    per-recording score: class, rank (1 = worst of its class), id, gt_mass_g, estimate_g, rel_error, score,
    n_flagged, cues."""
    t = recordings.copy()
    err = t["rel_error"].where(t["estimate_g"].notna(), np.inf)
    t = t.assign(_err=err).sort_values(["container_class", "_err"], ascending=[True, False], kind="stable")
    t["rank"] = t.groupby("container_class").cumcount() + 1
    cols = ["container_class", "rank", "id", "gt_mass_g", "estimate_g", "rel_error", "score", "n_flagged", "cues"]
    return t[cols].reset_index(drop=True)


def per_class(recordings: pd.DataFrame) -> pd.DataFrame:
    """Per class: recordings, mean score (%) — the CORSMAL score of that class's recordings —, mean ε over the
    estimated ones, recordings with flagged patches."""
    g = recordings.groupby("container_class")
    return pd.DataFrame({"recordings": g.size(), "score %": 100 * g["score"].mean(), "mean ε": g["rel_error"].mean(),
                         "with flagged patches": g["n_flagged"].apply(lambda s: int((s > 0).sum()))})


def filter_patches(patches: pd.DataFrame, recordings: pd.DataFrame, *, flagged: bool | None = None,
                   cue: str | None = None, cls: str | None = None, track: int | None = None,
                   min_error: float | None = None) -> pd.DataFrame:
    """The chosen patches that pass every filter given: ``flagged`` (True / False), ``cue`` (one of a flagged
    patch's cues), ``cls`` (the recording's container class), ``track`` (the patch's object track), ``min_error``
    (the recording's relative error above it; not-estimated recordings pass). Ordered by the recording's error
    (worst first), then rank."""
    by_id = recordings.set_index("id") if "id" in recordings.columns else recordings
    err = by_id["rel_error"].where(by_id["estimate_g"].notna(), np.inf) if "estimate_g" in by_id else by_id["rel_error"]
    p = patches.assign(rec_error=patches["recording"].map(err), rec_class=patches["recording"].map(
        by_id["container_class"]))
    keep = np.ones(len(p), bool)
    if flagged is not None:
        keep &= p["flagged"].to_numpy() == bool(flagged)
    if cue:
        keep &= p["cues"].fillna("").str.split(",").map(lambda cs: cue in cs).to_numpy()
    if cls:
        keep &= (p["rec_class"] == cls).to_numpy()
    if track is not None:
        keep &= (p["track"] == int(track)).to_numpy()
    if min_error is not None:
        keep &= (p["rec_error"].fillna(np.inf) > float(min_error)).to_numpy()
    out = p[keep]
    return out.sort_values(["rec_error", "recording", "rank"], ascending=[False, True, True], kind="stable")


def cues_of(patches: pd.DataFrame) -> list[str]:
    """Every cue kind that occurs in ``patches``, sorted."""
    return sorted({c for cs in patches["cues"].fillna("") for c in cs.split(",") if c})


def patch_exclusions(patches: pd.DataFrame, tags: dict | None = None) -> list[Exclusion]:
    """``Exclusion`` entries (recording, frame, box) for the patch rows given, each with its tag (``tags``:
    (recording, rank) → text) as the note."""
    tags = tags or {}
    return [Exclusion(str(r.recording), int(r.frame), (int(r.x1), int(r.y1), int(r.x2), int(r.y2)),
                      str(tags.get((str(r.recording), int(r.rank)), "")))
            for r in patches.itertuples()]


def pandas_summary(recordings: pd.DataFrame, patches: pd.DataFrame) -> pd.DataFrame:
    """Per recording: flagged chosen patches counted in the patch table, and error, score and estimate — pandas."""
    n = patches.groupby("recording")["flagged"].sum().astype(int)
    by_id = recordings.set_index("id") if "id" in recordings.columns else recordings
    out = pd.DataFrame({"n_flagged": n.reindex(by_id.index).fillna(0).astype(int),
                        "rel_error": by_id["rel_error"], "score": by_id["score"], "estimate_g": by_id["estimate_g"]})
    return out.sort_index().rename_axis("recording")


def catalog_summary(catalog) -> pd.DataFrame:
    """The same figures from a catalog server's segment table (``massviz.views.rerun_serve.Catalog``), computed by
    DataFusion: SQL over the ``property:massviz:*`` columns."""
    cols = ", ".join(f'"property:massviz:{c}"[1] AS {c}' for c in SUMMARY_COLUMNS)
    df = catalog.sql(f"SELECT rerun_segment_id AS recording, {cols} FROM segments ORDER BY recording")
    df["n_flagged"] = df["n_flagged"].astype(int)
    return df.set_index("recording")


def flagged_from_catalog(catalog) -> pd.DataFrame:
    """All recordings with flagged chosen patches (their count and cues), from the catalog (DataFusion)."""
    return catalog.sql('SELECT rerun_segment_id AS recording, "property:massviz:n_flagged"[1] AS n_flagged, '
                       '"property:massviz:cues" AS cues, "property:massviz:flagged_ranks" AS ranks FROM segments '
                       'WHERE "property:massviz:n_flagged"[1] > 0 ORDER BY recording')


def compare_summaries(a: pd.DataFrame, b: pd.DataFrame, tol: float = 1e-9) -> pd.DataFrame:
    """``a`` and ``b`` (same recordings, ``SUMMARY_COLUMNS``) side by side with a column ``same`` per recording: equal
    within ``tol`` and the catalog's rounding (half a unit of the decimals ``SHOWN_DIGITS`` keeps; the tables keep full
    precision)."""
    a, b = a.sort_index(), b.reindex(a.sort_index().index)
    same = np.ones(len(a), bool)
    for c in SUMMARY_COLUMNS:
        x, y = a[c].astype(float).to_numpy(), b[c].astype(float).to_numpy()
        close = tol + (0.5 * 10.0 ** -SHOWN_DIGITS[c] if c in SHOWN_DIGITS else 0.0)  # within the rounding
        same &= (np.isnan(x) & np.isnan(y)) | (np.abs(x - y) <= close)
    both = pd.concat({"pandas": a, "catalog": b}, axis=1)
    both[("same", "")] = same  # (both["same"] is that column)
    return both


def tagged_rows(patches: pd.DataFrame, keys: Iterable[tuple[str, int]]) -> pd.DataFrame:
    """The rows of ``patches`` named by (recording, rank) keys."""
    keys = set(keys)
    return patches[[(str(r), int(k)) in keys for r, k in zip(patches["recording"], patches["rank"])]]


__all__ = ["PATCH_COLUMNS", "SUMMARY_COLUMNS", "SHOWN_DIGITS", "best_frame", "flag_cues", "recording_properties", "rounded_properties", "patch_rows",
           "recordings_table", "tables_from_traces", "read_dataset", "ranked", "per_class", "filter_patches",
           "cues_of", "patch_exclusions", "pandas_summary", "catalog_summary", "flagged_from_catalog",
           "compare_summaries", "tagged_rows"]
