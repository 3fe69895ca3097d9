"""Two runs of a whole dataset side by side (pandas in, pandas out): what changed when the detector, its weights,
the threshold or K changed.

A run is the failure browser's two tables (``massviz.evaluation.browser``): one row per recording (estimate,
relative error, score, flags, settings) and one row per chosen patch (rank, frame, box, prediction, flag). It comes
from

* a dataset folder written by ``massviz log DATASET --rrd-dir OUT`` (``load_run``: its ``index.csv`` and
  ``patches.csv``; nothing is recomputed; ``with_traces(plan_traces(run, options))`` adds the traces of its
  recordings, from the trace cache with the settings, source and weights its ``index.csv`` records (read and
  checked by ``massviz.io.run_folder``, the pipelines built by ``massviz.app``), each checked against the folder's
  estimate), or
* traces (``run_from_traces``), e.g. those of the trace cache selected by their settings (``run_from_cache``:
  detector, threshold, K, stride, weights; cached detections are reused, a threshold or K the cache can serve runs
  no detector, and a recording without a usable cache entry is processed once and cached), or the cache's
  selection indexes (``run_from_indexes``: no full trace read; the tables of the patches' images aside, the same).

``patch_changes(a, b)`` matches the chosen patches of each recording by frame and box (IoU >= ``iou`` in the same
frame, one to one, as ``massviz.evaluation.compare`` matches detections): one row per patch, ``same``, ``re-ranked``,
``added`` (only in B) or ``dropped`` (only in A), with its flag in each run. ``compare_runs(a, b)`` is one row per
recording: estimate, relative error and score of A and B (``_a``/``_b``) and their B − A ``delta_``, the changed
patches (``frame:x1,y1,x2,y2``), the flags that appeared or went, ranked by how much the error changed (a
recording estimated by one run only first). ``run_scores`` gives per class and overall the score of A, B and of the
pairwise best (each recording's better run).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

import numpy as np
import pandas as pd

from massviz.app import PipelineOptions
from massviz.errors import MassvizError

if TYPE_CHECKING:
    from massviz.core.trace import Trace
from massviz.evaluation.browser import read_dataset, tables_from_traces
from massviz.evaluation.compare import DEFAULT_IOU, match_boxes

#: the settings a run from the trace cache may set (the ``PipelineOptions`` fields marked as settings), and how each
#: is read from text.
SETTINGS = PipelineOptions.setting_types()
#: the per-recording figures compared (``_a``, ``_b`` and ``delta_`` columns).
FIGURES = ("estimate_g", "rel_error", "score", "n_flagged")
#: the settings columns of a recording row, shown per run.
SETTING_COLUMNS = ("detector", "k", "threshold", "stride", "weights_id")
CHANGES = ("same", "re-ranked", "added", "dropped")
#: two estimates closer than this (grams) are a tie: neither run is better (the last printed digit of an estimate
#: is 0.1 g; differences of ~1e-5 g are floating-point noise of the same patches, not a change)
TIE_G = 0.05
#: ``outcome`` of a recording in ``compare_runs``: which run is better, a tie, or not comparable (no ground truth, in
#: one run only)
OUTCOMES = ("b better", "a better", "tie", "")


@dataclass
class Run:
    """One run of a dataset: ``recordings`` (indexed by id) and ``patches`` tables, a ``label``; ``traces`` when the
    run was made from traces (the two-run recordings and the patch map need them), ``source`` what it was read
    from."""

    label: str
    recordings: pd.DataFrame
    patches: pd.DataFrame
    traces: list | None = None
    source: str = ""
    recordings_of: list = field(default_factory=list)  # the Recording of each trace, where known


def load_run(folder: str | Path, label: str | None = None) -> Run:
    """The run a dataset folder (``massviz log DATASET --rrd-dir OUT``) holds; ``DataError`` naming the file when
    it is incomplete (``browser.read_dataset``)."""
    recordings, patches = read_dataset(folder)
    return Run(label or Path(folder).name, recordings, patches, source=str(folder))


def run_from_traces(traces: Sequence, label: str = "", recordings_of: Sequence = ()) -> Run:
    """The run of ``traces`` (one per recording)."""
    recordings, patches = tables_from_traces(list(traces))
    return Run(label, recordings, patches, traces=list(traces), recordings_of=list(recordings_of))


def parse_settings(text: str, what: str = "settings") -> dict:
    """``"detector=depth,threshold=0.3,k=3"`` → ``{"detector": "depth", "threshold": 0.3, "k": 3}``;
    ``MassvizError`` naming the bad part (names: ``SETTINGS``)."""
    out = {}
    for part in (p.strip() for p in str(text).split(",")):
        if not part:
            continue
        name, sep, value = part.partition("=")
        name = name.strip().replace("-", "_").lower()
        if not sep or name not in SETTINGS or not value.strip():
            raise MassvizError(f"{what} {text!r}: {part!r} is not NAME=VALUE with NAME one of "
                               f"{', '.join(SETTINGS)}")
        try:
            out[name] = SETTINGS[name](value.strip())
        except ValueError:
            raise MassvizError(f"{what} {text!r}: {name} must be {'an integer' if SETTINGS[name] is int else 'a number'}"
                               f", got {value.strip()!r}") from None
    return out


def describe_settings(settings: dict) -> str:
    return ",".join(f"{k}={v}" for k, v in settings.items()) or "defaults"


def run_from_cache(recordings: Sequence, options=None, *, label: str | None = None, progress: bool = False,
                   **settings) -> Run:
    """The run of ``recordings`` (paths or ``Recording`` objects) with ``options`` (``PipelineOptions``) and
    ``settings`` (``SETTINGS`` names) over them, from the trace cache (``massviz.app``: cached detections are
    reused; only what the cache cannot serve is computed, then cached)."""
    from massviz.app import build_pipeline
    from massviz.io.recording import open_recording

    options = (options or PipelineOptions()).replace(**settings) if settings else (options or PipelineOptions())
    pipeline = build_pipeline(options)
    recs = [r if not isinstance(r, (str, Path)) else open_recording(r) for r in recordings]
    traces = [pipeline.process(r, progress=progress) for r in recs]
    return run_from_traces(traces, label if label is not None else describe_settings(settings), recs)


@dataclass
class TracePlan:
    """What ``with_traces`` computes for a run folder: its ``run``, the recording of each id (``recordings``) and
    one pipeline per distinct settings with the ids it serves (``pipelines``), every input checked."""

    run: Run
    recordings: dict
    pipelines: list


def plan_traces(run: Run, options=None, ids: Sequence | None = None, *, weights_option: str = "--weights",
                allow_partial: bool = False) -> TracePlan:
    """Check that the traces of a run folder's recordings ``ids`` (default: all) can be made as the folder records
    them, before anything runs: each row read (``massviz.io.run_folder.read_rows``: its source found and opened as
    the recording of that id, its settings ``detector``, ``threshold``, ``k``, ``stride``), one pipeline built per
    distinct settings over ``options`` (``PipelineOptions``: the detector's weights, replay input, precision, cache
    ...; ``massviz.app.build_pipelines``), and the mass CNN ``options`` loads is the one of the row's ``weights_id``
    (``weights_option``: the option that gives it, for the message). ``MassvizError`` naming the folder's
    ``index.csv`` and the recording when not."""
    from massviz.app import build_pipelines
    from massviz.io.run_folder import read_rows

    options = options or PipelineOptions()
    folder = Path(run.source)
    ids = list(run.recordings.index) if ids is None else list(ids)
    rows = read_rows(run.recordings, folder, ids, precision=options.precision, allow_partial=allow_partial)
    pipelines = []
    for pipeline, rids in build_pipelines(options, {rid: row.settings for rid, row in rows.items()}):
        have = getattr(pipeline.model, "weights_id", "") or ""
        for rid in rids:
            want = run.recordings.loc[rid].get("weights_id")
            want = want if isinstance(want, str) else ""
            if want != have:
                raise MassvizError(f"recording {rid!r} was made with the mass-CNN weights {want!r}, the checkpoint "
                                   f"{weights_option} gives is {have!r}", folder)
        pipelines.append((pipeline, rids))
    return TracePlan(run, {rid: row.recording for rid, row in rows.items()}, pipelines)


def with_traces(plan: TracePlan, *, progress: bool = False) -> Run:
    """The run of ``plan`` (``plan_traces``) with the traces of its recordings (``Run.traces``, in the plan's order,
    and ``recordings_of``), each from the trace cache (a recording the cache cannot serve is processed once and
    cached); ``MassvizError`` naming the folder's ``index.csv`` and the recording when a trace's estimate is not
    the folder's (both none, or equal to float precision): the folder was made with what the options do not
    reproduce (other detector weights, replay input ...)."""
    from massviz.io.run_folder import INDEX_NAME, row_error

    traces = {}
    for pipeline, rids in plan.pipelines:
        for rid in rids:
            traces[rid] = pipeline.process(plan.recordings[rid], progress=progress)
    index_path = Path(plan.run.source) / INDEX_NAME
    for rid, trace in traces.items():
        got = float(trace.estimate) if trace.estimate >= 0 else np.nan
        want = pd.to_numeric(pd.Series([plan.run.recordings.loc[rid].get("estimate_g")]), errors="coerce").iloc[0]
        if not (np.isnan(got) and np.isnan(want) or np.isclose(got, want, rtol=1e-6, atol=1e-6)):
            raise row_error(index_path, rid, f"the trace made with its settings estimates {got:.6g} g, the folder's "
                           f"estimate_g is {want:.6g} g: the folder was made with what this command does not "
                           "reproduce (other detector weights, replay input or precision?)")
    ids = list(plan.recordings)
    return dataclasses.replace(plan.run, traces=[traces[r] for r in ids],
                               recordings_of=[plan.recordings[r] for r in ids])


def trace_from_index(index, *, k: int, threshold: float) -> "Trace":
    """A ``Trace`` of a selection index (``massviz.io.cache.TraceIndex``: every detection's columns, no patch or
    mask) selected with ``k`` and ``threshold``: its selection, estimate and flags as ``reselect`` makes them on the
    full trace (they read no patch or mask), in a fraction of the time of reading the full trace. The ground-truth
    overlaps the index kept (``Detections.gt_iou`` ...) are those of the recording's ground truth when the trace
    was cached."""
    from massviz.core.flags import analyse, ground_truth_source
    from massviz.core.selection import check_not_below_cut, estimate_mass, select_k_nearest
    from massviz.core.trace import Trace

    check_not_below_cut(threshold, index.detect_threshold, "the cached trace", index.trace_path)
    dets = index.detections
    selection = select_k_nearest(dets.d, dets.score, int(k), float(threshold), index.excluded)
    trace = Trace(recording=index.recording, detector=dict(index.detector), detect_threshold=index.detect_threshold,
                  threshold=float(threshold), k=int(k), stride=index.stride, frames=index.frames, detections=dets,
                  selection=selection, estimate=estimate_mass(dets.pred, selection), weights_id=index.weights_id,
                  excluded=index.excluded,
                  ground_truth_source=ground_truth_source(index.recording) if np.isfinite(dets.gt_iou).any() else "")
    if trace.flags is None or not trace.flags.describes(trace):  # the flags of this selection
        trace = dataclasses.replace(trace, flags=analyse(trace))
    return trace


def run_from_indexes(indexes: Sequence, *, k: int, threshold: float, label: str = "") -> Run:
    """The run of cached selection indexes (``massviz.evaluation.tuning.index_recordings``, or a warm command's
    ``cached_indexes``) at ``k`` and ``threshold``: the tables of ``run_from_traces``, without reading any full
    trace (what a comparison over a 1,140-recording dataset reads)."""
    return run_from_traces([trace_from_index(i, k=k, threshold=threshold) for i in indexes], label)


# ------------------------------------------------------------------------------------------------- comparison
def patch_changes(a: Run, b: Run, iou: float = DEFAULT_IOU) -> pd.DataFrame:
    """One row per chosen patch of either run, per recording both runs hold: ``recording``, ``patch``
    (``frame:x1,y1,x2,y2``, A's box where both), ``frame``, ``rank_a``, ``rank_b`` (-1: not chosen in that run),
    ``change`` (``CHANGES``), ``flagged_a``, ``flagged_b``, ``cues_a``, ``cues_b``, ``pred_g_a``, ``pred_g_b``,
    ``iou``. Patches match by frame and box (IoU >= ``iou``, one to one, greedy, highest first)."""
    if not 0.0 < iou <= 1.0:
        raise ValueError("iou must be in (0, 1]")
    common = sorted(set(a.recordings.index) & set(b.recordings.index))
    sa, sb = _PatchArrays(a.patches, common), _PatchArrays(b.patches, common)
    cols = {c: [] for c in ("recording", "patch", "frame", "rank_a", "rank_b", "change", "flagged_a", "flagged_b",
                            "cues_a", "cues_b", "pred_g_a", "pred_g_b", "iou")}

    def add(rid, i, j, change, v):
        ref, k = (sa, i) if i >= 0 else (sb, j)
        box = ref.box[k]
        cols["recording"].append(rid)
        cols["patch"].append(f"{ref.frame[k]}:{box[0]},{box[1]},{box[2]},{box[3]}")
        cols["frame"].append(int(ref.frame[k]))
        for side, arr, idx in (("a", sa, i), ("b", sb, j)):
            cols[f"rank_{side}"].append(int(arr.rank[idx]) if idx >= 0 else -1)
            cols[f"flagged_{side}"].append(bool(arr.flagged[idx]) if idx >= 0 else False)
            cols[f"cues_{side}"].append(arr.cues[idx] if idx >= 0 else "")
            cols[f"pred_g_{side}"].append(float(arr.pred[idx]) if idx >= 0 else np.nan)
        cols["change"].append(change)
        cols["iou"].append(v)

    for rid in common:
        ia, ib = sa.rows.get(rid, _NONE), sb.rows.get(rid, _NONE)
        partner = {}
        fa_all, fb_all = sa.frame[ia], sb.frame[ib]
        for frame in np.intersect1d(fa_all, fb_all):
            fa, fb = ia[fa_all == frame], ib[fb_all == frame]
            for i, j, v in match_boxes(sa.box[fa].astype(np.float64), sb.box[fb].astype(np.float64), iou):
                partner[int(fa[i])] = (int(fb[j]), v)
        for i in ia:
            hit = partner.get(int(i))
            if hit is None:
                add(rid, int(i), -1, "dropped", np.nan)
            else:
                add(rid, int(i), hit[0], "same" if sa.rank[i] == sb.rank[hit[0]] else "re-ranked", hit[1])
        matched_b = {j for j, _ in partner.values()}
        for j in ib:
            if int(j) not in matched_b:
                add(rid, -1, int(j), "added", np.nan)
    return pd.DataFrame(cols)


_NONE = np.zeros(0, np.int64)


class _PatchArrays:
    """A patch table's columns as arrays, and each recording's row positions (``rows``), for ``patch_changes``."""

    def __init__(self, patches: pd.DataFrame, recordings):
        p = patches[patches["recording"].isin(recordings)]
        self.frame = p["frame"].to_numpy(np.int64)
        self.rank = p["rank"].to_numpy(np.int64)
        self.box = p[["x1", "y1", "x2", "y2"]].to_numpy(np.int64)
        self.flagged = p["flagged"].to_numpy(bool)
        self.cues = [c if isinstance(c, str) else "" for c in p["cues"]] if "cues" in p else [""] * len(p)
        self.pred = p["pred_g"].to_numpy(np.float64) if "pred_g" in p else np.full(len(p), np.nan)
        self.rows = {rid: np.asarray(ix, np.int64) for rid, ix in
                     pd.Series(np.arange(len(p))).groupby(p["recording"].to_numpy()).groups.items()}
        self.rows = {rid: np.sort(np.asarray(ix, np.int64)) for rid, ix in self.rows.items()}


def _joined(values) -> str:
    return " ".join(values)


def _cue_set(text) -> set:
    return {c for c in str(text if isinstance(text, str) else "").split(",") if c}


def compare_runs(a: Run, b: Run, iou: float = DEFAULT_IOU, changes: pd.DataFrame | None = None) -> pd.DataFrame:
    """One row per recording of either run (module docstring), indexed by id: ``container_class``, ``gt_mass_g``,
    ``estimate_g_a``/``_b``/``delta_estimate_g``, ``rel_error_*``, ``score_*``, ``n_flagged_*`` (delta: B − A),
    ``in_runs`` (``both``, ``A``, ``B``), the settings of each run (``detector_a`` ...), ``patches_added``,
    ``patches_dropped``, ``patches_reranked`` (``frame:x1,y1,x2,y2`` separated by spaces; re-ranked ones with
    ``@rankA>rankB``), ``n_patches_changed``, ``flags_appeared``/``flags_gone`` (flagged patches: ``frame:box``),
    ``n_flags_appeared``/``n_flags_gone``, ``cues_appeared``/``cues_gone``; ranked by how much the relative error
    changed (``abs_delta_rel_error``, a recording estimated by one run only first as ∞, not comparable ones last;
    ``change_rank`` is that order, 1 first)."""
    changes = patch_changes(a, b, iou) if changes is None else changes
    ra, rb = a.recordings, b.recordings
    ids = sorted(set(ra.index) | set(rb.index), key=str)
    out = pd.DataFrame(index=pd.Index(ids, name=None))
    out["id"] = ids
    for col in ("container_class", "gt_mass_g"):
        out[col] = ra[col].reindex(ids).combine_first(rb[col].reindex(ids)) if col in ra and col in rb else np.nan
    out["in_runs"] = ["both" if i in ra.index and i in rb.index else ("A" if i in ra.index else "B") for i in ids]
    for fig in FIGURES:
        xa = pd.to_numeric(ra[fig], errors="coerce").reindex(ids) if fig in ra else pd.Series(np.nan, index=ids)
        xb = pd.to_numeric(rb[fig], errors="coerce").reindex(ids) if fig in rb else pd.Series(np.nan, index=ids)
        out[f"{fig}_a"], out[f"{fig}_b"], out[f"delta_{fig}"] = xa, xb, xb - xa
    for col in SETTING_COLUMNS:
        out[f"{col}_a"] = ra[col].reindex(ids) if col in ra else np.nan
        out[f"{col}_b"] = rb[col].reindex(ids) if col in rb else np.nan
    ch = changes

    def joined(mask, values) -> pd.Series:
        mask = np.asarray(mask, bool)
        if not mask.any():
            return pd.Series("", index=ids)
        return values[mask].groupby(ch["recording"][mask]).agg(" ".join).reindex(ids).fillna("")

    rr_ = ch["change"] == "re-ranked"
    out["patches_added"] = joined(ch["change"] == "added", ch["patch"])
    out["patches_dropped"] = joined(ch["change"] == "dropped", ch["patch"])
    out["patches_reranked"] = joined(rr_, ch["patch"] + "@" + ch["rank_a"].astype(str) + ">" +
                                     ch["rank_b"].astype(str))
    out["flags_appeared"] = joined(ch["flagged_b"] & ~ch["flagged_a"], ch["patch"])
    out["flags_gone"] = joined(ch["flagged_a"] & ~ch["flagged_b"], ch["patch"])
    count = lambda col: out[col].map(lambda s: len(s.split()) if s else 0)  # noqa: E731
    out["n_patches_changed"] = count("patches_added") + count("patches_dropped") + count("patches_reranked")
    out["n_flags_appeared"], out["n_flags_gone"] = count("flags_appeared"), count("flags_gone")
    cues_a = ra["cues"].reindex(ids).map(_cue_set) if "cues" in ra else pd.Series([set()] * len(ids), index=ids)
    cues_b = rb["cues"].reindex(ids).map(_cue_set) if "cues" in rb else pd.Series([set()] * len(ids), index=ids)
    out["cues_appeared"] = [",".join(sorted(y - x)) for x, y in zip(cues_a, cues_b)]
    out["cues_gone"] = [",".join(sorted(x - y)) for x, y in zip(cues_a, cues_b)]
    out["outcome"] = outcomes(out)
    ea, eb = out["rel_error_a"].to_numpy(float), out["rel_error_b"].to_numpy(float)
    key = np.abs(eb - ea)
    one_only = (np.isfinite(ea) != np.isfinite(eb)) & out["gt_mass_g"].notna().to_numpy() & \
        (out["in_runs"] == "both").to_numpy()
    key[one_only] = np.inf
    out["abs_delta_rel_error"] = key
    out = out.sort_values(["abs_delta_rel_error", "id"], ascending=[False, True], na_position="last",
                          kind="stable")
    out["change_rank"] = np.arange(1, len(out) + 1)
    return out


def outcomes(table: pd.DataFrame, tie_g: float = TIE_G) -> pd.Series:
    """Per recording of a comparison: ``"tie"`` when both runs estimate it within ``tie_g`` grams of each other (or
    neither estimates it), else ``"b better"`` / ``"a better"`` by the CORSMAL score (a run that estimates beats one
    that does not); ``""`` without a ground truth or when one run lacks the recording."""
    ga, gb = table["estimate_g_a"].to_numpy(float), table["estimate_g_b"].to_numpy(float)
    sa = np.nan_to_num(table["score_a"].to_numpy(float), nan=0.0)
    sb = np.nan_to_num(table["score_b"].to_numpy(float), nan=0.0)
    estimated_a, estimated_b = np.isfinite(ga) & (ga >= 0), np.isfinite(gb) & (gb >= 0)
    tie = (estimated_a & estimated_b & (np.abs(gb - ga) < tie_g)) | (~estimated_a & ~estimated_b) | (sa == sb)
    result = np.where(tie, "tie", np.where(sb > sa, "b better", "a better")).astype(object)
    comparable = table["gt_mass_g"].notna().to_numpy() & (table["in_runs"] == "both").to_numpy()
    result[~comparable] = ""
    return pd.Series(result, index=table.index, name="outcome")


def filter_comparison(table: pd.DataFrame, *, worse_by: float | None = None, better_by: float | None = None,
                      flag_appeared: bool | None = None, flag_gone: bool | None = None, patches_changed: bool | None = None,
                      cls: str | None = None) -> pd.DataFrame:
    """The rows of a ``compare_runs`` table that pass every filter given: ``worse_by`` (B's relative error above
    A's by more than this; a recording B no longer estimates counts as worse), ``better_by`` (the converse),
    ``flag_appeared`` / ``flag_gone`` (a flagged patch appeared / went, or not), ``patches_changed``, ``cls``."""
    keep = np.ones(len(table), bool)
    ea, eb = table["rel_error_a"].to_numpy(float), table["rel_error_b"].to_numpy(float)
    if worse_by is not None:
        lost = np.isfinite(ea) & ~np.isfinite(table["estimate_g_b"].to_numpy(float))
        keep &= (np.nan_to_num(eb - ea, nan=-np.inf) > worse_by) | lost
    if better_by is not None:
        gained = ~np.isfinite(table["estimate_g_a"].to_numpy(float)) & np.isfinite(eb)
        keep &= (np.nan_to_num(ea - eb, nan=-np.inf) > better_by) | gained
    if flag_appeared is not None:
        keep &= (table["n_flags_appeared"].to_numpy() > 0) == bool(flag_appeared)
    if flag_gone is not None:
        keep &= (table["n_flags_gone"].to_numpy() > 0) == bool(flag_gone)
    if patches_changed is not None:
        keep &= (table["n_patches_changed"].to_numpy() > 0) == bool(patches_changed)
    if cls:
        keep &= (table["container_class"] == cls).to_numpy()
    return table[keep]


def run_scores(table: pd.DataFrame) -> pd.DataFrame:
    """Per class and ``all`` (the recordings with a ground truth both runs hold): ``recordings``, ``score_a %``,
    ``score_b %``, ``best %`` (the mean of each recording's better score: the pairwise best), ``mean ε a``/``b``,
    ``b better``/``a better``/``ties`` (the recordings' ``outcome``: estimates within :data:`TIE_G` grams are a tie,
    whatever their scores' last digits). Scores are the CORSMAL per-recording score exp(−ε) (0 when not estimated),
    averaged."""
    t = table[(table["in_runs"] == "both") & table["gt_mass_g"].notna()].copy()
    t["score_a"] = t["score_a"].fillna(0.0)
    t["score_b"] = t["score_b"].fillna(0.0)
    t["best"] = np.maximum(t["score_a"], t["score_b"])
    if "outcome" not in t:
        t["outcome"] = outcomes(t)

    def summary(g: pd.DataFrame) -> dict:
        return {"recordings": len(g), "score_a %": 100 * g["score_a"].mean(), "score_b %": 100 * g["score_b"].mean(),
                "best %": 100 * g["best"].mean(), "mean ε a": g["rel_error_a"].mean(),
                "mean ε b": g["rel_error_b"].mean(), "b better": int((g["outcome"] == "b better").sum()),
                "a better": int((g["outcome"] == "a better").sum()), "ties": int((g["outcome"] == "tie").sum())}

    rows = {str(c): summary(g) for c, g in t.groupby("container_class", sort=True)}
    rows["all"] = summary(t)
    return pd.DataFrame.from_dict(rows, orient="index")


def write_table(table: pd.DataFrame, path: str | Path) -> Path:
    """``table`` as CSV or Parquet (by the suffix: .csv, .parquet), atomically."""
    from massviz.io.atomic import atomic_path
    from massviz.io.untrusted.tables import write_csv

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".csv", ".parquet"):
        raise MassvizError("the table's file must end in .csv or .parquet", path)
    with atomic_path(path) as tmp:
        if suffix == ".csv":
            write_csv(table, tmp)
        else:
            table.to_parquet(tmp, index=False)
    return path


__all__ = ["Run", "SETTINGS", "FIGURES", "CHANGES", "TIE_G", "OUTCOMES", "outcomes", "TracePlan", "load_run",
           "run_from_traces", "run_from_cache", "plan_traces", "with_traces", "run_from_indexes", "trace_from_index",
           "parse_settings", "describe_settings", "patch_changes", "compare_runs", "filter_comparison", "run_scores",
           "write_table"]
