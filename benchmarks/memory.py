"""Peak memory of the pipeline does not grow with the recording's length.

Builds two synthetic RGB-D recordings (640x480 by default, a textured container moving across a table in front of
a wall), one of 30 and one of 300 frames, runs the whole pipeline (detector, features, mass CNN, selection; no trace cache) on
each in a fresh Python process, and compares their peak resident set sizes (``ru_maxrss``). Frames are streamed and
only the nearest ``KEEP_PATCHES`` patches are held, so the ratio should stay near 1; it exits 1 when
``peak(300) / peak(30) > --max-ratio`` (default 1.2).

The frames must be large enough for the check to mean something: torch and friends take ~700 MB before the first
frame, so holding every 320x240 frame (0.4 MB each with its depth) would add only ~1.15x. The script prints the
ratio that holding every frame would give and warns when it is not above --max-ratio.

    python benchmarks/memory.py                      # replay detector (detections written with the recording)
    python benchmarks/memory.py --detector depth     # the depth detector (~1 s a frame at 640x480 on 2 cores)
    python benchmarks/memory.py --size 320 240       # smaller frames (see above)
    python benchmarks/memory.py --simulate-leak      # hold every frame: must exit 1 (the check has teeth)
    python benchmarks/memory.py --layout png         # rgb/*.png instead of rgb.mp4

Mass-CNN weights: --weights PATH, else $MASSVIZ_WEIGHTS, else ../shared/weights/corsmal_visual/Encoder_pool_aug_158.torch.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_WEIGHTS = ROOT.parent / "shared" / "weights" / "corsmal_visual" / "Encoder_pool_aug_158.torch"


def object_box(i: int, n: int, width: int, height: int) -> list[int]:
    """The container's box in frame i of n: it moves left to right (and comes nearer)."""
    box_w, box_h = width // 8, height * 4 // 15
    x1 = width // 16 + (width - width // 8 - box_w) * i // max(n - 1, 1)
    y1 = height * 3 // 8
    return [x1, y1, x1 + box_w, y1 + box_h]


