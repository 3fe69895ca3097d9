"""How long a threshold × K sweep takes over the bundled samples' cached traces (goal: 100 pairs in < 1 s).

    python benchmarks/sweep_speed.py [--cache DIR] [--weights PATH] [--plot heatmap.png]

The traces come from the trace cache (made once with the depth detector at threshold 0.4 if missing); the timed part
is only ``massviz.evaluation.sweep.sweep`` over 10 thresholds × 10 K values, which runs no detector and no model.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cache", default=None, help="trace cache directory (default: massviz's)")
    p.add_argument("--weights", default=None, help="mass-CNN checkpoint (default: $MASSVIZ_WEIGHTS / download)")
    p.add_argument("--plot", default="sweep_heatmap.png", help="heatmap output (default: sweep_heatmap.png)")
    p.add_argument("--repeat", type=int, default=5, help="timed repetitions (default: 5)")
    args = p.parse_args()

    from massviz.app import process
    from massviz.detect import make_detector
    from massviz.evaluation.sweep import best_pair, parse_range, sweep
    from massviz.io.cache import TraceCache
    from massviz.io.checkpoint import load_checkpoint
    from massviz.io.recording import find_recordings, open_recording
    from massviz.io.weights import resolve_weights
    from massviz.views.score_plot import plot_heatmap

    model = load_checkpoint(resolve_weights(args.weights))
    detector = make_detector("depth", 0.4)
    cache = TraceCache(args.cache)
    recs = [open_recording(r) for r in find_recordings(ROOT / "data_samples")]
    t0 = time.perf_counter()
    traces = [process(r, detector, model, k=5, cache=cache) for r in recs]
    print(f"traces of {len(traces)} recordings ready in {time.perf_counter() - t0:.2f} s (cache: {cache.dir})")

    thresholds, ks = parse_range("0.4:0.85:0.05"), parse_range("1:10", int)
    times = []
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        table = sweep(traces, thresholds, ks)
        times.append(time.perf_counter() - t0)
    n = len(thresholds) * len(ks)
    print(f"{n} (threshold, K) pairs over {len(traces)} recordings: best {min(times) * 1000:.1f} ms, "
          f"median {sorted(times)[len(times) // 2] * 1000:.1f} ms ({min(times) / n * 1e6:.0f} µs per pair)")
    best = best_pair(table)
    print(f"best pair: threshold {best['threshold']:.2f}, K {int(best['k'])}: {best['score']:.2f} %")
    plot_heatmap(table, args.plot)
    print(f"wrote {args.plot}")
    return 0 if min(times) < 1.0 else 1


if __name__ == "__main__":
    sys.exit(main())
