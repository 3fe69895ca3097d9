"""Every cached operation at dataset scale: a synthetic CCM-sized cached dataset of up to 1,140 recordings,
and at 10 / 100 / 1,140 recordings the CLI sweep of 100 (threshold, K) pairs end to end, the in-process sweep, the
Tuner's build time and memory, its slider latency, the failure panel's build time and slider latency, and a warm
``estimate`` of one cached recording.

    MASSVIZ_WEIGHTS=../shared/weights/corsmal_visual/Encoder_pool_aug_158.torch \\
        .venv/bin/python benchmarks/dataset_scale.py [--sizes 10,100,1140] [--out DIR]

How the synthetic dataset is built (cheaply) and how realistic it is:

* The three bundled samples are processed once for real (``massviz sweep data_samples --detector depth``): that run
  leaves their traces, selection indexes, remembered identities and the remembered pipeline in the cache, exactly
  as any first run does. The warm ``estimate`` is timed on one of them (a real recording and a real trace).
* Each synthetic recording ``rec_NNNN`` is a massviz folder in the CCM shape: an ``rgb.mp4`` and 100–300 depth PNGs
  (228,000 frames over 1,140 recordings, as CCM's one view), hard links to the samples' files (no bytes copied:
  the warm path only ``stat``s them, one stat per file as for real files), ``meta.json`` with a random ground-truth
  mass and ``intrinsics.json``. They are never opened cold (the mp4 is not a video).
* Its cache entry is what a run would have written: under the key of its (synthetic) content fingerprint and the
  real depth detector's settings, the full trace file (a copy of a sample's, ~0.2–0.9 MB: smaller than a real
  150-frame trace) and a selection index with 2–10 detections per frame (random d, score above 0.4, prediction,
  box, track): 1.4 M detections in all, the size of a 1,140-recording dataset. Its identity memo (``located/``) is
  written by ``massviz.io.identity.remember`` from the real files, as opening it would.
* So every figure below reads exactly the files a warm command reads on a real dataset of that shape; only the
  detections' values are random (the sweep's cost does not depend on them) and the full trace a Tuner loads for
  the recording on screen is a sample's.

Prints the machine and its load (the machine is shared: figures move with the load).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "data_samples"
SWEEP_ARGS = ("--detector", "depth", "--threshold", "0.4:0.85:0.05", "--k", "1:10", "--cached-only", "--quiet")


def rss_mb() -> float:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def load() -> str:
    return " ".join(f"{v:.1f}" for v in os.getloadavg())


CPU = {"last": 0.0}


def massviz(*args, env, cwd=None) -> tuple[float, subprocess.CompletedProcess]:
    """Run the CLI; (wall seconds, result); ``CPU["last"]``: its CPU seconds (user + system), which the machine's
    load changes far less than the wall time."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    run = subprocess.run([sys.executable, "-m", "massviz", *map(str, args)], capture_output=True, text=True, env=env,
                         cwd=cwd or ROOT)
    s = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    CPU["last"] = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    if run.returncode != 0:
        raise SystemExit(f"massviz {' '.join(map(str, args))} failed:\n{run.stderr[-2000:]}")
    return s, run


def synthetic_index(rng, n_frames: int, width: int = 1280, height: int = 720):
    """Detections of one recording: 2–10 a frame, random but well-formed."""
    from massviz.core.types import Detections

    per = rng.integers(2, 11, n_frames)
    n = int(per.sum())
    frame = np.repeat(np.arange(n_frames), per)
    x1 = rng.integers(0, width - 200, n)
    y1 = rng.integers(0, height - 200, n)
    w, h = rng.integers(20, 200, n), rng.integers(20, 200, n)
    return Detections(frame=frame, xyxy=np.stack([x1, y1, x1 + w, y1 + h], 1),
                      score=rng.uniform(0.41, 1.0, n), class_id=rng.choice([41, 44, 73, 46], n),
                      d=np.round(rng.uniform(300, 2500, n), 2), a=np.round(w / width, 2), b=np.round(h / height, 2),
                      pred=rng.uniform(2, 300, n), track=rng.integers(1, 6, n))


