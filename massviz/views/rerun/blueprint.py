"""The viewer's default layout (a Rerun blueprint) for a trace or a live session."""
from __future__ import annotations

import numpy as np
import rerun.blueprint as rrb

from massviz.core.trace import Trace

#: the 3D view's start, as ``massviz render``'s default: orbited from the recording camera by this yaw (about the
#: vertical, from the right) and pitch (from above), and backed off to this many times the target's distance so that
#: the camera's frustum at the origin is in view.
YAW_DEG, PITCH_DEG, BACK_OFF = 25.0, 15.0, 2.5


def oblique_eye(target) -> rrb.EyeControls3D:
    """An orbit eye looking at ``target`` (camera frame, m) from the recording camera's side, turned by ``YAW_DEG``
    and ``PITCH_DEG`` (the formula of ``massviz.views.open3d_view.view_extrinsic``) at ``BACK_OFF`` times its
    distance, image up."""
    target = np.asarray(target, float)
    r = float(np.linalg.norm(target)) or 1.0
    yaw, pitch = np.radians(YAW_DEG), np.radians(PITCH_DEG)
    offset = np.array([np.sin(yaw) * np.cos(pitch), -np.sin(pitch), -np.cos(yaw) * np.cos(pitch)])
    eye = target + BACK_OFF * r * offset
    return rrb.EyeControls3D(kind=rrb.Eye3DKind.Orbital, position=eye.tolist(), look_target=target.tolist(),
                             eye_up=[0.0, -1.0, 0.0])


def tile_name(rank: int, flagged: bool = False) -> str:
    """A patch tile's title: short enough to show whole in a narrow tile."""
    return f"★{rank}" + (" ⚑ flagged" if flagged else "")


def default_blueprint(n_patches: int, *, has_3d: bool = True, flagged=(), look_at_m: float = 1.0,
                      points: bool = False, target=None, image_size: tuple[int, int] | None = None) -> rrb.Blueprint:
    """RGB + detections + masks, depth and 3D on the left; the chosen patches, predictions and text on the right.

    The 2D views fit the whole image (``image_size`` (width, height): their visual bounds). The 3D view starts
    oblique (``oblique_eye``: yaw 25°, pitch 15°, as ``massviz render``) looking at ``target`` (camera frame, m;
    default ``look_at_m`` metres along the optical axis), with the camera frustum in view; it shows the detection
    clouds and the depth back-projected by Rerun through the ``Pinhole`` (or ``/world/points`` instead when
    ``points``). The RGB image is not in it. ``flagged``: ranks of flagged patches (tile "★r ⚑ flagged", other tiles
    "★r"). The predictions plot has no legend over it (series are named on hover; colours: patches magenta, flagged red,
    estimate white, without flagged cyan, ground truth green, running blue)."""
    flagged = {int(r) for r in flagged}
    bounds = {}
    if image_size is not None:
        w, h = image_size
        bounds = {"visual_bounds": rrb.VisualBounds2D(x_range=[0.0, float(w)], y_range=[0.0, float(h)])}
    camera = rrb.Spatial2DView(name="RGB · detections · masks", origin="/camera",
                               contents=["/camera/rgb", "/camera/detections", "/camera/masks"], **bounds)
    depth = rrb.Spatial2DView(name="Depth", origin="/camera", contents=["/camera/depth"], **bounds)
    lower = [depth]
    if has_3d:
        eye = oblique_eye(target if target is not None else [0.0, 0.0, float(look_at_m)])
        lower.append(rrb.Spatial3DView(name="3D (camera frame, m)", origin="/", eye_controls=eye,
                                       contents=["/world/**", "/camera"] + ([] if points else ["/camera/depth"])))
    if n_patches:
        patches = rrb.Grid(*[rrb.Spatial2DView(name=tile_name(r, r in flagged), origin=f"/patches/{r}")
                             for r in range(n_patches)], name="Chosen patches (model input)")
    else:
        patches = rrb.TextDocumentView(name="Summary", origin="/summary")
    text = rrb.Tabs(rrb.TextLogView(name="Decisions", origin="/log"),
                    rrb.TextDocumentView(name="Summary", origin="/summary"),
                    rrb.TextDocumentView(name="Timings", origin="/timings"),
                    rrb.TimeSeriesView(name="Latency per frame (ms)", origin="/latency"))
    predictions = rrb.TimeSeriesView(
        name="Predictions (g)",
        origin="/predictions", plot_legend=rrb.PlotLegend(visible=False))
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(camera, rrb.Horizontal(*lower), row_shares=[3, 2]),
            rrb.Vertical(patches, predictions, text, row_shares=[2, 2, 2]),
            column_shares=[3, 2]),
        rrb.TimePanel(timeline="frame"),
        collapse_panels=False,
    )


def _target(trace: Trace, recording):
    """The nearest chosen patch in the camera frame (m): its measured centre, else its box centre at its d; None
    without a chosen patch or intrinsics (no frame is read)."""
    intr = recording.intrinsics
    if len(trace.selection) == 0 or intr is None:
        return None
    i = int(trace.selection[0])
    for m in trace.measurements:
        if m.detection == i:
            return [float(v) for v in m.center]
    d = float(trace.detections.d[i])
    if not np.isfinite(d):
        return None
    x1, y1, x2, y2 = (float(v) for v in trace.detections.xyxy[i])
    z = d / 1000.0
    return [((x1 + x2) / 2 - intr.cx) * z / intr.fx, ((y1 + y2) / 2 - intr.cy) * z / intr.fy, z]


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
                             points=points, target=_target(trace, recording),
                             image_size=(recording.width, recording.height))


