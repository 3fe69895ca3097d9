"""The viewer's default layout (a Rerun blueprint) for a trace or a live session."""
from __future__ import annotations

import numpy as np
import rerun.blueprint as rrb

from massviz.core.trace import Trace

def default_blueprint(n_patches: int, *, has_3d: bool = True, flagged=(), look_at_m: float = 1.0,
                      points: bool = False) -> rrb.Blueprint:
    """RGB + detections + masks, depth and 3D on the left; the chosen patches, predictions and text on the right.

    The 3D view starts at the camera (the origin of ``/world``, the camera frame) looking along its optical axis at
    ``look_at_m`` metres (orbiting around that point), image up. It shows the camera frustum, the detection clouds
    and the depth back-projected by Rerun through the ``Pinhole`` (or ``/world/points`` instead when ``points``).
    The RGB image is not in it: seen from the camera it would cover the whole view. ``flagged``: ranks of flagged
    patches (their tiles are named "patch ★r ⚑ flagged")."""
    flagged = {int(r) for r in flagged}
    camera = rrb.Spatial2DView(name="RGB · detections · masks", origin="/camera",
                               contents=["/camera/rgb", "/camera/detections", "/camera/masks"])
    depth = rrb.Spatial2DView(name="Depth", origin="/camera", contents=["/camera/depth"])
    lower = [depth]
    if has_3d:
        eye = rrb.EyeControls3D(position=[0.0, 0.0, 0.0], look_target=[0.0, 0.0, float(look_at_m)],
                                eye_up=[0.0, -1.0, 0.0])
        lower.append(rrb.Spatial3DView(name="3D (camera frame, m)", origin="/", eye_controls=eye,
                                       contents=["/world/**", "/camera"] + ([] if points else ["/camera/depth"])))
    if n_patches:
        patches = rrb.Grid(*[rrb.Spatial2DView(name=f"patch ★{r}" + (" ⚑ flagged" if r in flagged else ""),
                                               origin=f"/patches/{r}") for r in range(n_patches)],
                           name="Chosen patches (model input)")
    else:
        patches = rrb.TextDocumentView(name="Summary", origin="/summary")
    text = rrb.Tabs(rrb.TextLogView(name="Decisions", origin="/log"),
                    rrb.TextDocumentView(name="Summary", origin="/summary"),
                    rrb.TextDocumentView(name="Timings", origin="/timings"),
                    rrb.TimeSeriesView(name="Latency per frame (ms)", origin="/latency"))
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(camera, rrb.Horizontal(*lower), row_shares=[3, 2]),
            rrb.Vertical(patches, rrb.TimeSeriesView(name="Predictions (g)", origin="/predictions"), text,
                         row_shares=[2, 2, 2]),
            column_shares=[3, 2]),
        rrb.TimePanel(timeline="frame"),
        collapse_panels=False,
    )


def _look_at_m(trace: Trace) -> float:
    """Where the 3D view looks: the nearest chosen patch's distance d (m), else 1 m (no frame is read)."""
    if len(trace.selection) == 0:
        return 1.0
    d = float(trace.detections.d[int(trace.selection[0])])
    return float(np.clip(d / 1000.0, 0.1, 10.0)) if np.isfinite(d) else 1.0


def blueprint_for(trace: Trace, recording, *, points: bool = False) -> rrb.Blueprint:
    """``default_blueprint`` for this trace: its K patches, a 3D view (with intrinsics) looking at its scene."""
    return default_blueprint(len(trace.selection), has_3d=recording.intrinsics is not None,
                             flagged=[p.rank for p in trace.flags.flagged], look_at_m=_look_at_m(trace),
                             points=points)


