"""What ``cloud``, ``render`` and ``view3d`` share: run (or reuse) the pipeline, then the 3D stage."""
from __future__ import annotations

import sys

from massviz.commands._common import add_pipeline_args


def add_3d_args(p) -> None:
    p.add_argument("recording", metavar="REC", help="recording folder or CCM video path")
    add_pipeline_args(p)


def measured_trace(args):
    """(recording, trace with measurements) for ``args.recording``; a recording without intrinsics gets one line on
    stderr and a trace without measurements."""
    from massviz.commands._common import build
    from massviz.core.geometry import skip_reason, with_measurements
    from massviz.io.recording import open_recording

    rec = open_recording(args.recording)
    trace = build(args).process(rec)
    reason = skip_reason(rec)
    if reason:
        print(reason, file=sys.stderr)
    return rec, with_measurements(trace, rec)
