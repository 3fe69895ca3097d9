"""What ``cloud``, ``render`` and ``view3d`` share: run (or reuse) the pipeline, then the 3D stage."""
from __future__ import annotations

import sys

from massviz.commands._common import add_pipeline_args


def add_3d_args(p) -> None:
    p.add_argument("recording", metavar="REC", help="recording folder or CCM video path")
    add_pipeline_args(p)


def measured_trace(args, needs_intrinsics: str | None = None):
    """(recording, trace with measurements, the ``MeasureStage`` that measured it and holds the chosen frames'
    clouds) for ``args.recording``; a recording without intrinsics gets one line on stderr and a trace without
    measurements, or, for a command that cannot work without them (``needs_intrinsics``: its name), one error line
    before the pipeline runs."""
    from massviz.commands._common import build
    from massviz.errors import MassvizError
    from massviz.io.recording import open_recording
    from massviz.measure3d.settings import skip_reason
    from massviz.measure3d.stage import with_measurements

    rec = open_recording(args.recording, allow_partial=args.allow_partial)
    if needs_intrinsics and skip_reason(rec):
        what = skip_reason(rec).split(": ", 1)[-1].split(", so no 3D")[0]  # "no camera intrinsics (where ...)"
        raise MassvizError(f"{what}: massviz {needs_intrinsics} needs them, nothing written", args.recording)
    frame = getattr(args, "frame", None)
    if frame is not None and not 0 <= frame < rec.num_frames:
        raise MassvizError(f"--frame must be >= 0 and < {rec.num_frames} (the recording's frames), got {frame}")
    trace = build(args).process(rec)
    reason = skip_reason(rec)
    if reason:
        print(reason, file=sys.stderr)
    trace, stage = with_measurements(trace, rec)
    return rec, trace, stage
