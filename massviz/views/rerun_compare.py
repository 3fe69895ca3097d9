"""Two traces in one Rerun file, as two recordings of application ``massviz`` (``massviz compare --rrd``).

Each trace is logged exactly as ``massviz log`` logs it (``log_trace_with_clouds``: the entity tree in
docs/entity-tree.md), on its own recording named after its side ("A: ...", "B: ..."), plus ``/compare`` (static
``TextDocument``, markdown): the comparison report. The viewer lists both recordings; switch between them in its
recording panel, the layout (the default blueprint) is the same for both. The two recordings are written to temporary files and merged into one
with Rerun's own ``rerun rrd merge``; the output file appears only when everything succeeded.
"""
from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import uuid
from pathlib import Path

import rerun as rr

from massviz.errors import MassvizError
from massviz.io.atomic import atomic_path
from massviz.views.rerun.output import APPLICATION_ID
from massviz.views.rerun.trace_logger import log_trace_with_clouds


def log_two_traces(sides, rrd: str | Path, *, markdown: str | None = None, progress: bool = False,
                   video: str = "auto", replay=None) -> list[str]:
    """Write ``sides`` — ``[(name, trace, recording), (name, trace, recording)]`` — into one .rrd at ``rrd``, one
    Rerun recording per side; returns their recording ids (in order). ``replay(trace, recording)``: (the trace
    measured, its frames with their clouds), ``massviz.measure3d.stage.measured_replay``; without it no cloud is
    logged."""
    rrd = Path(rrd)
    ids = []
    with tempfile.TemporaryDirectory(prefix="massviz-compare-") as tmp, atomic_path(rrd) as out:
        parts = []
        for n, (name, trace, recording) in enumerate(sides):
            part = Path(tmp) / f"side{n}.rrd"
            stream = rr.RecordingStream(APPLICATION_ID, recording_id=str(uuid.uuid4()))
            stream.save(os.fspath(part))
            try:
                stream.send_recording_name(str(name))
                frames = None
                if replay is not None:
                    trace, frames = replay(trace, recording)
                log_trace_with_clouds(trace, recording, stream=stream, progress=progress, video=video,
                                      frames=frames)
                if markdown is not None:
                    stream.log("/compare", rr.TextDocument(markdown, media_type=rr.MediaType.MARKDOWN), static=True)
                stream.flush()
            finally:
                stream.disconnect()
            ids.append(stream.get_recording_id())
            parts.append(os.fspath(part))
        cmd = [sys.executable, "-m", "rerun", "rrd", "merge", *parts, "-o", os.fspath(out)]
        done = subprocess.run(cmd, capture_output=True, text=True)
        if done.returncode != 0 or not out.is_file() or out.stat().st_size == 0:
            last = (done.stderr.strip().splitlines() or ["no output"])[-1]
            raise MassvizError(f"could not merge the two recordings into one .rrd (rerun rrd merge: {last})", rrd)
    return ids


__all__ = ["log_two_traces"]
