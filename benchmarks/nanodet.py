"""NanoDet's pipeline end to end (read, detect, masks, features, predict, select) in frames/s at 1280x720 and
640x480, side by side with Mask R-CNN fp32 in the same run: goals >= 15 frames/s at 1280x720 and >= 25x Mask R-CNN.

The frames are the 8 real RGB-D frames of CCM recording 618 (../shared/ccm_real/618), written at each size as a
massviz folder in a temporary directory (lossless PNGs, resized; intrinsics scaled) and processed by
``massviz.core.pipeline.run`` with the published mass CNN (../shared/weights, else the cached/downloaded one), reading
included. Mask R-CNN runs with random weights (the COCO weights are not available here; its speed does not depend on
them much: the box post-processing keeps few boxes either way) on fewer frames (it takes seconds a frame).

    .venv/bin/python benchmarks/nanodet.py [--rounds 3] [--maskrcnn-frames 3] [--threads N]

NanoDet runs twice per size: with the 3D measure stage observing the run (``massviz.measure3d.stage.MeasureStage``,
Open3D: the chosen detections' measured sizes, once per recording, at its end: a fixed cost that 8 frames amortise
poorly), as ``massviz log`` and ``cloud`` run it, and without it (the stages the goal names, as ``estimate`` runs). Prints frames/s per detector and size, the ratio, and ``uptime``
(the machine is shared: every figure is inflated by other work on it).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
REAL = SHARED / "ccm_real" / "618"
ONNX = SHARED / "detectors" / "nanodet" / "object_detection_nanodet_2022nov.onnx"
WEIGHTS = SHARED / "weights" / "corsmal_visual" / "Encoder_pool_aug_158.torch"


def make_folder(dst: Path, width: int, height: int, n: int | None = None) -> Path:
    """618's frames resized to width x height as a massviz folder (rgb/, depth/, intrinsics.json)."""
    from massviz.io.untrusted import load_calibration_pickle

    (dst / "rgb").mkdir(parents=True)
    (dst / "depth").mkdir()
    names = sorted(p.name for p in (REAL / "rgb").glob("*.png"))[:n]
    for name in names:
        rgb = cv2.imread(str(REAL / "rgb" / name))
        depth = cv2.imread(str(REAL / "depth" / name), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(dst / "rgb" / name), cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA))
        cv2.imwrite(str(dst / "depth" / name), cv2.resize(depth, (width, height), interpolation=cv2.INTER_NEAREST))
    k = load_calibration_pickle(REAL / "calib" / "c3_calib.pickle")[0]["rgb"]
    sx, sy = width / 1280, height / 720
    (dst / "intrinsics.json").write_text(json.dumps({"fx": float(k[0][0]) * sx, "fy": float(k[1][1]) * sy,
                                                     "cx": float(k[0][2]) * sx, "cy": float(k[1][2]) * sy,
                                                     "width": width, "height": height}))
    return dst


def frames_per_second(folder: Path, detector, model, rounds: int, measure: bool = True) -> tuple[float, float, dict]:
    """Best-of-``rounds`` frames/s of ``pipeline.run`` over the folder (after one warm-up frame), and its estimate;
    ``measure``: with the 3D measure stage observing the run (the chosen detections' sizes, once per recording at
    its end), or without it."""
    from massviz.core.pipeline import run
    from massviz.io.recording import open_recording
    from massviz.measure3d.stage import MeasureStage

    def measured_run(rec):
        if not measure:
            return run(rec, detector, model, k=5)
        stage = MeasureStage(rec)
        return stage.finish(run(rec, detector, model, k=5, on_frame=stage.on_frame))

    rec = open_recording(folder)
    run(open_recording(folder), detector, model, k=5, stride=rec.info().num_frames or 8)  # warm-up: loads the models
    best, trace = 0.0, None
    for _ in range(rounds):
        t0 = time.perf_counter()
        trace = measured_run(open_recording(folder))
        best = max(best, len(trace.frames) / (time.perf_counter() - t0))
    stages = {k: v / max(1, len(trace.frames)) * 1000 for k, v in trace.timings.items() if k != "total"}
    stages["measure3d_recording"] = trace.timings.get("measure3d", float("nan")) * 1000
    return best, trace.estimate, stages


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rounds", type=int, default=3, help="NanoDet runs per size; the best counts (default 3)")
    p.add_argument("--maskrcnn-frames", type=int, default=3, help="frames Mask R-CNN runs per size (default 3)")
    p.add_argument("--threads", type=int, help="cv2 and torch threads (default: their own)")
    args = p.parse_args(argv)
    if not REAL.is_dir() or not ONNX.is_file():
        print(f"needs {REAL} and {ONNX}", file=sys.stderr)
        return 2
    import torch

    from massviz.detect.maskrcnn import MaskRCNNDetector
    from massviz.detect.nanodet import NanoDetDetector
    from massviz.io.checkpoint import load_checkpoint
    from massviz.io.weights import resolve_weights

    if args.threads:
        cv2.setNumThreads(args.threads)
        torch.set_num_threads(args.threads)
    model = load_checkpoint(WEIGHTS if WEIGHTS.is_file() else resolve_weights())
    nano = NanoDetDetector(threshold=0.4, weights=ONNX).load()
    mrcnn = MaskRCNNDetector(threshold=0.4, pretrained=False, device="cpu")
    print(f"uptime at start: {subprocess.run(['uptime'], capture_output=True, text=True).stdout.strip()}")
    print(f"cv2 {cv2.__version__} threads {cv2.getNumThreads()}, torch {torch.__version__} threads "
          f"{torch.get_num_threads()}, {os.cpu_count()} CPUs")
    print(f"{'size':>9}  {'detector':>18}  {'frames/s':>8}  {'estimate g':>10}  per-frame ms (read / detect / features "
          f"/ predict / select); 3D measure stage ms per recording")
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for width, height in ((1280, 720), (640, 480)):
            full = make_folder(Path(tmp) / f"n{width}", width, height)
            few = make_folder(Path(tmp) / f"m{width}", width, height, args.maskrcnn_frames + 1)
            for name, det, folder, rounds, measure in (("nanodet", nano, full, args.rounds, True),
                                                       ("nanodet (no 3D)", nano, full, args.rounds, False),
                                                       ("maskrcnn fp32", mrcnn, few, 1, True)):
                fps, est, st = frames_per_second(folder, det, model, rounds, measure)
                rows[(width, name)] = fps
                stages = " / ".join(f"{st.get(k, float('nan')):.0f}" for k in ("read", "detect", "features", "predict",
                                                                               "select"))
                print(f"{width}x{height:<4}  {name:>18}  {fps:8.2f}  {est:10.1f}  {stages}; "
                      f"{st['measure3d_recording']:.0f}", flush=True)
            ratio = rows[(width, "nanodet")] / rows[(width, "maskrcnn fp32")]
            print(f"{'':>9}  NanoDet / Mask R-CNN: {ratio:.0f}x", flush=True)
    print(f"uptime at end: {subprocess.run(['uptime'], capture_output=True, text=True).stdout.strip()}")
    for name in ("nanodet (no 3D)", "nanodet"):
        fps, ratio = rows[(1280, name)], rows[(1280, name)] / rows[(1280, "maskrcnn fp32")]
        print(f"goals, {name}: >= 15 frames/s at 1280x720 ({'met' if fps >= 15 else 'NOT met'}: {fps:.1f}), >= 25x "
              f"Mask R-CNN ({'met' if ratio >= 25 else 'NOT met'}: {ratio:.0f}x)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
