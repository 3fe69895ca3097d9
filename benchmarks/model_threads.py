"""The mass CNN with 1 vs 2 torch intra-op threads, side by side in one run: the same patches predicted
alternately with each thread count, so that both see the same load on the shared machine.

    MASSVIZ_WEIGHTS=../shared/weights/corsmal_visual/Encoder_pool_aug_158.torch \\
        .venv/bin/python benchmarks/model_threads.py [--repeat 40] [--patches 6,16]

Prints per thread count and batch size the median and 95th percentile of one ``MassPredictor.predict`` call, the ratio,
whether the predictions are bit-identical across thread counts, and the load average.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeat", type=int, default=40)
    p.add_argument("--patches", default="6,16", help="patches per call (default: 6,16)")
    args = p.parse_args(argv)
    import torch  # after the arguments: --help does not wait for it

    from massviz.io.checkpoint import load_checkpoint
    from massviz.io.weights import resolve_weights

    reference = ROOT.parent / "shared" / "weights" / "corsmal_visual" / "Encoder_pool_aug_158.torch"
    weights = os.environ.get("MASSVIZ_WEIGHTS") or str(reference)
    model = load_checkpoint(resolve_weights(weights))
    model.threads = 0  # predict with torch's setting, the one set below
    rng = np.random.default_rng(0)
    print(f"{os.cpu_count()} CPUs, torch {torch.__version__}, load average at the start "
          f"{' '.join(f'{v:.1f}' for v in os.getloadavg())}")
    for n in (int(v) for v in args.patches.split(",")):
        patches = [rng.integers(0, 255, (int(rng.integers(40, 200)), int(rng.integers(40, 200)), 3), np.uint8)
                   for _ in range(n)]
        feats = np.stack([rng.uniform(0.05, 0.3, n), rng.uniform(0.1, 0.5, n), rng.uniform(400, 1500, n)], 1)
        times = {1: [], 2: []}
        preds = {}
        for _ in range(2):  # warm-up
            for t in times:
                torch.set_num_threads(t)
                preds[t] = model.predict(patches, feats)
        for r in range(args.repeat):
            for t in (times if r % 2 == 0 else reversed(list(times))):  # alternate who goes first
                torch.set_num_threads(t)
                t0 = time.perf_counter()
                preds[t] = model.predict(patches, feats)
                times[t].append(1000 * (time.perf_counter() - t0))
        stats = {t: (statistics.median(v), float(np.percentile(v, 95))) for t, v in times.items()}
        same = np.array_equal(preds[1], preds[2])
        print(f"{n} patches: 1 thread {stats[1][0]:.1f} ms median (p95 {stats[1][1]:.1f}); 2 threads "
              f"{stats[2][0]:.1f} ms (p95 {stats[2][1]:.1f}); 2 threads / 1 thread = {stats[2][0] / stats[1][0]:.2f}; "
              f"predictions bit-identical: {same} (max difference {np.abs(preds[1] - preds[2]).max():.2e} g)")
    print(f"load average at the end {' '.join(f'{v:.1f}' for v in os.getloadavg())}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