def build(out: Path, cache: Path, n: int, env: dict, seed: int = 0) -> list[Path]:
    """The synthetic dataset (see the module docstring): ``out/rec_NNNN`` x n, cached in ``cache``."""
    from massviz.core.types import RecordingInfo
    from massviz.detect.depth import DepthDetector
    from massviz.io.cache import TraceCache, save_index
    from massviz.io.identity import remember

    seconds, _ = massviz("sweep", SAMPLES, "--detector", "depth", "--threshold", "0.4", "--k", "5", "--quiet",
                         "--cache", cache, env=env)
    print(f"cold sweep of the 3 samples (fills the cache, the indexes, the remembered identities): {seconds:.1f} s")
    tc = TraceCache(cache)
    sample_traces = sorted((cache / "traces").glob("*/t0.4.npz"))
    info = {"name": "depth", **DepthDetector(threshold=0.4).settings()}
    rng = np.random.default_rng(seed)
    frames_dir = out.parent / "_frames"  # copies: a hard link changes its source's ctime, not the samples' then
    frames_dir.mkdir(parents=True, exist_ok=True)
    depth_src = []
    for src in sorted((SAMPLES / "cup_handover" / "depth").glob("*.png")):
        shutil.copyfile(src, frames_dir / src.name)
        depth_src.append(frames_dir / src.name)
    mp4 = frames_dir / "video_stand_in.mp4"
    mp4.write_bytes(b"\0" * 4096)
    base = json.loads((SAMPLES / "cup_handover" / "meta.json").read_text())
    t0 = time.perf_counter()
    recs = []
    for j in range(n):  # 1: every file (linking changes the linked inode's ctime: identities are taken after)
        rec = out / f"rec_{j:04d}"
        frames = 100 + (j * 37) % 201  # 100..300, mean ~200
        (rec / "depth").mkdir(parents=True, exist_ok=True)
        if not (rec / "rgb.mp4").exists():
            os.link(mp4, rec / "rgb.mp4")
        for i in range(frames):
            dst = rec / "depth" / f"{i:06d}.png"
            if not dst.exists():
                os.link(depth_src[i % len(depth_src)], dst)
        meta = {**base, "id": rec.name, "config_id": str(j),
                "container": {**base.get("container", {}), "mass_g": float(np.round(rng.uniform(2, 120), 1))}}
        (rec / "meta.json").write_text(json.dumps(meta))
        shutil.copyfile(SAMPLES / "cup_handover" / "intrinsics.json", rec / "intrinsics.json")
        recs.append((rec, frames, meta))
    print(f"wrote {n} synthetic recordings ({sum(f for _, f, _ in recs)} depth frames) in "
          f"{time.perf_counter() - t0:.1f} s")
    t0 = time.perf_counter()
    paths = []
    weights_id = _weights_id(cache)
    for j, (rec, frames, meta) in enumerate(recs):  # 2: what opening and processing them would have remembered
        files = [rec / "rgb.mp4", *sorted((rec / "depth").glob("*.png"))]
        rinfo = RecordingInfo(id=rec.name, config_id=str(j), path=str(rec), kind="folder", width=1280, height=720,
                              num_frames=frames, fps=30.0, rgb=str(rec / "rgb.mp4"), intrinsics=None, meta=meta)
        stub = SimpleNamespace(path=rec, id=rec.name, kind="folder", config_id=str(j), num_frames=frames, notes=[],
                               input_files=lambda files=files: files, info=lambda rinfo=rinfo: rinfo,
                               fingerprint=lambda hasher=None, j=j, **_: f"synthetic-{seed}-{j:06d}")
        remember(rec, stub, {"files": {str(rec / "meta.json"), str(rec / "intrinsics.json")},
                             "dirs": {str(rec / "depth")}}, cache, False)
        entry = tc.entry(stub, info, 1)
        entry.mkdir(parents=True, exist_ok=True)
        trace_file = entry / "t0.4.npz"
        shutil.copyfile(sample_traces[j % len(sample_traces)], trace_file)
        trace = SimpleNamespace(recording=rinfo, detector=info, detect_threshold=0.4, stride=1,
                                weights_id=weights_id, frames=np.arange(frames), detections=synthetic_index(rng, frames))
        save_index(trace, trace_file)
        paths.append(rec)
    print(f"cached {n} synthetic recordings (identities, trace files, indexes) in {time.perf_counter() - t0:.1f} s")
    return paths


def _weights_id(cache: Path) -> str:
    """The model id the cold run remembered (every cached trace must carry it)."""
    for memo in (cache / "pipelines").glob("*.json"):
        return json.loads(memo.read_text())["resolved"]["weights_id"]
    raise SystemExit("no remembered pipeline in the cache: the cold run did not finish")


def subset(out: Path, paths: list[Path], n: int) -> Path:
    """A dataset root holding the first ``n`` recordings (symbolic links; the full set is ``out`` itself)."""
    root = out.parent / f"first_{n}"
    root.mkdir(exist_ok=True)
    for p in paths[:n]:
        if not (root / p.name).exists():
            (root / p.name).symlink_to(p, target_is_directory=True)
    return root


