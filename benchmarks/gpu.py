"""massviz on a GPU against its own detector and the paper's loop, like with like: one table per scenario.

The rules (docs/gpu.md):

* **the same frames in every row**: one recording of ``--frames`` distinct frames (default 150, 1280x720: an mp4
  like CCM's and 16-bit depth PNGs, ``vs_paper_loop.make_recording(distinct=True)``), every row over all of them;
* **the same mode and batch in a row**: the faithful mode (fp32, batch 1) and, on CUDA, the fast one (fp16,
  batch 8); the detector alone runs in the mode and batch of the massviz row next to it;
* **warm and cold as separate columns**: *warm* = frames/s in steady state, everything built, loaded and run once
  before the clock (one fresh process per measurement); *cold* = the wall clock of a fresh process from its start to
  its answer (``python -m massviz estimate`` as a user runs it, imports, CUDA context, model building and the first
  slow calls included), and frames/s from it;
* **the paper's loop timed the same two ways** (``vs_paper_loop.paper_loop`` in a fresh process: cold = that
  process's wall clock; warm = its frames/s after its first frame, imports, models and first kernels done);
* **the estimates checked relatively**: massviz fp32 against the paper's loop within 0.5 %, against the loop with
  its code's defaults (TF32 on, on CUDA) and with TF32 off;
* printed with the table: torch and torchvision versions, the device (GPU name), CPU cores and the load average.

Rows per scenario ((a) 0 and (b) ~100 kept detections a frame, ``vs_paper_loop.make_weights``' random Mask R-CNN
weights biased like a detector): the detector alone (frames decoded beforehand, on the device; on CUDA
``detect_device`` and every kept mask pasted in its box there, on a CPU ``detect_batch`` with its masks), massviz
end to end, the paper's loop. Then the goals (scenario b; measured and reported).

    python benchmarks/gpu.py --json gpu.json                       # CUDA: ~5 minutes
    python benchmarks/gpu.py --device cpu --frames 2 --scenarios b --size 320x180   # a quick run on a CPU
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from vs_paper_loop import DEFAULT_WEIGHTS, HEIGHT, WIDTH, make_recording, make_weights  # noqa: E402

MODES = {"fp32": ("fp32", 1), "fp16": ("fp16", 8), "bf16": ("bf16", 8)}  # precision, batch
LABEL = {"a": "(a) 0 kept / frame", "b": "(b) ~100 kept / frame"}
COLUMNS = ("what", "mode", "batch", "frames", "warm frames/s", "cold s", "cold frames/s", "notes")


def _env() -> dict:
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""),
           "PYTHONUNBUFFERED": "1"}
    env.pop("MASSVIZ_DEBUG", None)
    return env


def _sync(device) -> None:
    import torch

    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()


# --------------------------------------------------------------------------------------------------------- workers
def detector_worker(args) -> dict:
    """The detector alone, warm: every frame decoded and in memory before the clock, one call per batch."""
    import numpy as np
    import torch

    from massviz.core.device import faithful_fp32, resolve_device, upload
    from massviz.detect.maskrcnn import MaskRCNNDetector
    from massviz.io.recording import open_recording

    device = resolve_device(args.device)
    frames = list(open_recording(args.recording).frames())
    det = MaskRCNNDetector(weights=args.detector_weights, device=str(device), precision=args.precision)
    batches = [frames[i:i + args.batch] for i in range(0, len(frames), args.batch)]

    def once(group):
        if device.type != "cuda":
            return det.detect_batch(group) if len(group) > 1 else [det.detect(group[0])]
        dets, masks = det.detect_device(group, upload([f.rgb for f in group], device))
        xyxy = np.concatenate([d.xyxy for d in dets]) if dets else np.zeros((0, 4), np.int32)
        if len(xyxy):  # every kept mask pasted in its box, as the pipeline needs it
            h = int(max((xyxy[:, 3] - xyxy[:, 1]).max(), 1))
            w = int(max((xyxy[:, 2] - xyxy[:, 0]).max(), 1))
            masks.windows(np.arange(len(xyxy)), xyxy, h, w)
        return dets

    with torch.inference_mode(), faithful_fp32(device, args.precision == "fp32"):
        once(batches[0])  # warm-up: kernels, allocations
        _sync(device)
        kept, t0 = 0, time.perf_counter()
        for group in batches:
            kept += sum(len(d) for d in once(group))
        _sync(device)
        seconds = time.perf_counter() - t0
    return {"frames": len(frames), "seconds": seconds, "fps": len(frames) / seconds,
            "kept_per_frame": kept / len(frames)}


def pipeline_worker(args) -> dict:
    """massviz end to end, warm: the pipeline built as ``estimate`` builds it and run once on the first batches
    before the clock; then the whole recording (reading included) on the clock."""
    from massviz.app import PipelineOptions, build_pipeline
    from massviz.core.pipeline import run
    from massviz.io.recording import open_recording

    rec = open_recording(args.recording)
    p = build_pipeline(PipelineOptions(detector="maskrcnn", detector_weights=str(args.detector_weights),
                                       weights=str(args.weights), device=args.device, precision=args.precision,
                                       batch=args.batch, no_cache=True, quiet=True))
    run(rec, p.detector, p.model, batch=p.batch, stride=max(1, rec.num_frames // (2 * p.batch)))  # warm-up
    _sync(args.device)
    t0 = time.perf_counter()
    trace = run(rec, p.detector, p.model, batch=p.batch)
    _sync(args.device)
    seconds = time.perf_counter() - t0
    return {"frames": len(trace.frames), "seconds": seconds, "fps": len(trace.frames) / seconds,
            "estimate": trace.estimate, "compute": trace.compute,
            "ms_per_frame": {k: round(v / len(trace.frames) * 1000, 2) for k, v in trace.timings.items()}}


def paper_worker(args) -> dict:
    """The paper's loop in this fresh process, as its code runs (imports, models, the loop; the parent measures the
    process's wall clock: the cold column). The warm column: frames/s after its first frame (each frame timed by the
    loop), models built and kernels warm by then. ``--tf32 off``: inside ``faithful_fp32`` (IEEE fp32 on CUDA)."""
    import contextlib

    from vs_paper_loop import paper_loop

    from massviz.core.device import faithful_fp32

    times: list[float] = []
    with faithful_fp32(args.device) if args.tf32 == "off" else contextlib.nullcontext():
        estimate, chosen, n, tie = paper_loop(args.recording, args.detector_weights, args.weights,
                                              device=args.device, times=times)
    frames = len(times) - 1
    warm = (frames - 1) / (times[-1] - times[0]) if frames > 1 else None
    return {"frames": frames, "warm_fps": warm, "estimate": estimate, "detections": n, "tie": tie}


def worker(args) -> int:
    out = {"detector": detector_worker, "pipeline": pipeline_worker, "paper": paper_worker}[args.worker](args)
    print("RESULT " + json.dumps(out, default=str))
    return 0


def run_worker(kind: str, **kw) -> dict:
    """A worker in a fresh process; its result, and ``wall``: the process's wall clock from its start."""
    cmd = [sys.executable, __file__, "--worker", kind]
    for k, v in kw.items():
        if v is True:
            cmd.append(f"--{k.replace('_', '-')}")
        elif v is not None and v is not False:
            cmd += [f"--{k.replace('_', '-')}", str(v)]
    t0 = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True, env=_env(), cwd=ROOT)
    wall = time.perf_counter() - t0
    line = next((x for x in reversed(done.stdout.splitlines()) if x.startswith("RESULT ")), None)
    if done.returncode != 0 or line is None:
        return {"error": (done.stderr.strip().splitlines() or ["no output"])[-1][:300], "wall": wall}
    return {**json.loads(line[len("RESULT "):]), "wall": wall}


