"""`massviz --help` start-up time of this checkout against another revision, measured alternately in one run.

    python benchmarks/startup.py --before 43ae703 --runs 10

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


def time_help(src: Path, cwd: Path) -> float:
    # cwd outside both checkouts: `python -m` puts the working directory first on sys.path
    env = {**os.environ, "PYTHONPATH": str(src)}
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "massviz", "--help"], env=env, check=True, stdout=subprocess.DEVNULL,
                   cwd=cwd)
    return time.perf_counter() - t0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--before", required=True, help="git revision to compare with (e.g. the last release)")
    p.add_argument("--runs", type=int, default=10)
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        old = Path(tmp) / "before"
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(old), args.before], check=True,
                       capture_output=True)
        try:
            times = {"before": [], "after": []}
            for _ in range(args.runs):
                times["before"].append(time_help(old, Path(tmp)))
                times["after"].append(time_help(ROOT, Path(tmp)))
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(old)], check=False,
                           capture_output=True)
    before, after = statistics.median(times["before"]), statistics.median(times["after"])
    print(f"massviz --help, median of {args.runs}: before ({args.before}) {before:.3f} s, after {after:.3f} s, "
          f"{before / after:.2f}x faster")
    return 0


if __name__ == "__main__":
    sys.exit(main())
