"""Latency of a notebook slider change (threshold, K, stride) over 10 recordings: budget 200 ms.

Builds the bundled samples' traces (depth detector, cached in --cache), repeats them to 10 recordings, and times
``TuningPanel.set`` — the whole callback: re-selection of every recording, the CORSMAL score, and the refresh of the
panel's widgets (patch tiles, tables) — for a sweep of slider values. Prints median / p95 / max per slider and exits 1
when the max is over the budget.

    .venv/bin/python benchmarks/widgets_latency.py [--weights PATH] [--cache DIR] [--recordings 10] [--budget-ms 200]
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    import massviz as mv
    from massviz.views.widgets import Tuner, TuningPanel

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--weights", help="mass-CNN checkpoint (default: $MASSVIZ_WEIGHTS, ../shared/..., or download)")
    p.add_argument("--cache", help="trace cache (default: $MASSVIZ_CACHE_DIR or the user cache)")
    p.add_argument("--recordings", type=int, default=10)
    p.add_argument("--budget-ms", type=float, default=200.0)
    args = p.parse_args(argv)
    reference = ROOT.parent / "shared" / "weights" / "corsmal_visual" / "Encoder_pool_aug_158.torch"
    weights = args.weights or os.environ.get("MASSVIZ_WEIGHTS") or (str(reference) if reference.is_file() else None)
    t0 = time.perf_counter()
    samples = mv.process_recordings(mv.collect_recordings([ROOT / "data_samples"]), detector="depth",
                                    weights=weights, cache=args.cache, quiet=True)
    print(f"{len(samples)} sample traces in {time.perf_counter() - t0:.1f} s (cached after the first run)")
    traces = [samples[i % len(samples)] for i in range(args.recordings)]
    panel = TuningPanel(Tuner(traces))
    sweeps = {"threshold": [0.45, 0.5, 0.6, 0.7, 0.8, 0.4], "k": [1, 3, 8, 16, 32, 5], "stride": [2, 3, 4, 6, 12, 1]}
    worst = 0.0
    for name, values in sweeps.items():
        ms = np.array([1000 * panel.set(**{name: v}) for v in values])
        worst = max(worst, ms.max())
        print(f"{name:>9}: median {np.median(ms):6.1f} ms, p95 {np.percentile(ms, 95):6.1f} ms, max {ms.max():6.1f} ms"
              f" over {len(ms)} changes, {args.recordings} recordings")
    ok = worst <= args.budget_ms
    print(f"worst {worst:.1f} ms: {'within' if ok else 'OVER'} the {args.budget_ms:.0f} ms budget")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
