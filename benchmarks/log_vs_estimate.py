"""`massviz log` against `massviz estimate` on an uncached 1280x720 recording, for this checkout and another revision.

    python benchmarks/log_vs_estimate.py --before 4a221be --runs 2 [--cache cold]

The recording is assembled in a temporary folder from the 8 real frames of ``../shared/ccm_real/618`` (1280x720 RGB
PNG + 16-bit depth PNG, the frontal camera's intrinsics from its calibration pickle), repeated to ``--frames``
frames. Both commands run with ``--detector depth --no-cache`` (nothing comes from the trace cache; ``--cache cold``:
with a new, empty trace cache per run, which keys the trace by the frames' content) and the paper's weights from
``../shared``; ``log`` writes an .rrd. The other revision is checked out into a temporary git worktree
and run through PYTHONPATH, so both use the same interpreter and packages; runs alternate (before/after,
estimate/log) so that machine noise hits all alike. Prints the median wall time of each and log / estimate.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("MASSVIZ_SHARED", ROOT.parent / "shared"))
SOURCE = SHARED / "ccm_real" / "618"
WEIGHTS = SHARED / "weights" / "corsmal_visual" / "Encoder_pool_aug_158.torch"


def make_recording(folder: Path, frames: int) -> Path:
    """A massviz folder recording of ``frames`` frames: 618's 8 real frames, repeated."""
    sys.path.insert(0, str(ROOT))
    from massviz.io.formats.ccm import intrinsics_ccm  # the CCM calibration reader (restricted unpickler)

    sources = sorted((SOURCE / "rgb").glob("*.png"))
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    for i in range(frames):
        src = sources[i % len(sources)]
        shutil.copyfile(src, folder / "rgb" / f"{i:06d}.png")
        shutil.copyfile(SOURCE / "depth" / src.name, folder / "depth" / f"{i:06d}.png")
    intr = intrinsics_ccm(SOURCE / "calib" / "c3_calib.pickle", 1280, 720)
    (folder / "intrinsics.json").write_text(json.dumps(intr.to_dict()))
    return folder


def run(src: Path, args: list, cwd: Path) -> float:
    env = {**os.environ, "PYTHONPATH": str(src)}
    env.pop("MASSVIZ_DEBUG", None)
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "massviz", *map(str, args)], env=env, cwd=cwd, capture_output=True,
                       text=True)
    seconds = time.perf_counter() - t0
    if r.returncode != 0:
        sys.exit(f"{src}: massviz {' '.join(map(str, args[:2]))} failed:\n{r.stderr}")
    return seconds


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--before", default="4a221be", help="git revision to compare with (default: 4a221be)")
    ap.add_argument("--runs", type=int, default=2, help="runs of each command per revision (default: 2)")
    ap.add_argument("--frames", type=int, default=32, help="frames of the recording (default: 32)")
    ap.add_argument("--cache", choices=["none", "cold"], default="none",
                    help="none (default): --no-cache; cold: a new, empty --cache folder for every run")
    args = ap.parse_args()
    for need in (SOURCE, WEIGHTS):
        if not need.exists():
            sys.exit(f"missing {need} (the benchmark reads ../shared in place)")
    with tempfile.TemporaryDirectory(prefix="massviz-logbench-") as tmp:
        tmp = Path(tmp)
        rec = make_recording(tmp / "rec618x", args.frames)
        before = tmp / "before"
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(before), args.before],
                       check=True, capture_output=True)
        try:
            common = ["--detector", "depth", "--weights", WEIGHTS, "--quiet"]
            commands = {"estimate": ["estimate", rec, "--out", tmp / "out.csv", *common],
                        "log": ["log", rec, "--rrd", tmp / "out.rrd", *common]}
            times: dict[tuple[str, str], list[float]] = {}
            for n in range(args.runs):
                for name, src in (("before", before), ("after", ROOT)):
                    for cmd, argv in commands.items():
                        cache = ["--no-cache"] if args.cache == "none" else ["--cache", tmp / f"cache-{name}-{cmd}-{n}"]
                        times.setdefault((name, cmd), []).append(run(src, [*argv, *cache], tmp))
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(before)],
                           capture_output=True)
    cache = "--no-cache" if args.cache == "none" else "a cold --cache"
    print(f"recording: {args.frames} frames of 1280x720 (ccm_real/618 repeated); --detector depth, {cache}; "
          f"{args.runs} runs each, median wall seconds; {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f}")
    print(f"{'revision':<10} {'estimate':>9} {'log':>9} {'log/estimate':>13}")
    for name, label in (("before", args.before), ("after", "this")):
        est = statistics.median(times[(name, "estimate")])
        log = statistics.median(times[(name, "log")])
        print(f"{label:<10} {est:9.1f} {log:9.1f} {log / est:13.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
