"""`massviz --help` start-up time of this checkout against another revision, measured alternately in one run.

    python benchmarks/startup.py --before 43ae703 --runs 10
    python benchmarks/startup.py --before bab6251 --runs 5 --estimate

``--estimate`` also times the start-up of a command that runs the mass CNN: ``massviz estimate`` of one frame of
the bundled ``box_handover`` (depth detector, no cache; weights from $MASSVIZ_WEIGHTS or ../shared), i.e. imports,
weights, one frame and the CSV.

The other revision is checked out into a temporary git worktree and imported through PYTHONPATH, so both use the
same interpreter and packages; the runs alternate so that machine noise hits both alike. Prints the median of each
and their ratio.
"""
from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def time_massviz(src: Path, cwd: Path, args) -> float:
    """Wall seconds of ``python -m massviz ARGS`` importing massviz from ``src``."""
    # cwd outside both checkouts: `python -m` puts the working directory first on sys.path
    env = {**os.environ, "PYTHONPATH": str(src)}
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "massviz", *map(str, args)], env=env, check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=cwd)
    return time.perf_counter() - t0


def estimate_args(tmp: Path) -> list:
    weights = os.environ.get("MASSVIZ_WEIGHTS") or (ROOT.parent / "shared" / "weights" / "corsmal_visual"
                                                    / "Encoder_pool_aug_158.torch")
    return ["estimate", ROOT / "data_samples" / "box_handover", "--detector", "depth", "--stride", "1000",
            "--no-cache", "--quiet", "--weights", weights, "--out", tmp / "one.csv"]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--before", required=True, help="git revision to compare with (e.g. the last release)")
    p.add_argument("--runs", type=int, default=10)
    p.add_argument("--estimate", action="store_true",
                   help="also time `massviz estimate` of one frame (start-up of a command running the mass CNN)")
    args = p.parse_args(argv)
    cases = {"massviz --help": ("--help",)}
    with tempfile.TemporaryDirectory() as tmp:
        old = Path(tmp) / "before"
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(old), args.before], check=True,
                       capture_output=True)
        if args.estimate:
            cases["massviz estimate, one frame"] = estimate_args(Path(tmp))
        try:
            times = {(name, which): [] for name in cases for which in ("before", "after")}
            for _ in range(args.runs):
                for name, case in cases.items():
                    times[name, "before"].append(time_massviz(old, Path(tmp), case))
                    times[name, "after"].append(time_massviz(ROOT, Path(tmp), case))
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(old)], check=False,
                           capture_output=True)
    for name in cases:
        before, after = statistics.median(times[name, "before"]), statistics.median(times[name, "after"])
        print(f"{name}, median of {args.runs}: before ({args.before}) {before:.3f} s, after {after:.3f} s, "
              f"{before / after:.2f}x faster")
    return 0


if __name__ == "__main__":
    sys.exit(main())