def run_estimate(rec: Path, detector_weights: Path, mass: Path, device: str, precision: str, batch: int,
                 out: Path) -> dict:
    """``massviz estimate`` as a user runs it (no cache): the process's wall clock, start-up included."""
    import csv

    cmd = [sys.executable, "-m", "massviz", "estimate", str(rec), "--detector", "maskrcnn", "--detector-weights",
           str(detector_weights), "--weights", str(mass), "--device", device, "--precision", precision,
           "--batch", str(batch), "--no-cache", "--quiet", "--out", str(out)]
    t0 = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True, env=_env(), cwd=ROOT)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        return {"error": (done.stderr.strip().splitlines() or ["no output"])[-1][:300], "wall": wall}
    with open(out, newline="") as fh:
        row = next(csv.DictReader(fh))
    return {"wall": wall, "pipeline_seconds": float(row["Execution time"]), "estimate": float(row["Container mass"])}


# ------------------------------------------------------------------------------------------------------------ table
def relative(a, b) -> float | None:
    """|a - b| / |a| (0 when equal, None when either is missing or not estimated)."""
    if a is None or b is None or a < 0 or b < 0:
        return None if a != b else 0.0
    return 0.0 if a == b else abs(a - b) / abs(a) if a else float("inf")


def machine(device) -> dict:
    import torch
    import torchvision

    from massviz.core.device import describe

    return {"device": describe(device), "torch": torch.__version__, "torchvision": torchvision.__version__,
            "cuda": torch.version.cuda, "python": platform.python_version(), "cpu_cores": os.cpu_count(),
            "load_average": [round(x, 2) for x in os.getloadavg()]}


