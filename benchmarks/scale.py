"""How the Ray engine of the dataset runner scales, measured side by side with the local engine in one run.

    python benchmarks/scale.py [--weights PATH] [--recordings 200] [--depth-copies 2] [--maskrcnn-frames 2]

Prints three figures:

(a) per-recording scheduling overhead of ``--engine ray`` over ``--engine local``: 200 one-frame recordings with the
    replay detector (one detection per frame, no cache), Ray with 1 worker vs local, run time without start-up,
    divided by the number of recordings (goal <= 30 ms);
(b) speed-up of 2 CPU workers over 1 on the depth detector: the samples (36 frames each) ``--depth-copies`` times,
    Ray 2 workers (1 torch thread each) vs Ray 1 worker (all threads), run time without start-up (goal >= 1.6x);
(c) a projection for the CCM public test set (228 recordings, ~150 frames, Mask R-CNN at the paper's settings) on
    1, 4 and 16 GPUs, from the per-frame costs measured here (Mask R-CNN on this CPU with random weights at the
    paper's input size; read + features + mass CNN from the depth run) and the stated assumptions.

Ray is started once, in this process (2 CPUs on this machine, no dashboard, servers on 127.0.0.1); its start-up and
the workers' start-up are printed apart. Other processes on the machine slow every figure: the load average is
printed with them.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import platform
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "data_samples"
NAMES = ("box_handover", "cup_handover", "glass_handover")
CCM_TEST, CCM_FRAMES, PAPER_GPU_S_PER_REC = 228, 150, 39.0  # paper: 2.7 h per public-test pass, median 39 s/rec


def timings(trace, recording, extra):
    """collect: the stage times and the frame count (small), for the per-frame costs."""
    return {"timings": dict(trace.timings), "frames": len(trace.frames), "detections": len(trace.detections)}


def make_dataset(root: Path, n: int, frames: int) -> list[Path]:
    out = []
    for i in range(n):
        src, dst = SAMPLES / NAMES[i % 3], root / f"rec_{i:04d}"
        for sub in ("rgb", "depth"):
            (dst / sub).mkdir(parents=True)
            for j in range(frames):
                shutil.copyfile(src / sub / f"{(i + j) % 36:06d}.png", dst / sub / f"{j:06d}.png")
        shutil.copyfile(src / "intrinsics.json", dst / "intrinsics.json")
        meta = json.loads((src / "meta.json").read_text())
        meta["id"] = dst.name
        (dst / "meta.json").write_text(json.dumps(meta))
        out.append(dst)
    return out


def tasks_of(paths):
    from massviz.runners.dataset import Task

    return [Task(i, str(p.resolve()), p.name) for i, p in enumerate(paths)]


def timed(tasks, options, engine, **kw):
    from massviz.runners.dataset import run_dataset

    stats: dict = {}
    outcomes = run_dataset(tasks, options, timings, engine=engine, progress=False, on_error="stop", stats=stats, **kw)
    assert all(o.ok for o in outcomes)
    return stats["seconds"] - stats.get("startup_s", 0.0), stats, outcomes


def maskrcnn_frame_cost(n_frames: int) -> dict:
    """Seconds per frame of Mask R-CNN (random weights, torchvision's resize to 800 px as at the paper's setting)
    at 1 thread and at all threads, on the samples' frames."""
    import torch

    from massviz.detect.maskrcnn import MaskRCNNDetector
    from massviz.io.recording import open_recording

    torch.manual_seed(0)
    det = MaskRCNNDetector(threshold=0.4, pretrained=False, device="cpu")
    frames = list(open_recording(SAMPLES / "cup_handover").frames(stride=36 // max(n_frames, 1)))[:n_frames]
    det.detect(frames[0])  # build + warm up
    out = {}
    before = torch.get_num_threads()
    for threads in sorted({1, before}):
        torch.set_num_threads(threads)
        t0 = time.perf_counter()
        for f in frames:
            det.detect(f)
        out[threads] = (time.perf_counter() - t0) / len(frames)
    torch.set_num_threads(before)
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--weights", default=None, help="mass-CNN checkpoint (default: $MASSVIZ_WEIGHTS / download)")
    p.add_argument("--recordings", type=int, default=200, help="(a): number of one-frame recordings (default: 200)")
    p.add_argument("--depth-copies", type=int, default=2, help="(b): copies of the 3 samples (default: 2)")
    p.add_argument("--maskrcnn-frames", type=int, default=2, help="(c): frames timed per thread count (default: 2)")
    args = p.parse_args()

    from massviz.app import PipelineOptions, build_pipeline
    from massviz.runners.dataset import portable_options
    from massviz.runners.ray_engine import LOCAL_ONLY_ENV, release_pools

    cpus = os.cpu_count() or 1
    cpu_name = next((ln.split(":", 1)[1].strip() for ln in Path("/proc/cpuinfo").read_text().splitlines()
                     if ln.startswith("model name")), platform.processor()) if Path("/proc/cpuinfo").exists() else ""
    print(f"machine: {cpus} CPUs ({cpu_name}), {platform.system()} {platform.release()}, Python "
          f"{platform.python_version()}; load average {os.getloadavg()[0]:.1f} at start")
    os.environ.setdefault(LOCAL_ONLY_ENV, "0")
    import ray

    t0 = time.perf_counter()
    ray.init(num_cpus=cpus, include_dashboard=False, logging_level="WARNING")
    print(f"ray {ray.__version__}: local instance started in {time.perf_counter() - t0:.1f} s")
    tmp = Path(tempfile.mkdtemp(prefix="massviz-scale-"))
    try:
        # ---------------------------------------------------------------------------------------------- (a)
        small = make_dataset(tmp / "small", args.recordings, 1)
        replay = tmp / "replay.json"
        replay.write_text(json.dumps({"detections": [{"frame": 0, "box": [200, 60, 300, 200], "score": 0.9,
                                                      "class": "cup"}]}))
        pipeline = build_pipeline(PipelineOptions(detector="replay", replay=str(replay), weights=args.weights,
                                                  no_cache=True, quiet=True))
        options = portable_options(pipeline)
        tasks = tasks_of(small)
        t_local, _, _ = timed(tasks, options, "local", pipeline=pipeline)
        t_ray1, s1, _ = timed(tasks, options, "ray", workers=1)
        t_ray2, s2, _ = timed(tasks, options, "ray", workers=2)
        n = len(tasks)
        over = (t_ray1 - t_local) / n * 1e3
        print(f"\n(a) {n} one-frame recordings, replay detector, no cache: local {t_local:.2f} s "
              f"({t_local / n * 1e3:.1f} ms/rec); ray 1 worker {t_ray1:.2f} s (+ {s1['startup_s']:.1f} s worker "
              f"start-up); ray 2 workers {t_ray2:.2f} s (+ {s2['startup_s']:.1f} s)")
        print(f"    scheduling overhead of the Ray engine: {over:+.1f} ms per recording over local "
              f"(goal <= 30 ms): {'OK' if over <= 30 else 'ABOVE GOAL'}")

        # ---------------------------------------------------------------------------------------------- (b)
        depth_paths = [SAMPLES / NAMES[i % 3] for i in range(3 * args.depth_copies)]
        copies = []
        for i, src in enumerate(depth_paths):  # distinct folders (the same recording twice would be one cache key)
            dst = tmp / "depth" / f"{src.name}_{i}"
            shutil.copytree(src, dst)
            copies.append(dst)
        pipeline = build_pipeline(PipelineOptions(detector="depth", weights=args.weights, no_cache=True, quiet=True))
        options = portable_options(pipeline)
        tasks = tasks_of(copies)
        t_w1, sw1, outs = timed(tasks, options, "ray", workers=1)
        t_w2, sw2, _ = timed(tasks, options, "ray", workers=2)
        speedup = t_w1 / t_w2
        frames = sum(o.value["frames"] for o in outs)
        print(f"\n(b) depth detector, {len(tasks)} recordings x 36 frames ({frames} frames): ray 1 worker "
              f"({sw1['threads']} threads) {t_w1:.2f} s = {frames / t_w1:.1f} frames/s; ray 2 workers "
              f"({sw2['threads']} thread each) {t_w2:.2f} s = {frames / t_w2:.1f} frames/s")
        print(f"    speed-up of 2 CPU workers over 1: {speedup:.2f}x (goal >= 1.6x): "
              f"{'OK' if speedup >= 1.6 else 'BELOW GOAL'}")
        per_frame_rest = statistics.median(
            (o.value["timings"].get("read", 0) + o.value["timings"].get("features", 0) +
             o.value["timings"].get("predict", 0)) / max(o.value["frames"], 1) for o in outs)

        # ---------------------------------------------------------------------------------------------- (c)
        mr = maskrcnn_frame_cost(args.maskrcnn_frames)
        cpu1 = mr[1]
        cpu_all = mr[max(mr)]
        gpu_frame = PAPER_GPU_S_PER_REC / CCM_FRAMES
        per_rec_gpu = CCM_FRAMES * (gpu_frame + per_frame_rest) + max(over, 0) / 1e3
        start = s1["startup_s"]
        print(f"\n(c) measured per frame: Mask R-CNN on this CPU {cpu1:.2f} s (1 thread), {cpu_all:.2f} s "
              f"({max(mr)} threads); read + features + mass CNN {per_frame_rest * 1e3:.1f} ms (depth run, 1 worker)")
        print(f"    projection, CCM public test ({CCM_TEST} recordings x {CCM_FRAMES} frames, Mask R-CNN every frame):")
        print(f"      assumptions: one GPU does Mask R-CNN in {gpu_frame:.2f} s/frame (the paper's median 39 s per "
              f"{CCM_FRAMES}-frame recording on one GPU, taken as the detector's cost); read + features + mass CNN "
              f"stay on the worker's CPU at the cost measured here; recordings take equal time and are spread "
              f"evenly (makespan = ceil({CCM_TEST}/G) recordings per GPU); workers start once ({start:.0f} s "
              f"measured here for the CPU actors, models load in it); storage keeps up; no failures")
        for g in (1, 4, 16):
            total = start + math.ceil(CCM_TEST / g) * per_rec_gpu
            print(f"      {g:2d} GPU(s): {total / 3600:6.2f} h  ({total / 60:7.1f} min)")
        cpu_total = CCM_TEST * CCM_FRAMES * (cpu1 + per_frame_rest) / cpus
        print(f"      this machine's CPUs ({cpus} workers x 1 thread): {cpu_total / 3600:.1f} h")
        print(f"\nload average {os.getloadavg()[0]:.1f} at the end")
    finally:
        release_pools()
        ray.shutdown()
        shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
