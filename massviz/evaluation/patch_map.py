"""A map of every chosen patch of a dataset (pandas in, pandas out): where are the failures like this one?

* The embedding of a patch is the mass CNN's own description of it: the pooled maps its head reads
  (``MassPredictor.pooled_features``: 128×7×7 = 6,272 values), L2-normalised. No other model.
* ``embed_trace`` computes the embeddings of a trace's chosen patches once and caches them **with the trace**,
  beside its trace-cache entry and keyed like it (the same recording content, detector settings and stride) and by
  the model's id: ``…/<id>-<key>/t0.4.npz`` → ``e0.4-<model id>.emb`` (an .npz inside, not named so: every
  ``*.npz`` of the cache is a trace). The file names the trace file's identity, so a rewritten trace is embedded
  again; patches another K or threshold chooses later are added to it.
* ``patch_map(runs, model)`` — one row per distinct chosen patch (recording, frame and box) of one or more runs
  (``massviz.evaluation.runs.Run`` from traces): ``patch_id`` (``recording/frame:x1,y1,x2,y2``), recording,
  frame, box, class, rank, flag, ``runs`` (which runs chose it; ``run``: ``both`` or the one), the recording's class
  and relative error, ``detection`` (its index in the trace of run ``source_run``), the ground-truth instance its
  mask lies on where the flags know it (``ground_truth``: ``container``, ``pitcher`` ...), and its 2D position
  ``x``, ``y`` (``layout_2d``: UMAP when umap-learn is installed, else t-SNE from scikit-learn, else PCA).
* ``PatchMap.nearest(patch_id, n)`` — the ``n`` most similar patches (cosine distance in the embedding).
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import pandas as pd

from massviz.errors import MassvizError


def embedding_path(trace_path: str | Path, weights_id: str) -> Path:
    """``…/t0.4.npz`` → ``…/e0.4-<model id>.emb``: the embeddings file beside a trace-cache entry."""
    from massviz.io.untrusted import safe_filename

    trace_path = Path(trace_path)
    return trace_path.with_name("e" + trace_path.name[1:].removesuffix(".npz") +
                                f"-{safe_filename(weights_id or 'model', 40)}.emb")


def _identity(path: Path) -> list[int]:
    from massviz.io.filehash import identity

    return identity(os.stat(path))[:4]


def _read_cached(path: Path, trace_path: Path) -> dict[int, np.ndarray]:
    """detection → embedding from ``path``; {} when missing, unreadable or of another trace file."""
    from massviz.io.untrusted import load_npz_checked

    try:
        data = load_npz_checked(path, max_bytes=512 << 20)
        header = json.loads(data["header"].tobytes().decode())
        if header.get("trace") != _identity(trace_path):
            return {}
        det, feats = np.asarray(data["detection"], np.int64), np.asarray(data["features"], np.float32)
        if feats.ndim != 2 or len(det) != len(feats) or not np.isfinite(feats).all():
            return {}
        return {int(d): f for d, f in zip(det, feats)}
    except Exception:  # noqa: BLE001 - missing or damaged: computed again
        return {}


def _write_cached(path: Path, trace_path: Path, known: dict[int, np.ndarray]) -> None:
    from massviz.io.atomic import atomic_path

    det = np.array(sorted(known), np.int64)
    feats = np.stack([known[int(d)] for d in det]).astype(np.float16)
    header = np.frombuffer(json.dumps({"trace": _identity(trace_path)}).encode(), np.uint8)
    try:
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, header=header, detection=det, features=feats)
    except (OSError, MassvizError):
        pass  # a cache that cannot be written: the embeddings stand, they are only not kept


def _patch_images(trace, recording, need: list[int]) -> dict[int, np.ndarray]:
    dets = trace.detections
    out = {i: dets.patches[i] for i in need if dets.patches[i] is not None and dets.patches[i].size}
    missing = [i for i in need if i not in out]
    if missing and recording is not None and hasattr(recording, "frames"):
        from massviz.core.patches import crop

        frames = sorted({int(dets.frame[i]) for i in missing})
        for frame in recording.frames(indices=frames):
            for i in missing:
                if int(dets.frame[i]) == frame.index:
                    out[i] = crop(frame.rgb, dets.xyxy[i])
    return out


def embed_trace(trace, model, *, trace_path: str | Path | None = None, recording=None,
                detections: Sequence[int] | None = None) -> dict[int, np.ndarray]:
    """detection → embedding (float32, L2-normalised) of ``detections`` (default: the chosen patches) of
    ``trace``, read from / added to the file beside ``trace_path`` (its trace-cache entry) when given. A patch the
    trace did not keep is cut from ``recording``'s frame; one with no image anywhere is left out."""
    return embed_traces([trace], model, trace_paths=[trace_path], recordings=[recording],
                        detections=None if detections is None else [detections])[0]