def print_table(label: str, rows: list[dict]) -> None:
    print(f"\nscenario {label}:")
    print("  " + " | ".join(COLUMNS))
    for r in rows:
        cells = [r["what"], r["mode"], str(r["batch"]), str(r["frames"]),
                 f"{r['warm_fps']:.2f}" if r.get("warm_fps") else "-",
                 f"{r['cold_s']:.1f}" if r.get("cold_s") else "-",
                 f"{r['cold_fps']:.2f}" if r.get("cold_fps") else "-", r.get("notes", "")]
        print("  " + " | ".join(cells), flush=True)


def scenario(sc: str, args, device, rec: Path, tmp: Path) -> dict:
    dev = str(device)
    w = make_weights(tmp / f"maskrcnn_{sc}.pth", sc)
    common = {"recording": rec, "detector_weights": w, "weights": args.weights, "device": dev}
    rows: list[dict] = []
    out: dict = {"rows": rows}
    modes = [m for m in args.modes if not (device.type == "cpu" and m == "fp16")]
    for mode in modes:
        precision, batch = MODES[mode]
        batch = args.fast_batch if batch > 1 else 1
        alone = run_worker("detector", precision=precision, batch=batch, **common)
        warm = run_worker("pipeline", precision=precision, batch=batch, **common)
        cold = run_estimate(rec, w, args.weights, dev, precision, batch, tmp / f"{sc}_{mode}.csv")
        ratio = warm["fps"] / alone["fps"] if "fps" in warm and "fps" in alone else None
        rows.append({"what": "detector alone", "mode": mode, "batch": batch, "frames": alone.get("frames", args.frames),
                     "warm_fps": alone.get("fps"), "notes": alone.get("error") or
                     f"{alone['kept_per_frame']:.0f} kept/frame"})
        notes = warm.get("error") or cold.get("error") or (
            f"{warm['estimate']:.3f} g; warm {ratio:.2f}x the detector; cold start-up "
            f"{cold['wall'] - cold['pipeline_seconds']:.1f} s; {warm['compute'].get('device')}")
        rows.append({"what": "massviz end to end", "mode": mode, "batch": batch,
                     "frames": warm.get("frames", args.frames), "warm_fps": warm.get("fps"),
                     "cold_s": cold.get("wall"), "cold_fps": args.frames / cold["wall"] if "wall" in cold else None,
                     "notes": notes, "estimate": warm.get("estimate"), "cold_estimate": cold.get("estimate"),
                     "cold_startup_s": cold["wall"] - cold["pipeline_seconds"] if "error" not in cold else None,
                     "cold_pipeline_s": cold.get("pipeline_seconds"),
                     "vs_detector": ratio, "ms_per_frame": warm.get("ms_per_frame")})
        out.setdefault("massviz", {})[mode] = rows[-1]
    tf32 = ("default", "off") if device.type == "cuda" else ("default",)
    for t in tf32:
        paper = run_worker("paper", tf32=t, **common)
        ok = "error" not in paper
        rows.append({"what": f"paper's loop (TF32 {t})" if device.type == "cuda" else "paper's loop",
                     "mode": "fp32", "batch": 1, "frames": paper.get("frames", args.frames),
                     "warm_fps": paper.get("warm_fps"), "cold_s": paper["wall"] if ok else None,
                     "cold_fps": args.frames / paper["wall"] if ok else None, "estimate": paper.get("estimate"),
                     "notes": paper.get("error") or f"{paper['estimate']:.3f} g, {paper['detections']} detections"})
        out.setdefault("paper", {})[t] = rows[-1]
    mv = out.get("massviz", {}).get("fp32", {})
    checks = {}
    for t, row in out.get("paper", {}).items():
        rel = relative(row.get("estimate"), mv.get("estimate"))
        checks[t] = {"relative": rel, "within_half_percent": rel is not None and rel <= 0.005}
    out["estimate_checks"] = checks
    if mv.get("warm_fps") and out.get("paper", {}).get("default", {}).get("warm_fps"):
        out["vs_paper_warm"] = mv["warm_fps"] / out["paper"]["default"]["warm_fps"]
    if mv.get("cold_fps") and out.get("paper", {}).get("default", {}).get("cold_fps"):
        out["vs_paper_cold"] = mv["cold_fps"] / out["paper"]["default"]["cold_fps"]
    print_table(LABEL[sc], rows)
    for t, c in checks.items():
        print(f"  estimate, massviz fp32 vs the paper's loop (TF32 {t}): "
              + ("not estimated on one side" if c["relative"] is None else
                 f"{100 * c['relative']:.3f} % ({'within' if c['within_half_percent'] else 'OUTSIDE'} 0.5 %)"))
    for key in ("vs_paper_warm", "vs_paper_cold"):
        if key in out:
            print(f"  massviz fp32 / the paper's loop, {key.split('_')[-1]}: {out[key]:.2f}x")
    return out


