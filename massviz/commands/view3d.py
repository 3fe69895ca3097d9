"""``massviz view3d``: Open3D's interactive window on one frame's cloud, chosen containers and boxes."""
from __future__ import annotations

import argparse

from massviz.commands._3d import add_3d_args
from massviz.commands._common import PIPELINE_HELP


def register(sub) -> None:
    p = sub.add_parser(
        "view3d", help="open Open3D's 3D window on the scene with the chosen containers (needs a display)",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Run (or reuse) the pipeline on one recording and open Open3D's interactive window on one "
        "frame: the back-projected scene, the chosen detections in magenta and their measured boxes in green. "
        "Needs a display (DISPLAY or WAYLAND_DISPLAY); without one use 'massviz render'.",
        epilog="example:\n  massviz view3d data_samples/box_handover --detector depth\n" + PIPELINE_HELP)
    add_3d_args(p)
    p.add_argument("--frame", type=int, metavar="N", help="frame to show (default: the nearest chosen detection's)")
    p.set_defaults(func=run)


def run(args) -> int:
    from massviz.commands._3d import measured_trace
    from massviz.views.open3d_view import require_display, show

    require_display()  # say so before running anything
    rec, trace, stage = measured_trace(args, needs_intrinsics="view3d")
    show(trace, rec, stage.clouds_of(trace, trace.selection), frame_index=args.frame)
    return 0
