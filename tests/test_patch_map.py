"""The map of every chosen patch (``massviz.evaluation.patch_map``): the mass CNN's pooled features find the
pitcher patches of cup_handover from one of them, are cached beside the trace-cache entry, and lay out in 2D."""
from __future__ import annotations

import shutil

import numpy as np
import pytest

from massviz.evaluation.patch_map import embedding_path, layout_2d, patch_map


@pytest.fixture(scope="module")
def setup(sample_cache, weights, samples_dir, tmp_path_factory):
    """Two runs of the samples (K 5 and K 10) from a copy of the samples' cache (embeddings are written into it)."""
    from massviz.app import PipelineOptions, build_pipeline
    from massviz.evaluation.runs import run_from_cache
    from massviz.io.cache import TraceCache
    from massviz.io.recording import collect_recordings

    cache = tmp_path_factory.mktemp("pm") / "cache"
    shutil.copytree(sample_cache, cache)
    recs = collect_recordings([samples_dir])
    options = PipelineOptions(detector="depth", weights=str(weights), cache=str(cache), threshold=0.4, quiet=True)
    runs = [run_from_cache(recs, options, label="K 5"), run_from_cache(recs, options, k=10, label="K 10")]
    return runs, build_pipeline(options).model, TraceCache(cache)


class Counting:
    """The model, counting the patches it embeds."""

    def __init__(self, model):
        self.model, self.weights_id, self.embedded = model, model.weights_id, 0

    def pooled_features(self, patches, **kw):
        self.embedded += len(patches)
        return self.model.pooled_features(patches, **kw)


def test_a_pitcher_patch_finds_the_other_pitcher_patches_first(setup):
    runs, model, cache = setup
    m = patch_map(runs, model, cache=cache)
    p = m.patches
    assert len(p) == 30 and p["patch_id"].is_unique  # K 10 of three recordings; K 5's are among them
    assert set(p["run"]) == {"both", "K 10"} and (p["run"] == "both").sum() == 15
    pitcher = p[p["ground_truth"] == "pitcher"]  # the flags' ground truth: the mask lies on the pitcher
    assert len(pitcher) == 3 and set(pitcher["recording"]) == {"cup_handover"} and pitcher["flagged"].all()
    for pid in pitcher["patch_id"]:
        near = m.nearest(pid, n=len(p) - 1)
        assert len(near) == len(p) - 1 and pid not in set(near["patch_id"])
        assert list(near["ground_truth"][:2]) == ["pitcher", "pitcher"], near[["patch_id", "ground_truth"]]
        assert (np.diff(near["distance"].to_numpy()) >= 0).all()
        cups = near[(near["recording"] == "cup_handover") & (near["ground_truth"] != "pitcher")]
        assert len(cups) == 7 and near.index.get_loc(cups.index[0]) >= 2  # every cup patch after the pitcher's
    assert np.isfinite(p[["x", "y"]].to_numpy()).all() and p[["x", "y"]].to_numpy().std(axis=0).min() > 0
    with pytest.raises(KeyError):
        m.nearest("nowhere/1:0,0,1,1")


def test_embeddings_are_cached_beside_the_trace_and_reused(setup):
    runs, model, cache = setup
    counting = Counting(model)
    first = patch_map(runs[:1], counting, cache=cache)  # the first test may have filled the files already
    trace_file = cache.lookup(runs[0].recordings_of[1], runs[0].traces[1].detector, 1, 0.4)
    emb = embedding_path(trace_file, model.weights_id)
    assert emb.parent == trace_file.parent and emb.is_file() and emb.suffix == ".emb"
    assert not list(cache.dir.glob("*/e*.npz"))  # every *.npz of the cache is a trace
    counting.embedded = 0
    again = patch_map(runs, counting, cache=cache)
    assert counting.embedded == 0  # all 30 read from the files beside the traces
    same = again.patches.set_index("patch_id").loc[first.patches["patch_id"]]
    for pid, f in zip(first.patches["patch_id"], first.features, strict=False):
        assert np.array_equal(again.features[again.patches.index[again.patches["patch_id"] == pid][0]], f)
    assert len(same) == 15
    emb.write_bytes(b"not an npz")  # a damaged file is computed again, never fatal
    patch_map(runs[:1], counting, cache=cache)
    assert counting.embedded == 5


def test_layout_methods():
    rng = np.random.default_rng(0)
    x = np.concatenate([rng.normal(0, 1, (20, 30)), rng.normal(8, 1, (20, 30))]).astype(np.float32)
    xy, method = layout_2d(x, "pca")
    assert method == "PCA" and xy.shape == (40, 2)
    assert abs(xy[:20, 0].mean() - xy[20:, 0].mean()) > 5 * max(xy[:20, 0].std(), xy[20:, 0].std())
    xy, method = layout_2d(x, "auto")
    assert method in ("umap", "t-SNE", "PCA") and np.isfinite(xy).all()
