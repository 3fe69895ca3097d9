"""``massviz log``'s run: the pipeline over one recording with a Rerun sink
(``massviz.views.rerun.trace_logger.TraceLogger``) given each frame's result as it is processed and the final trace.
The runner owns the loop; the sink only draws."""
from __future__ import annotations

from pathlib import Path

from massviz.core.trace import Trace
from massviz.views.rerun.blueprint import default_blueprint
from massviz.views.rerun.output import Output
from massviz.views.rerun.trace_logger import TraceLogger, trace_frames


def log_run(pipeline, recording, *, rrd: str | Path | None = None, spawn: bool = False, progress: bool = False,
            video: str = "auto", points: bool = False, clouds: bool = True, measure=None,
            before_close=None) -> tuple[Trace, dict]:
    """Run ``pipeline`` (``massviz.app.Pipeline``) on ``recording`` and log it in one pass (``massviz log``): each
    frame's ``FrameResult`` goes to the sink as it is processed, so no frame is read twice; a trace that comes from
    the cache (no frame processed) is given to the sink frame by frame from the recording, read once
    (``trace_frames``). The selection is the pipeline's (``Pipeline.selection``, resolved once): its K shapes the
    first layout, sent before the frames; the final one comes from the trace. Outputs and options as
    ``massviz.views.rerun.trace_logger.log_trace_with_clouds``. ``measure``: the measure stage
    (``massviz.measure3d.stage.MeasureStage``, made with ``clouds="active"``) observing the same steps (or the replay):
    its clouds of each frame go to the sink, and the trace is measured (``MeasureStage.finish``) before what needs
    the whole trace is logged; None: no cloud, no measurement. ``before_close(trace)``: more output made from the
    trace (``log --ply``), run once the recording is delivered and before the .rrd is renamed into place, so that
    when it fails no .rrd is left either. Returns (trace, stats)."""
    with Output(rrd=rrd, spawn=spawn) as out:
        layout = default_blueprint(pipeline.selection.k, has_3d=recording.intrinsics is not None,
                                   image_size=(recording.width, recording.height))
        logger = TraceLogger(recording, out.stream, video=video, points=points, clouds=clouds, blueprint=layout)

        def on_frame(frame, result):
            logger.on_frame(frame, result, None if measure is None else measure.on_frame(frame, result))

        trace = pipeline.process(recording, on_frame=on_frame)
        if not logger.frames:
            replayed = None if measure is None else measure.replay_frames(trace)
            for frame, result, clouds_of_frame in trace_frames(trace, recording, progress=progress, frames=replayed):
                logger.on_frame(frame, result, clouds_of_frame)
        if measure is not None:
            trace = measure.finish(trace)
        stats = logger.finish(trace, points=points)
        if before_close is not None:
            out.flush()
            before_close(trace)
    stats.update(out.stats(), log_seconds=logger.seconds, seconds=out.seconds)
    return trace, stats


__all__ = ["log_run"]
