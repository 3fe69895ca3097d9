"""The whole dataset at CCM scale: a synthetic dataset of N recordings (default 1,140, CCM's one view) written as
light .rrd files, served by Rerun's catalog server, queried, browsed (notebook 04's grid) and tuned (notebook 02's
TuningPanel). Prints the figures and the machine's load; no assertion.

Synthetic recordings (cheap, and how realistic): each is one of the three bundled samples (36 frames of 480×270, its
trace from the cache: depth detector, replayed, no detector or model runs) under a new id, with its ground-truth
mass drawn at random (so errors, scores and ranks differ) and its recording properties recomputed. Writing one light
.rrd costs what a real one costs for those sizes (it reads the source's best frame and writes the overlays, patches,
predictions, decisions and properties); a CCM recording is 1280×720 with ~150 frames, so its best-frame JPEG and its
per-frame overlays are larger (3–4×) — the light .rrd of the real CCM recording 618 (8 frames) is ~0.4 MB. The
pipeline itself (detection) is not timed here: see benchmarks/scale.py.

    .venv/bin/python benchmarks/dataset_catalog.py [--n 1140] [--out DIR] [--weights PATH] [--cache DIR]

Goals: serve start to table listed <= 10 s, a catalog query <= 1 s, a slider change <= 300 ms.
"""
from __future__ import annotations

import argparse
import copy
import dataclasses
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def synthetic(samples, recordings, n: int, seed: int = 0):
    """``n`` (trace, recording) pairs: the samples under new ids ``syn_0000`` ..., random ground-truth masses."""
    rng = np.random.default_rng(seed)
    out = []
    for j in range(n):
        t, rec = samples[j % len(samples)], recordings[j % len(recordings)]
        meta = copy.deepcopy(t.recording.meta)
        container = dict(meta.get("container", {}))
        container["mass_g"] = float(np.round(rng.uniform(2.0, 120.0), 1))
        meta["container"] = container
        trace = copy.copy(t)
        trace.recording = dataclasses.replace(t.recording, id=f"syn_{j:04d}", config_id=str(j), meta=meta)
        out.append((trace, rec))
    return out


def timed(fn, *args, repeat: int = 1, **kwargs):
    best, value = None, None
    for _ in range(repeat):
        t0 = time.perf_counter()
        value = fn(*args, **kwargs)
        s = time.perf_counter() - t0
        best = s if best is None else min(best, s)
    return best, value


def main(argv=None) -> int:
    import massviz as mv
    from massviz.evaluation import browser as B
    from massviz.views.failure_browser import BrowserState, FailureBrowser
    from massviz.views.rerun_dataset import write_index, write_recording
    from massviz.views.rerun_serve import open_catalog
    from massviz.views.widgets import Tuner, TuningPanel

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, default=1140, help="recordings (default: 1140, CCM's one view)")
    p.add_argument("--out", help="dataset folder (default: a temporary one, removed at the end)")
    p.add_argument("--weights", help="mass-CNN checkpoint (default: $MASSVIZ_WEIGHTS, ../shared/..., or download)")
    p.add_argument("--cache", help="trace cache (default: $MASSVIZ_CACHE_DIR or the user cache)")
    args = p.parse_args(argv)
    print(f"load average at the start: {' '.join(f'{v:.1f}' for v in os.getloadavg())} on {os.cpu_count()} CPUs")
    reference = ROOT.parent / "shared" / "weights" / "corsmal_visual" / "Encoder_pool_aug_158.torch"
    weights = args.weights or os.environ.get("MASSVIZ_WEIGHTS") or (str(reference) if reference.is_file() else None)
    recs = mv.collect_recordings([ROOT / "data_samples"])
    samples = mv.process_recordings(recs, detector="depth", weights=weights, cache=args.cache, quiet=True)
    pairs = synthetic(samples, recs, args.n)
    tmp = None if args.out else tempfile.mkdtemp(prefix="massviz-bench-")
    out = Path(args.out or tmp) / "dataset"
    out.mkdir(parents=True, exist_ok=True)
    try:
        t0 = time.perf_counter()
        results = [write_recording(t, r, out) for t, r in pairs]
        index, patches = write_index(out, results)
        write_s = time.perf_counter() - t0
        rrd, inp = index["rrd_bytes"].to_numpy(float), index["input_bytes"].to_numpy(float)
        print(f"write {args.n} light .rrd files: {write_s:.1f} s ({1000 * write_s / args.n:.0f} ms per recording); "
              f"{rrd.mean():,.0f} bytes per recording against {inp.mean():,.0f} input bytes "
              f"({rrd.mean() / inp.mean():.3f}x); {rrd.sum() / 2**20:.0f} MiB in all")

        t0 = time.perf_counter()
        cat = open_catalog(out)
        started = time.perf_counter() - t0
        table = cat.segment_table()
        listed = time.perf_counter() - t0
        print(f"serve: catalog server up in {started:.2f} s, segment table of {len(table)} rows listed "
              f"{listed:.2f} s after the start (goal <= 10 s)")
        try:
            q, flagged = timed(B.flagged_from_catalog, cat, repeat=3)
            print(f"catalog query (DataFusion SQL) 'every recording with flagged patches': {1000 * q:.0f} ms, "
                  f"{len(flagged)} recordings, {int(flagged['n_flagged'].sum())} flagged patches (goal <= 1 s)")
            q2, summary = timed(B.catalog_summary, cat, repeat=3)
            same = B.compare_summaries(B.pandas_summary(index, patches), summary)["same"].all()
            print(f"catalog summary of every recording: {1000 * q2:.0f} ms; equal to pandas over the tables: {same}")
        finally:
            cat.close()

        recordings, patch_table = B.read_dataset(out)
        build, browser = timed(lambda: FailureBrowser(BrowserState(recordings, patch_table), out, viewer=False))
        lat = {name: 1000 * browser.set(**f) for name, f in
               [("flagged", {"flagged": True}), ("class cup", {"flagged": None, "cls": "cup"}),
                ("error > 2", {"cls": None, "min_error": 2.0}), ("cue size", {"min_error": None, "cue": "size"}),
                ("all", {"cue": None})]}
        print(f"notebook 04 grid over {len(patch_table)} patches of {len(recordings)} recordings: built in "
              f"{1000 * build:.0f} ms ({browser.max_tiles} tiles shown); filter changes (ms): "
              + ", ".join(f"{k} {v:.0f}" for k, v in lat.items()))

        traces = [t for t, _ in pairs]
        t0 = time.perf_counter()
        panel = TuningPanel(Tuner(traces))
        print(f"TuningPanel over {len(traces)} recordings built in {time.perf_counter() - t0:.1f} s")
        sweeps = {"k": [6, 3, 5], "threshold": [0.6, 0.4], "stride": [2, 1]}
        for name, values in sweeps.items():
            ms = [1000 * panel.set(**{name: v}) for v in values]
            print(f"slider {name}: {', '.join(f'{m:.0f}' for m in ms)} ms (goal <= 300 ms)")
    finally:
        if tmp:
            shutil.rmtree(tmp, ignore_errors=True)
    print(f"load average at the end: {' '.join(f'{v:.1f}' for v in os.getloadavg())}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