def goals(b: dict, frames: int) -> list[dict]:
    got = []
    for mode, row in b.get("massviz", {}).items():
        if row.get("vs_detector") is not None:
            got.append((f"warm end to end / detector alone, {mode}", row["vs_detector"], 0.8))
        if row.get("warm_fps") is not None:
            got.append((f"{mode} warm end to end frames/s at ~100 kept/frame", row["warm_fps"],
                        25 if mode == "fp32" else 50))
    fp32 = b.get("massviz", {}).get("fp32", {})
    if fp32.get("cold_pipeline_s") is not None:  # start-up + the pipeline's seconds scaled to 300 frames
        got.append((f"cold estimate of 300 frames, seconds (scaled from {frames})",
                    fp32["cold_startup_s"] + fp32["cold_pipeline_s"] * 300 / max(frames, 1), 20))
    if b.get("vs_paper_warm") is not None:
        got.append(("x the paper's loop, warm against warm (fp32)", b["vs_paper_warm"], 10))
    return [{"goal": g, "measured": m, "target": t, "met": (m <= t) if "seconds" in g else (m >= t)}
            for g, m, t in got]


# ------------------------------------------------------------------------------------------------------------ main
def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cuda", help="cuda (default), cuda:N or cpu")
    p.add_argument("--frames", type=int, default=150, help="distinct frames, every row (default: 150)")
    p.add_argument("--size", default=f"{WIDTH}x{HEIGHT}", help=f"frame size WxH (default: {WIDTH}x{HEIGHT})")
    p.add_argument("--modes", nargs="+", default=["fp32", "fp16"], choices=sorted(MODES),
                   help="modes (default: fp32, the faithful one, batch 1, and fp16, the fast one; fp16 needs CUDA)")
    p.add_argument("--fast-batch", type=int, default=8, help="frames per batch of the bf16/fp16 modes (default: 8)")
    p.add_argument("--scenarios", nargs="+", default=["b", "a"], choices=["a", "b"])
    p.add_argument("--weights", type=Path, default=Path(os.environ.get("MASSVIZ_WEIGHTS", DEFAULT_WEIGHTS)),
                   help="mass-CNN checkpoint (default: $MASSVIZ_WEIGHTS or ../shared/weights/...158.torch)")
    p.add_argument("--json", type=Path, help="also write every figure to this JSON file")
    p.add_argument("--worker", choices=["detector", "pipeline", "paper"], help=argparse.SUPPRESS)
    p.add_argument("--recording", type=Path, help=argparse.SUPPRESS)
    p.add_argument("--detector-weights", type=Path, help=argparse.SUPPRESS)
    p.add_argument("--precision", default="fp32", help=argparse.SUPPRESS)
    p.add_argument("--batch", type=int, default=1, help=argparse.SUPPRESS)
    p.add_argument("--tf32", default="default", choices=["default", "off"], help=argparse.SUPPRESS)
    args = p.parse_args()
    sys.path.insert(0, str(ROOT))
    if args.worker:
        return worker(args)
    if not args.weights.is_file():
        sys.exit(f"gpu.py: mass-CNN weights not found: {args.weights} (pass --weights PATH)")
    try:
        width, height = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        sys.exit(f"gpu.py: --size {args.size}: not WxH")
    if args.frames < 1:
        sys.exit("gpu.py: --frames must be >= 1")
    from massviz.core.device import resolve_device
    from massviz.errors import MassvizError

    try:
        device = resolve_device(args.device)
    except MassvizError as err:
        sys.exit(f"gpu.py: {err}")
    result = {"machine": machine(device), "frames": args.frames, "size": f"{width}x{height}", "scenarios": {}}
    m = result["machine"]
    print(f"massviz benchmark: {m['device']}; torch {m['torch']}, torchvision {m['torchvision']} (CUDA {m['cuda']}); "
          f"Python {m['python']}, {m['cpu_cores']} CPU cores, load average {m['load_average'][0]:.2f}; "
          f"{args.frames} distinct frames {width}x{height} in every row", flush=True)
    with tempfile.TemporaryDirectory(prefix="massviz-bench-") as tmp:
        tmp = Path(tmp)
        rec = make_recording(tmp / "rec", args.frames, distinct=True, width=width, height=height)
        for sc in args.scenarios:
            result["scenarios"][sc] = scenario(sc, args, device, rec, tmp)
    result["goals"] = goals(result["scenarios"].get("b", {}), args.frames)
    result["machine"]["load_average_end"] = [round(x, 2) for x in os.getloadavg()]
    if result["goals"]:
        print("\ngoals (scenario b; measured and reported):")
        for g in result["goals"]:
            print(f"  {g['goal']:<56} {g['measured']:8.2f}  ({'<=' if 'seconds' in g['goal'] else '>='} "
                  f"{g['target']})  {'met' if g['met'] else 'MISSED'}")
    print(f"load average at the end {result['machine']['load_average_end'][0]:.2f}")
    if args.json:
        args.json.write_text(json.dumps(result, indent=1, default=str))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
