"""massviz in Rerun: every stage of one estimate on a ``frame`` timeline, with a default layout.

The package: ``entities`` (one small ``log_*`` function per kind of data, in the style of Rerun's ``rgbd`` and
``detect_and_track_objects`` examples), ``blueprint`` (the default layout), ``frame_logger`` (``FrameLogger``: one
processed frame and its ``FrameResult``, as ``massviz log`` and ``massviz live`` both log it), ``trace_logger`` (a
trace -> a recording stream: the sink ``TraceLogger`` and ``log_trace_with_clouds``), ``live_logger``
(``LiveLogger``: a live session frame by frame), ``output`` (where a stream goes: .rrd file, spawned or running
viewer, a caller's stream, the notebook's inline viewer; ``Output``, the one context-managed output). Sinks only
read: they log results (traces, frames, step results, the measure stage's clouds) and never run a stage or measure
(``massviz.runners.trace_to_rerun.log_trace`` gives ``log_trace_with_clouds`` the measure stage's clouds).

Entity tree (a public contract; docs/entity-tree.md copies it). Everything temporal is on the ``frame`` timeline (sequence =
frame index in the recording); a video asset's frames are also on ``video_time``.

=============================  ========================================================================================
entity                         what is logged
=============================  ========================================================================================
``/camera``                    ``Pinhole`` (static; RDF camera; only with intrinsics) and the ``AnnotationContext``
                               (static) naming the class ids used by ``/camera/detections`` and ``/camera/masks``
``/camera/rgb``                an mp4 Rerun can decode: the file once as ``AssetVideo`` (static, not re-encoded) and a
                               ``VideoFrameReference`` per processed frame; frame folders: ``EncodedImage`` of each
                               frame file's bytes; an mp4 Rerun cannot decode (e.g. CCM's MPEG-4 Part 2 'mp4v'):
                               JPEG ``EncodedImage`` per processed frame, with a warning in ``/log``
``/camera/depth``              ``EncodedDepthImage``: the recording's 16-bit PNG (mm) as its own bytes (``meter=1000``,
                               turbo colormap); the 3D view back-projects it through the ``Pinhole`` (``DepthImage``
                               of the decoded array when there is no PNG file)
``/camera/detections``         ``Boxes2D`` (XYXY) labelled "class score · d mm · track t", with class ids and
                               ``AnyValues`` track, detection; boxes coloured by object track, chosen patches in the
                               palette's chosen colour (class id ``CHOSEN_ID + rank``, label suffix "★rank"),
                               flagged ones in its flagged colour (class id ``FLAGGED_ID + rank``, "★rank ⚑ flagged")
``/camera/masks``              ``SegmentationImage`` of the same class ids (chosen masks drawn on top)
``/world``                     ``ViewCoordinates.RDF`` (static): the 3D world is the camera frame
``/world/points``              only with ``points=True`` (``massviz log --points``): ``Points3D``, depth back-projected
                               (Open3D) to metres in the camera frame, every ``step``-th pixel, at most ``max_points``,
                               coloured by RGB (only with intrinsics)
``/patches/<rank>``            ``EncodedImage`` (JPEG, quality 85) of chosen patch ``rank`` (0 = nearest) as the model saw it (zero-padded
                               square, 112×112) at its source frame, with ``AnyValues`` a, b, d_mm, frame, class,
                               score, pred_g, detection, track, flagged, flag
``/patches/<rank>/outline``    ``Boxes2D`` around the tile: chosen colour, or flagged colour labelled "⚑ flagged: why"
``/predictions/patch_<rank>``  ``Scalars``: that patch's prediction (g), at its source frame and the last frame
``/predictions/estimate``      ``Scalars``: the estimate (g) at the last processed frame (absent when not estimated)
``/predictions/estimate_without_flagged``  ``Scalars``: the mean prediction of the chosen patches not flagged
                               (``trace.flags``), at the last processed frame (only when some are flagged and
                               some are not)
``/predictions/ground_truth``  ``Scalars``: the container's mass from the recording's meta (``container.mass_g``), at
                               the first and the last processed frame (absent when unknown)
``/world/detections/<id>``     ``Points3D``: detection ``id``'s cleaned Open3D cloud (chosen ones highlighted), with
                               ``/box`` (``Boxes3D``, measured box of a chosen one) and ``/measurement`` (AnyValues);
                               logged at each processed frame (``TraceLogger.on_frame``; clouds from the measure
                               stage, ``massviz.measure3d.stage``, thinned to ``CLOUD_VOXEL_M``), cleared at the next
                               (only with intrinsics; ``clouds=False`` skips)
``/log``                       ``TextLog`` of the decisions (trace events, missing intrinsics, video fallback) with
                               levels, at their frames; one WARN per flagged patch at its frame and the flags'
                               summary line ("3 of 5 chosen patches look like another object ...") at the last
``/summary``                   ``TextDocument`` (static, markdown): recording, detector, K, estimate, chosen patches
                               with their track and flag
``/timings``                   ``TextDocument`` (static, markdown): seconds per pipeline stage and for logging
``/timings/<stage>``           ``Scalars`` (static): seconds of each stage of ``trace.timings`` and ``log`` (this
                               logging's own cost)
=============================  ========================================================================================

Class ids (``AnnotationContext`` at ``/camera``): 0 background, 1 cup, 2 book, 3 wine glass, 4 bottle, 5 object
(class-agnostic depth detector), 6 other COCO class, 7 below the trace's threshold, ``CHOSEN_ID + rank`` chosen patch,
``FLAGGED_ID + rank`` chosen patch flagged as probably not the container. Colours come from ``massviz.views.palette``
(the same chosen and flagged colours as the notebooks' figures and the Open3D render).
"""
from __future__ import annotations

from massviz.views.rerun.blueprint import blueprint_for, default_blueprint
from massviz.views.rerun.entities import (
                                          CHOSEN_ID,
                                          CLASS_IDS,
                                          CLOUD_VOXEL_M,
                                          FLAGGED_ID,
                                          MAX_POINTS,
                                          POINT_STEP,
                                          RgbLogger,
                                          log_flags,
)
from massviz.views.rerun.output import APPLICATION_ID, use_local_notebook_assets
from massviz.views.rerun.trace_logger import log_trace_with_clouds

__all__ = ["log_trace_with_clouds", "log_flags", "default_blueprint", "RgbLogger", "CLASS_IDS", "CHOSEN_ID",
           "FLAGGED_ID", "POINT_STEP", "MAX_POINTS", "CLOUD_VOXEL_M", "blueprint_for", "use_local_notebook_assets",
           "APPLICATION_ID"]
