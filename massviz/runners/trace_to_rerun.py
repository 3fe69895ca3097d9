"""A finished trace logged to Rerun with its clouds: the measure stage (``massviz.measure3d.stage``) measures the
chosen detections and replays the processed frames with each detection's cloud, the Rerun sink
(``massviz.views.rerun.log_trace_with_clouds``) logs them. What ``mv.log_trace`` and the notebooks call; ``massviz log`` runs
the pipeline with the same two instead (one pass, ``massviz.commands.log``)."""
from __future__ import annotations

from massviz.measure3d.stage import measured_replay
from massviz.views.rerun import trace_logger as sink
from massviz.views.rerun.blueprint import blueprint_for
from massviz.views.rerun.output import notebook_stream


def _measured(trace, recording, clouds: bool):
    if clouds and recording.intrinsics is not None:
        return measured_replay(trace, recording)
    return trace, None


def log_trace(trace, recording, *, clouds: bool = True, **options) -> dict:
    """``massviz.views.rerun.log_trace_with_clouds`` (``options``: its outputs and settings) of ``trace`` measured, with each
    detection's cloud under ``/world/detections`` (``clouds=False``: none, nothing measured). Returns its stats."""
    trace, frames = _measured(trace, recording, clouds)
    return sink.log_trace_with_clouds(trace, recording, clouds=clouds, frames=frames, **options)


def show_in_notebook(trace, recording, *, width: int = 1000, height: int = 640, clouds: bool = True,
                     **options) -> dict:
    """``log_trace`` into an inline Rerun viewer in the current notebook cell (``output.notebook_stream``), with
    massviz's default layout. Returns ``log_trace``'s stats."""
    trace, frames = _measured(trace, recording, clouds)
    stream = notebook_stream(recording.id, blueprint_for(trace, recording, points=bool(options.get("points"))),
                             width=width, height=height)
    return sink.log_trace_with_clouds(trace, recording, stream=stream, clouds=clouds, frames=frames, **options)


__all__ = ["log_trace", "show_in_notebook"]
