"""Mask R-CNN frames per second on a CUDA GPU: batch 1 / 4 / 8 x fp32 / fp16, at 1280x720 (massviz's detector path).

Random weights biased like benchmarks/vs_paper_loop.py scenario (b) (~100 detections a frame, masks pasted in their
boxes), synthetic frames; the first batch of each setting is a warm-up. Without a CUDA GPU it prints why and exits 0:
nothing is measured or faked on a CPU.

    python benchmarks/gpu_throughput.py [--frames 32] [--batches 1 4 8] [--precisions fp32 fp16]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--frames", type=int, default=32, help="frames timed per setting (default: 32)")
    p.add_argument("--batches", type=int, nargs="+", default=[1, 4, 8])
    p.add_argument("--precisions", nargs="+", default=["fp32", "fp16"], choices=["fp32", "bf16", "fp16"])
    args = p.parse_args()
    import torch

    if not torch.cuda.is_available():
        print("gpu_throughput: no CUDA GPU here (torch.cuda.is_available() is False): skipped, nothing measured")
        return 0
    sys.path.insert(0, str(ROOT))
    import numpy as np

    from massviz.core.types import Frame
    from massviz.detect.maskrcnn import MaskRCNNDetector

    sys.path.insert(0, str(ROOT / "benchmarks"))
    from vs_paper_loop import make_weights

    import tempfile

    rng = np.random.default_rng(0)
    frames = [Frame(i, rng.integers(0, 256, (720, 1280, 3), dtype=np.uint8), np.zeros((720, 1280), np.uint16))
              for i in range(max(args.batches))]
    print(f"GPU: {torch.cuda.get_device_name(0)}, torch {torch.__version__}; 1280x720, {args.frames} frames per "
          "setting")
    print(f"{'precision':>9} {'batch':>5} {'frames/s':>9} {'detections/frame':>17}")
    with tempfile.TemporaryDirectory() as tmp:
        weights = make_weights(Path(tmp) / "maskrcnn_b.pth", "b")
        for precision in args.precisions:
            det = MaskRCNNDetector(weights=weights, device="cuda", precision=precision)
            for batch in args.batches:
                group = frames[:batch]
                det.detect_batch(group)  # warm-up (cuDNN autotuning, allocations)
                torch.cuda.synchronize()
                n, dets, t0 = 0, 0, time.perf_counter()
                while n < args.frames:
                    out = det.detect_batch(group)
                    n += len(group)
                    dets += sum(len(d) for d in out)
                torch.cuda.synchronize()
                fps = n / (time.perf_counter() - t0)
                print(f"{precision:>9} {batch:>5} {fps:>9.2f} {dets / n:>17.1f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
