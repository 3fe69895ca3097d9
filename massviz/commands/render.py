"""``massviz render``: a headless picture of the 3D scene with the chosen containers and their boxes."""
from __future__ import annotations

import argparse
import sys

from massviz.commands._3d import add_3d_args
from massviz.commands._common import PIPELINE_HELP


def register(sub) -> None:
    p = sub.add_parser(
        "render", help="render the scene cloud, the chosen containers and their 3D boxes to a PNG (no display)",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Run (or reuse) the pipeline on one recording and draw one frame's back-projected cloud with "
        "Open3D's offscreen renderer (CPU, no display needed): the chosen detections' points in magenta, their "
        "measured boxes in green; a chosen patch flagged as probably not the container (see 'massviz log') in red, "
        "named FLAGGED in the caption and in a warning line. The view orbits the nearest chosen container from the "
        "recording camera's viewpoint (--yaw/--pitch; 0 0 is the camera's own view). A --frame without a chosen "
        "patch is an error that lists the frames with one.",
        epilog="example:\n  massviz render data_samples/cup_handover --detector depth --out cup3d.png\n" + PIPELINE_HELP)
    add_3d_args(p)
    p.add_argument("--out", required=True, metavar="PNG", help="output image (.png)")
    p.add_argument("--frame", type=int, metavar="N",
                   help="frame to draw, one with a chosen patch (default: the nearest chosen detection's)")
    p.add_argument("--size", default="960x540", metavar="WxH", help="image size in pixels (default: 960x540)")
    p.add_argument("--yaw", type=float, default=25.0, metavar="DEG", help="orbit about the vertical (default: 25)")
    p.add_argument("--pitch", type=float, default=15.0, metavar="DEG", help="orbit from above (default: 15)")
    p.set_defaults(func=run)


def parse_size(text: str) -> tuple[int, int]:
    from massviz.errors import MassvizError

    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise MassvizError(f"--size must be WIDTHxHEIGHT (e.g. 960x540), got {text!r}") from None
    if not (16 <= w <= 8192 and 16 <= h <= 8192):
        raise MassvizError(f"--size must be between 16 and 8192 pixels each way, got {text!r}")
    return w, h


def run(args) -> int:
    from pathlib import Path

    from massviz.commands._3d import measured_trace
    from massviz.errors import MassvizError
    from massviz.io.atomic import check_output_file
    from massviz.views.open3d_view import render_png

    out = Path(args.out)
    if out.suffix.lower() != ".png":
        raise MassvizError("--out must be a .png file", out)
    width, height = parse_size(args.size)
    check_output_file(out, "--out")
    rec, trace, stage = measured_trace(args, needs_intrinsics="render")
    info = render_png(trace, rec, stage.clouds_of(trace, trace.selection), out, frame_index=args.frame, width=width, height=height, yaw_deg=args.yaw,
                      pitch_deg=args.pitch)
    print(f"{rec.id}: wrote {out} (frame {info['frame']}, rendered in {info['seconds']:.1f} s)", file=sys.stderr)
    for flag in info["flagged"]:
        print(f"massviz render: warning: {rec.id}: frame {info['frame']}: chosen patch ★{flag.rank} (track "
              f"{flag.track}) is flagged, probably not the container (drawn in red): {flag.reason}", file=sys.stderr)
    return 0