def measure(root: Path, cache: Path, n: int, env: dict) -> dict:
    from massviz.commands._warm import cached_indexes, locate_all, warm_pipeline
    from massviz.evaluation.sweep import sweep
    from massviz.io.recording import find_recordings
    from massviz.views.widgets import Tuner

    res = {"n": n}
    res["cli_sweep_s"], run = massviz("sweep", root, *SWEEP_ARGS, "--cache", cache, env=env)
    res["cli_sweep_cpu_s"] = CPU["last"]
    assert f"over {n} recordings" in run.stdout, run.stdout[:300]
    args = SimpleNamespace(cache=str(cache), no_cache=False, detector="depth", weights=env["MASSVIZ_WEIGHTS"],
                           detector_weights=None, replay=None, precision="fp32", threshold=0.4, k=1, stride=1)
    t0, c0 = time.perf_counter(), time.process_time()
    pipeline = warm_pipeline(args, 0.4)
    recordings = locate_all(find_recordings(root), cache)
    indexes = cached_indexes(pipeline, recordings, 1, 0.4)
    res["read_indexes_s"] = (time.perf_counter() - t0, time.process_time() - c0)
    thresholds = [round(0.4 + 0.05 * i, 2) for i in range(10)]
    t0, c0 = time.perf_counter(), time.process_time()
    sweep(indexes, thresholds, list(range(1, 11)))
    res["sweep_in_process_s"] = (time.perf_counter() - t0, time.process_time() - c0)
    before = rss_mb()
    t0, c0 = time.perf_counter(), time.process_time()
    tuner = Tuner(indexes, k=5, threshold=0.4)
    tuner.current[0]  # the recording on screen: its full trace and flags
    res["tuner_build_s"] = (time.perf_counter() - t0, time.process_time() - c0)
    res["tuner_mb"] = rss_mb() - before
    res["rss_mb"] = rss_mb()
    lat = []
    try:
        from massviz.views.widgets import TuningPanel

        panel = TuningPanel(tuner)
        for change in ({"k": 6}, {"k": 3}, {"threshold": 0.6}, {"threshold": 0.4}, {"stride": 2}, {"stride": 1}):
            c0 = time.process_time()
            lat.append((1000 * panel.set(**change), 1000 * (time.process_time() - c0)))
        res["slider"] = "panel"
        from massviz.views.widgets import FailurePanel

        loads = []
        t0, c0 = time.perf_counter(), time.process_time()
        failures = FailurePanel(Tuner(indexes, k=5, threshold=0.4))  # ranking over all, the worst one shown
        res["failure_panel_s"] = (time.perf_counter() - t0, time.process_time() - c0)
        for change in ({"k": 6}, {"threshold": 0.6}):
            c0 = time.process_time()
            loads.append((1000 * failures.set(**change), 1000 * (time.process_time() - c0)))
        res["failure_slider_ms"] = loads
    except ImportError:  # no ipywidgets: the Tuner's update and the shown recording, without widgets
        for change in ({"k": 6}, {"k": 3}, {"threshold": 0.6}, {"threshold": 0.4}, {"stride": 2}, {"stride": 1}):
            t0, c0 = time.perf_counter(), time.process_time()
            tuner.update(**change)
            tuner.current[0]
            lat.append((1000 * (time.perf_counter() - t0), 1000 * (time.process_time() - c0)))
        res["slider"] = "tuner"
    res["slider_ms"] = lat
    return res


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", default="10,100,1140", help="dataset sizes (default: 10,100,1140)")
    p.add_argument("--out", help="work folder (default: a temporary one, removed at the end)")
    args = p.parse_args(argv)
    sizes = [int(s) for s in args.sizes.split(",")]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    reference = ROOT.parent / "shared" / "weights" / "corsmal_visual" / "Encoder_pool_aug_158.torch"
    env.setdefault("MASSVIZ_WEIGHTS", str(reference))
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, Python "
          f"{platform.python_version()}, {platform.system()} {platform.release()}; load average {load()}")
    tmp = None if args.out else tempfile.mkdtemp(prefix="massviz-scale-")
    work = Path(args.out or tmp)
    cache, out = work / "cache", work / "dataset" / "all"
    try:
        paths = build(out, cache, max(sizes), env)
        seconds, run = massviz("estimate", SAMPLES / "cup_handover", "--detector", "depth", "--cache", cache,
                               "--out", work / "one.csv", "--quiet", env=env)
        print(f"warm `massviz estimate` of one cached recording (cup_handover), start-up included: {seconds:.2f} s "
              f"wall, {CPU['last']:.2f} s CPU (goal <= 1 s); load {load()}")
        print("every figure: wall (CPU) — the CPU time is what the load changes least")
        print("| recordings | CLI sweep 100 pairs (s) | read indexes (s) | in-process sweep (s) | Tuner build (s) | "
              "Tuner memory (MB) | process RSS (MB) | slider moves (ms) | FailurePanel build (s) | its slider moves "
              "(ms) | load |")
        print("|---|---|---|---|---|---|---|---|---|---|---|")
        for n in sizes:
            root = out if n == len(paths) else subset(out, paths, n)
            r = measure(root, cache, n, env)
            w = lambda v: f"{v[0]:.2f} ({v[1]:.2f})"  # noqa: E731
            print(f"| {n} | {r['cli_sweep_s']:.2f} ({r['cli_sweep_cpu_s']:.2f}) | {w(r['read_indexes_s'])} | "
                  f"{w(r['sweep_in_process_s'])} | {w(r['tuner_build_s'])} | {r['tuner_mb']:.0f} | {r['rss_mb']:.0f} | "
                  f"{', '.join(f'{a:.0f} ({b:.0f})' for a, b in r['slider_ms'])} ({r['slider']}) | "
                  f"{w(r['failure_panel_s']) if 'failure_panel_s' in r else '-'} | "
                  f"{', '.join(f'{a:.0f} ({b:.0f})' for a, b in r.get('failure_slider_ms', []))} | {load()} |",
                  flush=True)
        print(f"peak RSS of this process: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")
    finally:
        if tmp:
            shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