def build_recording(folder: Path, n: int, layout: str, size: tuple[int, int]) -> Path:
    import cv2
    import numpy as np

    width, height = size
    x1, y1, x2, y2 = object_box(0, n, width, height)
    rng = np.random.default_rng(n)
    folder.mkdir(parents=True)
    (folder / "depth").mkdir()
    writer = None
    if layout == "video":
        writer = cv2.VideoWriter(str(folder / "rgb.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 30.0, (width, height))
    else:
        (folder / "rgb").mkdir()
    wall = rng.integers(60, 120, (height, width, 3), dtype=np.uint8)
    texture = rng.integers(0, 256, (y2 - y1, x2 - x1, 3), dtype=np.uint8)
    rows = []
    for i in range(n):
        rgb = wall.copy()
        depth = np.full((height, width), 2500, np.uint16)  # the wall, beyond the depth detector's range
        top = height * 17 // 24
        depth[top:, :] = np.linspace(900, 1400, height - top, dtype=np.uint16)[:, None]  # table top
        x1, y1, x2, y2 = object_box(i, n, width, height)
        rgb[y1:y2, x1:x2] = texture
        depth[y1:y2, x1:x2] = 800 - 200 * i // max(n - 1, 1)
        if writer is not None:
            writer.write(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        else:
            cv2.imwrite(str(folder / "rgb" / f"{i:06d}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        cv2.imwrite(str(folder / "depth" / f"{i:06d}.png"), depth)
        rows.append({"frame": i, "box": [x1, y1, x2, y2], "score": 0.9, "class": "cup"})
    if writer is not None:
        writer.release()
    (folder / "meta.json").write_text(json.dumps({"id": f"moving_{n}", "fps": 30}))
    (folder / "replay.json").write_text(json.dumps({"detections": rows}))
    return folder


def child(args) -> None:
    """Run the pipeline once and print one JSON line with this process's peak RSS."""
    from massviz.app import process
    from massviz.detect import make_detector
    from massviz.io.checkpoint import load_checkpoint
    from massviz.io.recording import open_recording

    t0 = time.perf_counter()
    rec = open_recording(args.child)
    if args.simulate_leak:  # keep every frame alive, to show the check catches a pipeline that accumulates frames
        held, frames = [], rec.frames
        rec.frames = lambda *a, **k: (held.append(f) or f for f in frames(*a, **k))
    detector = make_detector(args.detector, 0.4, replay=rec.path / "replay.json" if args.detector == "replay"
                             else None)
    model = load_checkpoint(args.weights)
    trace = process(rec, detector, model, k=5, cache=None)
    peak_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # kilobytes on Linux
    print(json.dumps({"frames": int(len(trace.frames)), "detections": int(len(trace.detections)),
                      "estimate_g": round(float(trace.estimate), 2), "seconds": round(time.perf_counter() - t0, 1),
                      "peak_rss_mb": round(peak_kb / 1024, 1)}))


def measure(folder: Path, args) -> dict:
    cmd = [sys.executable, __file__, "--child", str(folder), "--detector", args.detector, "--weights",
           str(args.weights)] + (["--simulate-leak"] if args.simulate_leak else [])
    out = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if out.returncode != 0:
        sys.exit(f"memory.py: the run on {folder} failed:\n{out.stderr.strip()}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--detector", choices=["depth", "replay"], default="replay",
                   help="replay (default: detections written with the recording) or depth")
    p.add_argument("--size", type=int, nargs=2, default=[640, 480], metavar=("W", "H"))
    p.add_argument("--layout", choices=["video", "png"], default="video", help="rgb.mp4 (default) or rgb/*.png")
    p.add_argument("--frames", type=int, nargs=2, default=[30, 300], metavar=("SHORT", "LONG"))
    p.add_argument("--max-ratio", type=float, default=1.2)
    p.add_argument("--weights", type=Path, default=Path(os.environ.get("MASSVIZ_WEIGHTS") or DEFAULT_WEIGHTS))
    p.add_argument("--simulate-leak", action="store_true",
                   help="hold every frame in memory (a deliberate leak: the check must then fail)")
    p.add_argument("--child", type=Path, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child:
        child(args)
        return 0
    if not args.weights.is_file():
        sys.exit(f"memory.py: mass-CNN weights not found: {args.weights} (pass --weights PATH)")
    with tempfile.TemporaryDirectory(prefix="massviz-memory-") as tmp:
        results = []
        for n in args.frames:
            folder = build_recording(Path(tmp) / f"moving_{n}", n, args.layout, tuple(args.size))
            results.append(measure(folder, args))
            r = results[-1]
            print(f"{n:4d} frames ({args.detector}, {args.layout}): peak RSS {r['peak_rss_mb']:.1f} MB, "
                  f"{r['detections']} detections, estimate {r['estimate_g']} g, {r['seconds']} s")
    short, long = (r["peak_rss_mb"] for r in results)
    ratio = long / short
    frame_mb = args.size[0] * args.size[1] * 5 / 2**20  # RGB uint8 + depth uint16
    held = (short + (args.frames[1] - args.frames[0]) * frame_mb) / short
    print(f"(holding every frame would give about {held:.2f}; growth {long - short:+.1f} MB)")
    if held <= args.max_ratio:
        print(f"warning: at {args.size[0]}x{args.size[1]} this check cannot see frames being held; use larger "
              "--size or more --frames")
    verdict = "ok" if ratio <= args.max_ratio else f"FAIL (> {args.max_ratio})"
    print(f"ratio {args.frames[1]}/{args.frames[0]} frames: {ratio:.3f} {verdict}")
    return 0 if ratio <= args.max_ratio else 1


if __name__ == "__main__":
    sys.exit(main())