def embed_traces(traces: Sequence, model, *, trace_paths: Sequence | None = None, recordings: Sequence | None = None,
                 detections: Sequence | None = None, rows: int = 64) -> list[dict[int, np.ndarray]]:
    """``embed_trace`` of each trace, the patches no file holds yet put through the model together (calls of
    ``rows`` patches, not one call per recording)."""
    n = len(traces)
    trace_paths = list(trace_paths or [None] * n)
    recordings = list(recordings or [None] * n)
    wid = getattr(model, "weights_id", "") or ""
    known, want, paths, todo = [], [], [], []
    for k, trace in enumerate(traces):
        sel = trace.selection if detections is None or detections[k] is None else detections[k]
        want.append([int(i) for i in sel])
        path = embedding_path(trace_paths[k], wid) if trace_paths[k] else None
        paths.append(path)
        known.append(_read_cached(path, Path(trace_paths[k])) if path is not None and path.is_file() else {})
        missing = [i for i in want[k] if i not in known[k]]
        if missing:
            images = _patch_images(trace, recordings[k], missing)
            todo += [(k, i, images[i]) for i in missing if i in images]
    for start in range(0, len(todo), 16 * rows):
        part = todo[start:start + 16 * rows]
        feats = model.pooled_features([img for _, _, img in part], rows=rows)
        feats /= np.maximum(np.linalg.norm(feats, axis=1, keepdims=True), 1e-12)
        for (k, i, _), f in zip(part, feats.astype(np.float16).astype(np.float32)):
            known[k][i] = f
    for k in sorted({k for k, _, _ in todo}):
        if paths[k] is not None:
            _write_cached(paths[k], Path(trace_paths[k]), known[k])
    return [{i: known[k][i] for i in want[k] if i in known[k]} for k in range(n)]


def trace_paths(traces: Sequence, recordings: Sequence, cache) -> list[Path | None]:
    """The trace-cache file of each trace (``cache``: a ``TraceCache``; None where not cached or no recording)."""
    out = []
    for trace, recording in zip(traces, list(recordings) + [None] * (len(traces) - len(recordings))):
        path = None
        if cache is not None and recording is not None:
            try:
                path = cache.lookup(recording, trace.detector, trace.stride, trace.threshold)
            except Exception:  # noqa: BLE001 - a recording whose files moved: embedded without the cache
                path = None
        out.append(path)
    return out


# ----------------------------------------------------------------------------------------------------------- map
@dataclass
class PatchMap:
    """``patches`` (one row per distinct chosen patch, module docstring) and their ``features`` (row-aligned,
    L2-normalised); ``method``: how ``x``/``y`` were laid out."""

    patches: pd.DataFrame
    features: np.ndarray
    method: str = ""

    def nearest(self, patch_id: str, n: int = 10) -> pd.DataFrame:
        """The ``n`` patches most similar to ``patch_id`` (cosine distance ``distance``, nearest first; itself
        left out)."""
        hits = np.flatnonzero(self.patches["patch_id"].to_numpy() == patch_id)
        if not len(hits):
            raise KeyError(f"no patch {patch_id!r} in the map")
        q = self.features[hits[0]]
        cosine = 1.0 - self.features @ q
        cosine[hits[0]] = np.inf
        order = np.lexsort((np.arange(len(cosine)), cosine))[:max(0, int(n))]  # ties: the earlier row
        order = order[np.isfinite(cosine[order])]
        return self.patches.iloc[order].assign(distance=cosine[order])


