"""Old import path of ``massviz.views.rerun`` (kept so existing imports work): the entity loggers, the blueprint,
``log_trace``, the sinks and the test-support .rrd reader, re-exported. New code imports ``massviz.views.rerun``."""
from __future__ import annotations

from massviz.views.rerun.blueprint import blueprint_for, default_blueprint  # noqa: F401
from massviz.views.rerun.entities import (CHOSEN_ID, CLASS_IDS, FLAGGED_ID, MAX_POINTS, POINT_STEP,  # noqa: F401
                                          RUNNING_COLOUR, RgbLogger, detection_class_ids, jpeg_bytes,
                                          log_annotation_context, log_clouds, log_depth, log_detections, log_events,
                                          log_flags, log_frame_clouds, log_masks, log_patch, log_pinhole,
                                          log_points, log_predictions, log_running, log_summary, log_timings,
                                          scene_depth_m, summary_markdown)
from massviz.views.rerun.output import APPLICATION_ID, use_local_notebook_assets  # noqa: F401
from massviz.views.rerun.replay import log_trace, show_in_notebook  # noqa: F401
from massviz.views.rerun.rrd_reader import rrd_contents, rrd_entities  # noqa: F401
