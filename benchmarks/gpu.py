"""massviz on a GPU, end to end, against its own detector and the paper's loop: one table, in about 5 minutes.

For scenarios (a) no detection kept (100 boxes a frame above torchvision's 0.05, none above 0.4) and (b) ~100 kept
detections a frame (``vs_paper_loop.py``'s random Mask R-CNN weights biased like a detector), on a 1280x720 recording
made here (an mp4 like CCM's and 16-bit depth PNGs, ``vs_paper_loop.make_recording``):

* **detector alone**: ``MaskRCNNDetector.detect_device`` on frames already on the device (the forward, the boxes
  copied back, the masks left there), per mode and batch;
* **massviz end to end**: ``python -m massviz estimate`` from the mp4 and the PNGs, no cache, in the faithful mode
  (fp32, its default batch) and the fast mode (fp16, batch 8): frames/s of the pipeline (the CSV's execution
  time), the process's wall time and its start-up (wall time - pipeline time);
* **the paper's loop** on the same device (``vs_paper_loop.paper_loop``: its model and frames moved there), on the
  first ``--paper-frames`` frames, with massviz fp32 on the same frames for the equal-estimate check;
* **the CPU path**: massviz fp32 on the CPU on the first ``--cpu-frames`` frames, against the same run on the
  device (fp32 estimates within 0.5 %).

Then the goals: end to end >= 0.8x the detector alone in the same mode and batch, faithful fp32 >= 25 frames/s and
the fast mode >= 50 frames/s at ~100 detections a frame, >= 15x the paper's loop. It needs only what a CUDA image
has (torch, torchvision, OpenCV, numpy, Pillow, tqdm; no Open3D or Rerun). ``--device cpu`` runs the same steps on
the CPU (small ``--frames``), so the script is known to run unchanged where no GPU is at hand.

    python benchmarks/gpu.py --json gpu.json                   # CUDA, 150 frames
    python benchmarks/gpu.py --device cpu --frames 2 --paper-frames 2 --cpu-frames 0 --modes fp32 --scenarios b
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from vs_paper_loop import DEFAULT_WEIGHTS, HEIGHT, WIDTH, make_recording, make_weights  # noqa: E402

MODES = {"fp32": ("fp32", None), "fp16": ("fp16", 8), "bf16": ("bf16", 8)}  # precision, batch (None: default)
LABEL = {"a": "(a) 0 kept / frame", "b": "(b) ~100 kept / frame"}


def _env() -> dict:
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""),
           "PYTHONUNBUFFERED": "1"}
    env.pop("MASSVIZ_DEBUG", None)
    return env


# --------------------------------------------------------------------------------------------------------- workers
def detector_worker(args) -> dict:
    import numpy as np
    import torch

    from massviz.core.device import faithful_fp32, resolve_device, upload
    from massviz.detect.maskrcnn import MaskRCNNDetector
    from massviz.io.recording import open_recording

    device = resolve_device(args.device)
    rec = open_recording(args.recording)
    frames = list(rec.frames(indices=list(range(min(args.batch, rec.num_frames)))))
    while len(frames) < args.batch:
        frames.append(frames[len(frames) % max(1, rec.num_frames)])
    det = MaskRCNNDetector(weights=args.detector_weights, device=str(device), precision=args.precision)
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    rgb = upload([f.rgb for f in frames], device)  # the frames already on the device: the detector's time alone
    with faithful_fp32(device, args.precision == "fp32"):
        det.detect_device(frames, rgb)  # warm-up: kernels, allocations
        sync()
        n, kept, t0 = 0, 0, time.perf_counter()
        while n < args.frames:
            out, masks = det.detect_device(frames, rgb)  # the forward, boxes copied back, masks left there
            n += len(frames)
            kept += sum(len(d) for d in out)
        sync()
        seconds = time.perf_counter() - t0
    return {"frames": n, "seconds": seconds, "fps": n / seconds, "kept_per_frame": kept / n,
            "device": str(device), "batch": args.batch, "precision": args.precision,
            "peak_gpu_mb": (torch.cuda.max_memory_allocated() / 2**20) if device.type == "cuda" else None,
            "mean_box_area": float(np.mean([((d.xyxy[:, 2] - d.xyxy[:, 0]) * (d.xyxy[:, 3] - d.xyxy[:, 1])).mean()
                                            for d in out if len(d)])) if kept else 0.0}


def paper_worker(args) -> dict:
    import torch
    from vs_paper_loop import paper_loop

    t0 = time.perf_counter()
    estimate, chosen, n, tie = paper_loop(args.recording, args.detector_weights, args.weights, device=args.device)
    if args.device.startswith("cuda"):
        torch.cuda.synchronize()
    return {"seconds": time.perf_counter() - t0, "estimate": estimate, "chosen": chosen, "detections": n, "tie": tie}


def stages_worker(args) -> dict:
    """The pipeline in this process on the recording (as ``estimate`` builds it, no cache): seconds per stage."""
    import numpy as np

    from massviz.app import PipelineOptions, build_pipeline
    from massviz.io.recording import open_recording

    options = PipelineOptions(detector="maskrcnn", detector_weights=str(args.detector_weights),
                              weights=str(args.weights), device=args.device, precision=args.precision,
                              batch=args.batch or None, no_cache=True, quiet=True)
    trace = build_pipeline(options).process(open_recording(args.recording))
    per_frame = {k: float(np.median(v)) * 1000 for k, v in trace.frame_timings.items()}
    return {"timings_s": trace.timings, "median_ms_per_frame": per_frame, "compute": trace.compute,
            "estimate": trace.estimate, "frames": len(trace.frames)}


def variants(args) -> dict:
    """The pipeline in one process on scenario (b), per mode, with the stage in a thread of its own or not
    (frames/s of each: ``run``'s default on CUDA, ``overlap``, was chosen from these)."""
    from massviz.app import PipelineOptions, build_pipeline
    from massviz.core.pipeline import run
    from massviz.io.recording import open_recording

    rec = open_recording(args.recording)
    out = {}
    for mode in args.modes:
        precision, batch = MODES[mode]
        batch = args.fast_batch if batch else None
        p = build_pipeline(PipelineOptions(detector="maskrcnn", detector_weights=str(args.detector_weights),
                                           weights=str(args.weights), device=args.device, precision=precision,
                                           batch=batch, no_cache=True, quiet=True))
        run(rec, p.detector, p.model, batch=p.batch, stride=max(1, rec.num_frames // 8))  # warm-up
        for overlap in (True, False):
            t0 = time.perf_counter()
            trace = run(rec, p.detector, p.model, batch=p.batch, overlap=overlap)
            fps = len(trace.frames) / (time.perf_counter() - t0)
            key = f"{mode} b{p.batch} overlap={overlap}"
            out[key] = {"fps": fps, "estimate": trace.estimate,
                        "ms_per_frame": {k: round(v / len(trace.frames) * 1000, 2) for k, v in trace.timings.items()}}
            print(f"  {key:<30} {fps:7.1f} frames/s  {out[key]['ms_per_frame']}", flush=True)
    return out


def worker(args) -> int:
    out = {"detector": detector_worker, "paper": paper_worker, "stages": stages_worker}[args.worker](args)
    print("RESULT " + json.dumps(out))
    return 0


def run_worker(kind: str, **kw) -> dict:
    cmd = [sys.executable, __file__, "--worker", kind]
    for k, v in kw.items():
        cmd += [f"--{k.replace('_', '-')}", str(v)]
    done = subprocess.run(cmd, capture_output=True, text=True, env=_env(), cwd=ROOT)
    line = next((x for x in reversed(done.stdout.splitlines()) if x.startswith("RESULT ")), None)
    if done.returncode != 0 or line is None:
        return {"error": (done.stderr.strip().splitlines() or ["no output"])[-1][:300]}
    return json.loads(line[len("RESULT "):])


def run_estimate(rec: Path, detector_weights: Path, mass: Path, device: str, precision: str, batch, out: Path) -> dict:
    """``massviz estimate`` as a user runs it (no cache): pipeline seconds from the CSV, wall time of the process."""
    cmd = [sys.executable, "-m", "massviz", "estimate", str(rec), "--detector", "maskrcnn", "--detector-weights",
           str(detector_weights), "--weights", str(mass), "--device", device, "--precision", precision,
           "--no-cache", "--quiet", "--exact", "--out", str(out)]
    if batch:
        cmd += ["--batch", str(batch)]
    t0 = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True, env=_env(), cwd=ROOT)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        return {"error": (done.stderr.strip().splitlines() or ["no output"])[-1][:300], "wall": wall}
    with open(out, newline="") as fh:
        row = next(csv.DictReader(fh))
    seconds = float(row["Execution time"])
    return {"seconds": seconds, "wall": wall, "startup": wall - seconds, "estimate": float(row["Container mass"]),
            "stderr_tail": done.stderr.strip().splitlines()[-1:]}


def startup_seconds() -> dict:
    """Wall time of ``python -m massviz --help`` and of importing what ``estimate`` with Mask R-CNN imports."""
    out = {}
    for name, code in (("massviz --help", None),
                       ("import torch, torchvision detection, massviz pipeline",
                        "import torch, torchvision.models.detection, massviz.core.pipeline, massviz.detect.maskrcnn")):
        cmd = [sys.executable, "-m", "massviz", "--help"] if code is None else [sys.executable, "-c", code]
        t0 = time.perf_counter()
        subprocess.run(cmd, capture_output=True, env=_env(), cwd=ROOT, check=False)
        out[name] = time.perf_counter() - t0
    return out


# ------------------------------------------------------------------------------------------------------------ main
def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cuda", help="cuda (default), cuda:N or cpu")
    p.add_argument("--frames", type=int, default=150, help="frames of the end-to-end recording (default: 150)")
    p.add_argument("--paper-frames", type=int, default=60,
                   help="frames the paper's loop and its massviz twin run on (default: 60; 0 skips them)")
    p.add_argument("--cpu-frames", type=int, default=6,
                   help="frames of the CPU-vs-device fp32 check (default: 6; 0 skips it)")
    p.add_argument("--modes", nargs="+", default=["fp32", "fp16"], choices=sorted(MODES),
                   help="end-to-end modes (default: fp32, the faithful one, and fp16, the fast one)")
    p.add_argument("--fast-batch", type=int, default=8, help="frames per batch of the bf16/fp16 modes (default: 8)")
    p.add_argument("--scenarios", nargs="+", default=["b", "a"], choices=["a", "b"])
    p.add_argument("--weights", type=Path, default=Path(os.environ.get("MASSVIZ_WEIGHTS", DEFAULT_WEIGHTS)),
                   help="mass-CNN checkpoint (default: $MASSVIZ_WEIGHTS or ../shared/weights/...158.torch)")
    p.add_argument("--json", type=Path, help="also write every figure to this JSON file")
    p.add_argument("--variants", action="store_true",
                   help="instead: scenario (b) in one process, the stage in its own thread or not (how run's "
                   "default on CUDA was chosen)")
    p.add_argument("--worker", choices=["detector", "paper", "stages"], help=argparse.SUPPRESS)
    p.add_argument("--recording", type=Path, help=argparse.SUPPRESS)
    p.add_argument("--detector-weights", type=Path, help=argparse.SUPPRESS)
    p.add_argument("--precision", default="fp32", help=argparse.SUPPRESS)
    p.add_argument("--batch", type=int, default=1, help=argparse.SUPPRESS)
    args = p.parse_args()
    sys.path.insert(0, str(ROOT))
    if args.worker:
        return worker(args)
    if args.variants:
        from vs_paper_loop import make_recording as make
        from vs_paper_loop import make_weights as weights_for

        with tempfile.TemporaryDirectory(prefix="massviz-gpu-") as tmp:
            args.recording = make(Path(tmp) / "rec", args.frames)
            args.detector_weights = weights_for(Path(tmp) / "w.pth", "b")
            print(f"variants, scenario (b), {args.frames} frames:", flush=True)
            result = variants(args)
        if args.json:
            args.json.write_text(json.dumps(result, indent=1))
        return 0
    if not args.weights.is_file():
        sys.exit(f"gpu.py: mass-CNN weights not found: {args.weights} (pass --weights PATH)")
    import torch

    from massviz.core.device import describe, resolve_device

    device = resolve_device(args.device)
    dev = str(device)
    result = {"machine": {"device": describe(device), "torch": torch.__version__, "cuda": torch.version.cuda,
                          "cpu_cores": os.cpu_count(), "load_average": os.getloadavg()[0],
                          "frames": args.frames, "size": f"{WIDTH}x{HEIGHT}"},
              "startup_s": startup_seconds(), "scenarios": {}}
    print(f"massviz GPU benchmark: {result['machine']['device']}, torch {torch.__version__} (CUDA "
          f"{torch.version.cuda}), {os.cpu_count()} CPU cores, load average {os.getloadavg()[0]:.1f}; "
          f"{args.frames} frames {WIDTH}x{HEIGHT}", flush=True)
    for name, s in result["startup_s"].items():
        print(f"  start-up: {name}: {s:.1f} s", flush=True)
    with tempfile.TemporaryDirectory(prefix="massviz-gpu-") as tmp:
        tmp = Path(tmp)
        t0 = time.perf_counter()
        rec = make_recording(tmp / "rec", args.frames)
        short = make_recording(tmp / "short", args.paper_frames) if args.paper_frames else None
        cpu_rec = make_recording(tmp / "cpu", args.cpu_frames) if args.cpu_frames else None
        print(f"  recordings made in {time.perf_counter() - t0:.1f} s", flush=True)
        for sc in args.scenarios:
            w = make_weights(tmp / f"maskrcnn_{sc}.pth", sc)
            rows, r = [], {"detector": {}, "end_to_end": {}}
            for mode in args.modes:
                precision, batch = MODES[mode]
                batch = args.fast_batch if batch else None
                if device.type == "cpu" and precision == "fp16":
                    continue
                e2e = run_estimate(rec, w, args.weights, dev, precision, batch, tmp / f"{sc}_{mode}.csv")
                b = batch or 1  # the detector's default: 1 in fp32 (faithful), 8 in bf16/fp16 on CUDA
                alone = run_worker("detector", device=dev, recording=rec, detector_weights=w, precision=precision,
                                   batch=b, frames=max(4 * b, min(args.frames, 64)), weights=args.weights)
                fps = args.frames / e2e["seconds"] if "seconds" in e2e else None
                ratio = fps / alone["fps"] if fps and "fps" in alone else None
                e2e.update(batch=b, fps=fps, vs_detector=ratio)
                r["end_to_end"][mode], r["detector"][mode] = e2e, alone
                if sc == "b":  # where the time goes, per stage (a run in one process, as estimate builds it)
                    st = run_worker("stages", device=dev, recording=rec, detector_weights=w, precision=precision,
                                    batch=batch or 0, weights=args.weights)
                    r.setdefault("stages", {})[mode] = st
                    if "median_ms_per_frame" in st:
                        print(f"  [{sc} {mode}] stages, median ms/frame: " + ", ".join(
                            f"{k} {v:.1f}" for k, v in st["median_ms_per_frame"].items()) +
                              f"; total {st['timings_s'].get('total', 0):.1f} s; {st['compute']}", flush=True)
                    else:
                        print(f"  [{sc} {mode}] stages: {st.get('error')}", flush=True)
                rows.append((f"detector alone {mode} b{b}", alone.get("fps"), alone.get("error") or
                             f"{alone.get('kept_per_frame', 0):.0f} kept/frame"))
                rows.append((f"massviz estimate {mode} b{b}", fps, e2e.get("error") or
                             f"{e2e['estimate']:.2f} g, wall {e2e['wall']:.1f} s, start-up {e2e['startup']:.1f} s, "
                             f"{ratio:.2f}x the detector" if fps and ratio else e2e.get("error", "")))
            if short is not None:
                paper = run_worker("paper", device=dev, recording=short, detector_weights=w, weights=args.weights)
                twin = run_estimate(short, w, args.weights, dev, "fp32", None, tmp / f"{sc}_short.csv")
                r["paper"], r["paper_twin"] = paper, twin
                pfps = args.paper_frames / paper["seconds"] if "seconds" in paper else None
                mfps = args.paper_frames / twin["seconds"] if "seconds" in twin else None
                same = ("estimate" in paper and "estimate" in twin and
                        (abs(paper["estimate"] - twin["estimate"]) < 0.01 or paper["estimate"] == twin["estimate"]
                         == -1 or (paper.get("tie") and abs(paper["tie"]["estimate"] - twin["estimate"]) < 0.01)))
                r["paper_equal"] = bool(same)
                rows.append((f"paper loop ({args.paper_frames} frames)", pfps, paper.get("error") or
                             f"{paper['estimate']:.2f} g"))
                rows.append((f"massviz fp32 same {args.paper_frames} frames", mfps, twin.get("error") or
                             f"{twin['estimate']:.2f} g; estimates {'EQUAL' if same else 'DIFFER'}; "
                             f"{(mfps / pfps) if pfps and mfps else float('nan'):.1f}x the paper's loop"))
                r["vs_paper"] = (mfps / pfps) if pfps and mfps else None
            if cpu_rec is not None and device.type != "cpu":
                on_cpu = run_estimate(cpu_rec, w, args.weights, "cpu", "fp32", None, tmp / f"{sc}_cpu.csv")
                on_dev = run_estimate(cpu_rec, w, args.weights, dev, "fp32", None, tmp / f"{sc}_cpu_dev.csv")
                r["cpu_check"] = {"cpu": on_cpu, "device": on_dev}
                if "estimate" in on_cpu and "estimate" in on_dev:
                    a, b = on_cpu["estimate"], on_dev["estimate"]
                    rel = 0.0 if a == b else abs(a - b) / abs(a) if a > 0 else float("inf")
                    r["cpu_check"]["relative_difference"] = rel
                    rows.append((f"CPU vs {device.type} fp32 ({args.cpu_frames} frames)", None,
                                 f"{a:.3f} g vs {b:.3f} g: {100 * rel:.3f} % "
                                 f"({'within' if rel <= 0.005 else 'OUTSIDE'} 0.5 %)"))
                else:
                    rows.append((f"CPU vs {device.type} fp32", None, on_cpu.get("error") or on_dev.get("error")))
            result["scenarios"][sc] = r
            print(f"\nscenario {LABEL[sc]}:", flush=True)
            print(f"  {'what':<36} {'frames/s':>9}  notes")
            for what, fps, note in rows:
                print(f"  {what:<36} {('%.1f' % fps) if fps else '-':>9}  {note}", flush=True)
    b = result["scenarios"].get("b", {})
    goals = []
    for mode, e2e in b.get("end_to_end", {}).items():
        if e2e.get("vs_detector") is not None:
            goals.append((f"end to end / detector alone, {mode}", e2e["vs_detector"], 0.8))
        if e2e.get("fps") is not None:
            goals.append((f"{mode} end to end frames/s at ~100 kept/frame", e2e["fps"], 25 if mode == "fp32" else 50))
    if b.get("vs_paper") is not None:
        goals.append(("x the paper's loop on the same device (fp32)", b["vs_paper"], 15))
    result["goals"] = [{"goal": g, "measured": m, "target": t, "met": m >= t} for g, m, t in goals]
    print("\ngoals (scenario b):")
    for g in result["goals"]:
        print(f"  {g['goal']:<48} {g['measured']:8.2f}  (>= {g['target']})  {'met' if g['met'] else 'MISSED'}")
    if args.json:
        args.json.write_text(json.dumps(result, indent=1, default=str))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