def layout_2d(features: np.ndarray, method: str = "auto", seed: int = 0) -> tuple[np.ndarray, str]:
    """(N×2 positions, the method used): ``auto`` is UMAP (umap-learn) when installed, else t-SNE (scikit-learn)
    when installed, else PCA; ``umap``, ``tsne`` and ``pca`` ask for one."""
    x = np.asarray(features, np.float32)
    n = len(x)
    if n < 3:
        return np.zeros((n, 2), np.float32) if n < 2 else np.array([[0, 0], [1, 0]], np.float32), "none"
    pca = _pca(x, min(50, n - 1, x.shape[1]), seed)
    if method in ("auto", "umap"):
        try:
            import umap  # noqa: F401

            xy = umap.UMAP(n_components=2, random_state=seed, n_neighbors=min(15, n - 1)).fit_transform(pca)
            return np.asarray(xy, np.float32), "umap"
        except ImportError:
            if method == "umap":
                raise MassvizError("UMAP needs umap-learn: pip install umap-learn") from None
    if method in ("auto", "tsne"):
        try:
            from sklearn.manifold import TSNE

            xy = TSNE(n_components=2, perplexity=float(min(30, max(2, (n - 1) // 3))), init="pca",
                      random_state=seed).fit_transform(pca)
            return np.asarray(xy, np.float32), "t-SNE"
        except ImportError:
            if method == "tsne":
                raise MassvizError("t-SNE needs scikit-learn: pip install scikit-learn") from None
    if method not in ("auto", "umap", "tsne", "pca"):
        raise MassvizError(f"layout method must be auto, umap, tsne or pca, got {method!r}")
    return pca[:, :2].astype(np.float32), "PCA"


def _pca(x: np.ndarray, k: int, seed: int = 0) -> np.ndarray:
    """The first ``k`` principal components' scores of ``x``: exact (SVD) for small inputs, else by a randomized
    SVD (Halko et al. 2011: a random projection, two power iterations; deterministic for ``seed``), which takes a
    second where the exact SVD of 5,700 × 6,272 features took minutes on two cores."""
    centred = x - x.mean(axis=0)
    if min(centred.shape) <= 500:
        u, s, _ = np.linalg.svd(centred, full_matrices=False)
    else:
        rng = np.random.default_rng(seed)
        q = centred @ rng.standard_normal((centred.shape[1], k + 10)).astype(centred.dtype)
        for _ in range(2):
            q, _ = np.linalg.qr(q)
            q = centred @ (centred.T @ q)
        q, _ = np.linalg.qr(q)
        ub, s, _ = np.linalg.svd(q.T @ centred, full_matrices=False)
        u = q @ ub
    out = u[:, :k] * s[:k]
    return out if out.shape[1] >= 2 else np.pad(out, ((0, 0), (0, 2 - out.shape[1])))


def _patch_id(recording: str, frame: int, box) -> str:
    return f"{recording}/{int(frame)}:{','.join(str(int(v)) for v in box)}"


def patch_map(runs: Sequence, model, *, cache=None, method: str = "auto", seed: int = 0) -> PatchMap:
    """The map of every chosen patch of ``runs`` (``Run`` objects made from traces; module docstring).
    ``cache``: the ``TraceCache`` the traces came from (embeddings are read from / kept beside its entries)."""
    from massviz.evaluation.browser import flag_cues

    rows: dict[str, dict] = {}
    feats: dict[str, np.ndarray] = {}
    for run in runs:
        if run.traces is None:
            raise MassvizError(f"run {run.label!r} holds no traces: the patch map needs them (a run from the "
                               "trace cache, or from traces)")
        recs = list(run.recordings_of) or [None] * len(run.traces)
        paths = trace_paths(run.traces, recs, cache)
        table = run.recordings
        embedded = embed_traces(run.traces, model, trace_paths=paths, recordings=recs)
        for trace, emb in zip(run.traces, embedded):
            rid = trace.recording.id
            dets = trace.detections
            names = dets.class_names()
            err = table["rel_error"].get(rid, np.nan) if "rel_error" in table else np.nan
            for rank, i in enumerate(int(i) for i in trace.selection):
                if i not in emb:
                    continue
                pid = _patch_id(rid, dets.frame[i], dets.xyxy[i])
                flag = trace.flags.of(i)
                flagged = bool(flag is not None and flag.flagged)
                row = rows.get(pid)
                if row is None:
                    x1, y1, x2, y2 = (int(v) for v in dets.xyxy[i])
                    row = rows[pid] = {
                        "patch_id": pid, "recording": rid, "frame": int(dets.frame[i]), "x1": x1, "y1": y1, "x2": x2,
                        "y2": y2, "class": names[i], "container_class": (trace.ground_truth.cls if trace.ground_truth
                                                                         is not None else "") or "",
                        "d_mm": float(dets.d[i]), "pred_g": float(dets.pred[i]), "ground_truth": (flag.ground_truth or "") if flag is not None else "",
                        "runs": [], "rank": {}, "flagged": False, "cues": "", "rel_error": {}, "detection": i,
                        "source_run": run.label}
                    feats[pid] = emb[i]
                row["runs"].append(run.label)
                row["rank"][run.label] = rank
                row["rel_error"][run.label] = float(err) if err is not None else np.nan
                if flagged:
                    row["flagged"] = True
                    row["cues"] = ",".join(flag_cues(flag))
    ids = list(rows)
    table = pd.DataFrame([rows[p] for p in ids])
    if not len(table):
        return PatchMap(pd.DataFrame(columns=["patch_id", "x", "y"]), np.zeros((0, 128 * 7 * 7), np.float32), "none")
    labels = [r.label for r in runs]
    table["run"] = ["both" if len(set(r)) > 1 else r[0] for r in table["runs"]] if len(labels) > 1 else labels[0]
    table["rel_error"] = [np.nanmax(list(e.values())) if e else np.nan for e in table["rel_error"]]
    table["rank"] = [min(r.values()) for r in table["rank"]]
    table["runs"] = [",".join(r) for r in table["runs"]]
    features = np.stack([feats[p] for p in ids]).astype(np.float32)
    xy, used = layout_2d(features, method, seed)
    table["x"], table["y"] = xy[:, 0], xy[:, 1]
    return PatchMap(table, features, used)


__all__ = ["PatchMap", "embedding_path", "embed_trace", "embed_traces", "trace_paths", "layout_2d", "patch_map"]
