"""3D through Open3D: back-projected clouds, each detection's masked cloud, its measured size, .ply files.

**Axes.** Every cloud is in metres in the *camera frame* of the recording's RGB camera, OpenCV convention (RDF):
x to the right of the image, y down the image, z forward along the optical axis (depth). This is the convention of
``Intrinsics`` and of Rerun's ``Pinhole`` with ``camera_xyz=RDF``, so clouds logged under the camera entity line up
with its image. (Open3D's own viewers look down -z with y up; the renderers here set their cameras accordingly.)

**Back-projection.** ``o3d.geometry.RGBDImage.create_from_color_and_depth`` (``depth_scale=1000``: depth PNGs are
millimetres) and ``PointCloud.create_from_rgbd_image`` with the recording's ``PinholeCameraIntrinsic``: pixel (u, v)
with depth z maps to ``((u - cx) z / fx, (v - cy) z / fy, z)``. Pixels without depth (0) or beyond ``depth_trunc``
give no point. A detection's cloud is the same with the depth zeroed outside its full-frame mask, then cleaned:
points farther than ``band_m`` from the mask's median depth are dropped (background seen through the mask's edge)
and Open3D's ``remove_statistical_outlier`` removes the stray ones (flying pixels at depth edges).

**Measured size.** The container's vertical axis comes from the cleaned cloud's oriented bounding box
(``get_minimal_oriented_bounding_box``, which fits a box's faces; the PCA ``get_oriented_bounding_box`` when that
fails): of its three axes, the one most aligned with the image's vertical (camera y). The measured box is then the
tightest box around the points with that vertical, turned to face the camera:

* **height**: the extent along the container's vertical. For an upright or tilted container this is its height,
  whatever its yaw.
* **width**: the extent across the line of sight (perpendicular to the vertical and to the ray from the camera to
  the cloud's centre), i.e. the container's width *as seen*: a cup's or glass's widest diameter, a box's face width
  when it faces the camera (``w·cos(yaw) + d·sin(yaw)`` when it is turned). This is what the CCM annotation's
  ``width at the top``/``width at the bottom`` measure for containers seen from the front, and, unlike the minimal
  box's own extents, it is not thrown off by a hand holding the container from the side.
* **depth**: the extent along the line of sight. Only the camera-facing surface is seen, so for a cup or glass this
  is about its radius, and for a box its visible side.

The box is stored as centre, extent and rotation ``R`` whose columns are the (width, height, depth) directions in the
camera frame (width ≈ +x, height ≈ +y: down, depth ≈ +z), a proper rotation; ``extent`` holds the matching lengths in
metres.

A recording without intrinsics has no metric 3D: ``measure`` returns nothing and ``skip_reason`` says why in one line.
"""
from __future__ import annotations

import dataclasses
import math
import os
import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import open3d as o3d

from massviz.atomic import atomic_path
from massviz.errors import MassvizError
from massviz.types import Detections, Frame, Intrinsics

#: default farthest depth (m) kept in clouds.
DEPTH_TRUNC_M = 4.0
#: half-width (m) of the depth band around a detection's median depth kept in its cloud.
BAND_M = 0.25
#: ``remove_statistical_outlier`` settings: neighbours, standard-deviation ratio.
SOR_NEIGHBOURS = 20
SOR_STD_RATIO = 2.0
#: colour (RGB 0..1) of the chosen detections' points and boxes; other detections keep their own colours.
CHOSEN_COLOUR = (1.0, 0.1, 0.75)
BOX_COLOUR = (0.05, 0.85, 0.2)


# ------------------------------------------------------------------------------------------------ intrinsics
def skip_reason(recording) -> str | None:
    """One line saying why ``recording`` gets no 3D stage, or None when it has intrinsics."""
    if getattr(recording, "intrinsics", None) is None:
        where = ("a calib/NNNNNN.pickle beside the CCM view" if getattr(recording, "kind", "") == "ccm"
                 else "intrinsics.json in the recording folder")
        return f"{recording.id}: no camera intrinsics ({where}), so no 3D: clouds and measurements skipped"
    return None


def require_intrinsics(recording) -> Intrinsics:
    """The recording's intrinsics, or a ``MassvizError`` naming what is missing."""
    reason = skip_reason(recording)
    if reason:
        raise MassvizError(reason)
    return recording.intrinsics


def pinhole(intr: Intrinsics) -> o3d.camera.PinholeCameraIntrinsic:
    return o3d.camera.PinholeCameraIntrinsic(int(intr.width), int(intr.height), float(intr.fx), float(intr.fy),
                                             float(intr.cx), float(intr.cy))


# ------------------------------------------------------------------------------------------------ clouds
def rgbd_cloud(rgb: np.ndarray, depth: np.ndarray, intr: Intrinsics, *,
               depth_trunc: float = DEPTH_TRUNC_M) -> o3d.geometry.PointCloud:
    """Coloured cloud of every pixel with depth in (0, ``depth_trunc``] (m, camera frame, RDF)."""
    color = o3d.geometry.Image(np.ascontiguousarray(rgb, dtype=np.uint8))
    d = o3d.geometry.Image(np.ascontiguousarray(depth, dtype=np.uint16))
    rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
        color, d, depth_scale=1000.0, depth_trunc=float(depth_trunc), convert_rgb_to_intensity=False)
    return o3d.geometry.PointCloud.create_from_rgbd_image(rgbd, pinhole(intr))


def scene_cloud(frame: Frame, intr: Intrinsics, *, depth_trunc: float = DEPTH_TRUNC_M) -> o3d.geometry.PointCloud:
    """The whole frame back-projected (no cleaning): one point per pixel with depth."""
    return rgbd_cloud(frame.rgb, frame.depth, intr, depth_trunc=depth_trunc)


def masked_cloud(frame: Frame, mask: np.ndarray, intr: Intrinsics, *, depth_trunc: float = DEPTH_TRUNC_M,
                 band_m: float | None = BAND_M, clean: bool = True) -> o3d.geometry.PointCloud:
    """The cloud of a full-frame boolean ``mask``: depth zeroed outside it, then (``clean``) the depth band around its
    median and statistical outlier removal (module docstring)."""
    depth = np.where(mask, frame.depth, 0).astype(np.uint16)
    if clean and band_m is not None:
        z = depth[depth > 0]
        if z.size:
            med = float(np.median(z))
            depth[np.abs(depth.astype(np.float64) - med) > band_m * 1000.0] = 0
    pcd = rgbd_cloud(frame.rgb, depth, intr, depth_trunc=depth_trunc)
    if clean and len(pcd.points) > SOR_NEIGHBOURS:
        pcd, _ = pcd.remove_statistical_outlier(nb_neighbors=SOR_NEIGHBOURS, std_ratio=SOR_STD_RATIO)
    return pcd


def detection_cloud(frame: Frame, dets: Detections, i: int, intr: Intrinsics, **kw) -> o3d.geometry.PointCloud:
    """Cleaned cloud of detection ``i`` (its mask pasted into the frame)."""
    return masked_cloud(frame, dets.full_mask(i, frame.height, frame.width), intr, **kw)


# ------------------------------------------------------------------------------------------------ measuring
@dataclass
class Size:
    """A cloud's measured box (module docstring): lengths in mm, box in metres."""

    height_mm: float
    width_mm: float
    depth_mm: float
    center: np.ndarray  # (3,) m
    extent: np.ndarray  # (3,) m: width, height, depth
    R: np.ndarray  # 3×3, columns: width, height, depth directions
    n_points: int

    def obb(self) -> o3d.geometry.OrientedBoundingBox:
        return o3d.geometry.OrientedBoundingBox(np.asarray(self.center, float), np.asarray(self.R, float),
                                                np.asarray(self.extent, float))


def oriented_box(pcd: o3d.geometry.PointCloud) -> o3d.geometry.OrientedBoundingBox:
    """Minimal oriented box of the cloud (PCA box when the minimal one fails, e.g. on a degenerate cloud)."""
    try:
        return pcd.get_minimal_oriented_bounding_box(robust=True)
    except RuntimeError:
        return pcd.get_oriented_bounding_box(robust=True)


def vertical_axis(box: o3d.geometry.OrientedBoundingBox) -> np.ndarray:
    """The box axis most aligned with the image's vertical (camera y), pointing down (+y)."""
    R = np.asarray(box.R, float)
    axis = R[:, int(np.argmax(np.abs(R[1, :])))]
    return axis if axis[1] >= 0 else -axis


def view_aligned_box(points: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(center, R, extent) of the tightest box around ``points`` with vertical ``up`` that faces the camera: columns of
    R are width (across the line of sight), height (``up``) and depth (along the line of sight)."""
    up = np.asarray(up, float) / np.linalg.norm(up)
    c = points.mean(axis=0)
    view = c / (np.linalg.norm(c) or 1.0)
    w = np.cross(up, view)
    if np.linalg.norm(w) < 1e-6:  # looking straight along the vertical: take the camera's x
        w = np.array([1.0, 0.0, 0.0]) - up[0] * up
    w /= np.linalg.norm(w)
    d = np.cross(w, up)
    R = np.stack([w, up, d], axis=1)
    local = (points - c) @ R
    lo, hi = local.min(axis=0), local.max(axis=0)
    return c + R @ ((lo + hi) / 2), R, hi - lo


def measure_cloud(pcd: o3d.geometry.PointCloud) -> Size | None:
    """Height, width, depth (mm) and measured box of a cloud (module docstring); None with fewer than 10 points."""
    n = len(pcd.points)
    if n < 10:
        return None
    center, R, extent = view_aligned_box(np.asarray(pcd.points), vertical_axis(oriented_box(pcd)))
    return Size(height_mm=1000 * extent[1], width_mm=1000 * extent[0], depth_mm=1000 * extent[2], center=center,
                extent=extent, R=R, n_points=n)


@dataclass
class Measurement:
    """Measured size of one chosen detection (``rank`` in the selection, ``detection`` its index in the trace)."""

    rank: int
    detection: int
    frame: int
    height_mm: float
    width_mm: float
    depth_mm: float
    center: list  # m, camera frame
    extent: list  # m: width, height, depth
    R: list  # 3×3 rows; columns are the width, height, depth directions
    n_points: int

    @classmethod
    def from_size(cls, rank: int, detection: int, frame: int, size: Size) -> "Measurement":
        return cls(rank=int(rank), detection=int(detection), frame=int(frame),
                   height_mm=round(float(size.height_mm), 1), width_mm=round(float(size.width_mm), 1),
                   depth_mm=round(float(size.depth_mm), 1), center=[float(v) for v in size.center],
                   extent=[float(v) for v in size.extent], R=np.asarray(size.R, float).tolist(),
                   n_points=int(size.n_points))

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "Measurement":
        return cls(**{f.name: d[f.name] for f in dataclasses.fields(cls)})

    def obb(self) -> o3d.geometry.OrientedBoundingBox:
        return o3d.geometry.OrientedBoundingBox(np.asarray(self.center, float), np.asarray(self.R, float),
                                                np.asarray(self.extent, float))


def ground_truth_size(meta: dict | None) -> dict | None:
    """The container's annotated size (mm) from a recording's meta (``container``: width_top_mm, width_bottom_mm,
    height_mm[, depth_mm]), or None when unknown. ``width_mm`` is the larger of top and bottom widths."""
    c = (meta or {}).get("container") or {}
    try:
        top, bottom, height = (float(c[k]) for k in ("width_top_mm", "width_bottom_mm", "height_mm"))
    except (KeyError, TypeError, ValueError):
        return None
    depth = float(c.get("depth_mm", -1) or -1)
    return {"height_mm": height, "width_top_mm": top, "width_bottom_mm": bottom, "width_mm": max(top, bottom),
            "depth_mm": depth}


def annotation_size(annotations, config_id) -> dict | None:
    """A CCM annotation row (``massviz.evaluate.read_annotations`` frame) as ``ground_truth_size`` input."""
    rows = annotations[annotations["id"].astype(str) == str(config_id)]
    if rows.empty:
        return None
    r = rows.iloc[0]
    return ground_truth_size({"container": {"width_top_mm": r["width at the top"],
                                            "width_bottom_mm": r["width at the bottom"], "height_mm": r["height"],
                                            "depth_mm": r.get("depth", -1)}})


def compare(m: Measurement, gt: dict | None) -> dict:
    """Measured vs annotated size: relative errors (%) of height and width, None where unknown."""
    if not gt:
        return {"height_err_pct": None, "width_err_pct": None}
    return {"height_err_pct": round(100 * (m.height_mm - gt["height_mm"]) / gt["height_mm"], 1),
            "width_err_pct": round(100 * (m.width_mm - gt["width_mm"]) / gt["width_mm"], 1)}


def _by_frame(indices, dets: Detections) -> dict[int, list[int]]:
    out: dict[int, list[int]] = {}
    for i in indices:
        out.setdefault(int(dets.frame[i]), []).append(int(i))
    return out


def measure(trace, recording, *, depth_trunc: float = DEPTH_TRUNC_M, band_m: float | None = BAND_M
            ) -> list[Measurement]:
    """Measure every chosen detection of ``trace`` (``trace.selection``, nearest first) from its cleaned cloud.

    Reads only the frames of the chosen detections. Returns [] for a recording without intrinsics (see
    ``skip_reason``) and skips detections whose cloud has fewer than 10 points.
    """
    if skip_reason(recording):
        return []
    intr = recording.intrinsics
    dets = trace.detections
    rank_of = {int(i): r for r, i in enumerate(trace.selection)}
    out = []
    groups = _by_frame(trace.selection, dets)
    for frame in recording.frames(indices=list(groups)):
        for i in groups[frame.index]:
            size = measure_cloud(detection_cloud(frame, dets, i, intr, depth_trunc=depth_trunc, band_m=band_m))
            if size is not None:
                out.append(Measurement.from_size(rank_of[i], i, frame.index, size))
    return sorted(out, key=lambda m: m.rank)


def with_measurements(trace, recording, **kw):
    """A copy of ``trace`` with ``measurements`` (``Measurement.to_dict()`` each) and the stage's wall time
    (``timings["measure3d"]``); an event records a skip for a recording without intrinsics."""
    t0 = time.perf_counter()
    ms = measure(trace, recording, **kw)
    timings = {**trace.timings, "measure3d": time.perf_counter() - t0}
    events = list(trace.events)
    reason = skip_reason(recording)
    if reason:
        events.append((-1, reason))
    for m in ms:
        events.append((m.frame, f"measured chosen patch {m.rank} (detection {m.detection}): height "
                                f"{m.height_mm:.0f} mm, width {m.width_mm:.0f} mm, depth {m.depth_mm:.0f} mm "
                                f"from {m.n_points} points"))
    return dataclasses.replace(trace, measurements=[m.to_dict() for m in ms], timings=timings, events=events)


def measurements_of(trace) -> list[Measurement]:
    """The trace's stored measurements as ``Measurement`` objects."""
    return [Measurement.from_dict(d) for d in getattr(trace, "measurements", None) or []]


# ------------------------------------------------------------------------------------------------ files
def save_cloud(path: str | Path, pcd: o3d.geometry.PointCloud) -> Path:
    """Write a binary .ply atomically (a reader never sees half a file)."""
    path = Path(path)
    with atomic_path(path) as tmp:
        if not o3d.io.write_point_cloud(str(tmp), pcd, write_ascii=False):
            raise MassvizError("Open3D could not write the point cloud", path)
    return path


def write_ply(out_dir: str | Path, trace, recording, *, frames=None, depth_trunc: float = DEPTH_TRUNC_M
              ) -> dict[str, int]:
    """Write .ply clouds into ``out_dir`` and return {file name: point count}.

    For each frame in ``frames`` (default: the frames of the chosen detections): ``scene_<frame>.ply`` (the whole
    frame) and ``detection_<id>.ply`` for every detection of that frame above the trace's threshold (``id`` = index
    in ``trace.detections``); the chosen ones also as ``chosen_<rank>.ply``. Nothing is written (and {} returned)
    for a recording without intrinsics.
    """
    if skip_reason(recording):
        return {}
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    intr, dets = recording.intrinsics, trace.detections
    rank_of = {int(i): r for r, i in enumerate(trace.selection)}
    if frames is None:
        frames = sorted({int(dets.frame[i]) for i in trace.selection})
    active = np.flatnonzero(trace.active())
    groups = _by_frame([i for i in active if int(dets.frame[i]) in set(int(f) for f in frames)], dets)
    written: dict[str, int] = {}
    for frame in recording.frames(indices=frames):
        scene = scene_cloud(frame, intr, depth_trunc=depth_trunc)
        written[save_cloud(out_dir / f"scene_{frame.index:06d}.ply", scene).name] = len(scene.points)
        for i in groups.get(frame.index, []):
            pcd = detection_cloud(frame, dets, i, intr, depth_trunc=depth_trunc)
            written[save_cloud(out_dir / f"detection_{i}.ply", pcd).name] = len(pcd.points)
            if i in rank_of:
                written[save_cloud(out_dir / f"chosen_{rank_of[i]}.ply", pcd).name] = len(pcd.points)
    return written


def write_ply_or_skip(out_dir: str | Path, trace, recording) -> str:
    """``write_ply`` with the default frames; returns the one line to print (what was written, or why nothing)."""
    reason = skip_reason(recording)
    if reason:
        return reason
    written = write_ply(out_dir, trace, recording)
    return f"{recording.id}: wrote {len(written)} .ply files to {out_dir}"


def box_lineset(obb: o3d.geometry.OrientedBoundingBox, colour=BOX_COLOUR) -> o3d.geometry.LineSet:
    ls = o3d.geometry.LineSet.create_from_oriented_bounding_box(obb)
    ls.paint_uniform_color(colour)
    return ls


# ------------------------------------------------------------------------------------------------ views
def frame_geometries(trace, recording, frame_index: int | None = None, *, depth_trunc: float = DEPTH_TRUNC_M
                     ) -> tuple[int, list[tuple[str, object]]]:
    """(frame, [(name, geometry)]) to draw: the scene cloud with the chosen detections' points recoloured
    (``CHOSEN_COLOUR``) and their oriented boxes as line sets. ``frame_index`` defaults to the frame of the nearest
    chosen detection (else the first processed frame)."""
    intr = require_intrinsics(recording)
    dets = trace.detections
    if frame_index is None:
        frame_index = (int(dets.frame[trace.selection[0]]) if len(trace.selection)
                       else int(trace.frames[0]) if len(trace.frames) else 0)
    frame = recording.read_frame(int(frame_index))
    chosen = [int(i) for i in trace.selection if int(dets.frame[i]) == frame.index]
    highlight = np.zeros((frame.height, frame.width), bool)
    for i in chosen:
        highlight |= dets.full_mask(i, frame.height, frame.width)
    depth = frame.depth
    scene = rgbd_cloud(frame.rgb, np.where(highlight, 0, depth).astype(np.uint16), intr, depth_trunc=depth_trunc)
    geoms: list[tuple[str, object]] = [("scene", scene)]
    stored = {m.detection: m for m in measurements_of(trace)}
    for r, i in enumerate(chosen):
        pcd = detection_cloud(frame, dets, i, intr, depth_trunc=depth_trunc)
        pcd.paint_uniform_color(CHOSEN_COLOUR)
        geoms.append((f"chosen_{i}", pcd))
        m = stored.get(i)
        size = measure_cloud(pcd) if m is None else None
        obb = m.obb() if m is not None else (size.obb() if size is not None else None)
        if obb is not None:
            geoms.append((f"box_{i}", box_lineset(obb)))
    return frame.index, geoms


def _look_at(eye: np.ndarray, target: np.ndarray, down=(0.0, 1.0, 0.0)) -> np.ndarray:
    """4×4 world-to-camera matrix (OpenCV camera: x right, y down, z forward) looking from ``eye`` at ``target``."""
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(np.asarray(down, float), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # rows: camera axes in world coordinates
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ eye
    return T


def view_extrinsic(target: np.ndarray, yaw_deg: float = 0.0, pitch_deg: float = 0.0) -> np.ndarray:
    """Extrinsic of a camera orbiting ``target`` from the recording camera's viewpoint by ``yaw`` (about the
    vertical, positive = from the right) and ``pitch`` (positive = from above). (0, 0) is the recording's camera."""
    if yaw_deg == 0 and pitch_deg == 0:
        return np.eye(4)
    target = np.asarray(target, float)
    r = float(np.linalg.norm(target))
    yaw, pitch = math.radians(yaw_deg), math.radians(pitch_deg)
    offset = r * np.array([math.sin(yaw) * math.cos(pitch), -math.sin(pitch), -math.cos(yaw) * math.cos(pitch)])
    return _look_at(target + offset, target)


def render_png(trace, recording, out: str | Path, *, frame_index: int | None = None, width: int = 960,
               height: int = 540, yaw_deg: float = 25.0, pitch_deg: float = 15.0, point_size: float = 2.0,
               background=(1.0, 1.0, 1.0)) -> dict:
    """Draw ``frame_geometries`` with Open3D's offscreen renderer (CPU: Filament on Mesa's llvmpipe, no display)
    into ``out`` (.png, atomically). The camera orbits the nearest chosen detection (or the scene's median point)
    from the recording camera's viewpoint by ``yaw_deg``/``pitch_deg``; 0/0 reproduces the recording's view.
    Returns {"frame", "path", "seconds"}."""
    t0 = time.perf_counter()
    intr = require_intrinsics(recording)
    frame, geoms = frame_geometries(trace, recording, frame_index)
    image = render_geometries(geoms, intr, width=width, height=height, yaw_deg=yaw_deg, pitch_deg=pitch_deg,
                              point_size=point_size, background=background)
    out = Path(out)
    with atomic_path(out) as tmp:
        if not o3d.io.write_image(str(tmp), o3d.geometry.Image(image)):
            raise MassvizError("Open3D could not write the image", out)
    return {"frame": frame, "path": str(out), "seconds": time.perf_counter() - t0}


def _orbit_target(geoms) -> np.ndarray:
    for name, g in geoms:
        if name.startswith("chosen_") and len(g.points):
            return np.asarray(g.get_center())
    pts = np.asarray(geoms[0][1].points)
    return np.median(pts, axis=0) if len(pts) else np.array([0.0, 0.0, 1.0])


def render_geometries(geoms, intr: Intrinsics, *, width: int = 960, height: int = 540, yaw_deg: float = 25.0,
                      pitch_deg: float = 15.0, point_size: float = 2.0, background=(1.0, 1.0, 1.0)) -> np.ndarray:
    """H×W×3 uint8 offscreen rendering of [(name, geometry)] through a pinhole like the recording's (scaled to
    ``width``×``height``). Without a display Open3D 0.20 renders headless with Filament's Vulkan backend on Mesa's
    llvmpipe (packages libvulkan1 and mesa-vulkan-drivers); no environment variable is needed."""
    from open3d.visualization import rendering

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    with _stdout_to_stderr():
        renderer = rendering.OffscreenRenderer(int(width), int(height))
        points = rendering.MaterialRecord()
        points.shader, points.point_size = "defaultUnlit", float(point_size) * width / 960
        lines = rendering.MaterialRecord()
        lines.shader, lines.line_width = "unlitLine", 3.0
        for name, g in geoms:
            renderer.scene.add_geometry(name, g, lines if isinstance(g, o3d.geometry.LineSet) else points)
        renderer.scene.set_background(list(background) + [1.0])
        s = min(width / intr.width, height / intr.height)
        K = np.array([[intr.fx * s, 0, width / 2 + (intr.cx - intr.width / 2) * s],
                      [0, intr.fy * s, height / 2 + (intr.cy - intr.height / 2) * s], [0, 0, 1]])
        renderer.setup_camera(K, view_extrinsic(_orbit_target(geoms), yaw_deg, pitch_deg), int(width), int(height))
        image = np.asarray(renderer.render_to_image()).copy()
        del renderer
    return image


@contextmanager
def _stdout_to_stderr():
    """Send what native code prints on stdout (Filament's start-up lines) to stderr while the block runs, so that
    commands keep stdout for their output."""
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        os.dup2(2, 1)
        yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)


def has_display() -> bool:
    """Whether an interactive window can open (X11 ``DISPLAY`` or ``WAYLAND_DISPLAY`` is set)."""
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def require_display() -> None:
    """``MassvizError`` (one line) when no interactive window can open."""
    if not has_display():
        raise MassvizError("no display (DISPLAY and WAYLAND_DISPLAY are unset): use 'massviz render REC --out "
                           "view.png' for a headless picture")


def show(trace, recording, frame_index: int | None = None) -> int:
    """Open Open3D's interactive window on ``frame_geometries``; ``MassvizError`` when there is no display."""
    require_display()
    frame, geoms = frame_geometries(trace, recording, frame_index)
    o3d.visualization.draw_geometries([g for _, g in geoms], window_name=f"massviz {recording.id} frame {frame}",
                                      front=[0, 0, -1], up=[0, -1, 0], lookat=_orbit_target(geoms), zoom=0.5)
    return frame


# ------------------------------------------------------------------------------------------------ Rerun
def log_frame_clouds(trace, frame: Frame, intr: Intrinsics, stream, *, root: str = "world/detections",
                     voxel_m: float = 0.004) -> list[str]:
    """Log each detection of ``frame`` (above the trace's threshold) as ``/<root>/<id>`` (Points3D, its colours;
    chosen ones in ``CHOSEN_COLOUR`` with their box as ``<id>/box`` Boxes3D labelled with the measured size).
    Call it with the stream's time already set to the frame. ``voxel_m`` thins the clouds (0: every point).
    Returns the entity paths logged."""
    import rerun as rr

    dets = trace.detections
    rank_of = {int(i): r for r, i in enumerate(trace.selection)}
    stored = {m.detection: m for m in measurements_of(trace)}
    idx = [int(i) for i in np.flatnonzero((dets.frame == frame.index) & trace.active())]
    paths = []
    for i in idx:
        pcd = detection_cloud(frame, dets, i, intr)
        if len(pcd.points) == 0:
            continue
        m = stored.get(i)
        size = None
        if i in rank_of and m is None:
            size = measure_cloud(pcd)
            m = Measurement.from_size(rank_of[i], i, frame.index, size) if size is not None else None
        shown = pcd.voxel_down_sample(voxel_m) if voxel_m > 0 else pcd
        pts = np.asarray(shown.points, np.float32)
        path = f"{root}/{i}"
        if i in rank_of:
            colours = np.tile((np.array(CHOSEN_COLOUR) * 255).astype(np.uint8), (len(pts), 1))
        else:
            colours = (np.asarray(shown.colors) * 255).astype(np.uint8)
        stream.log(path, rr.Points3D(pts, colors=colours, radii=0.002))
        if m is not None:
            label = f"#{m.rank} h {m.height_mm:.0f} w {m.width_mm:.0f} d {m.depth_mm:.0f} mm"
            stream.log(f"{path}/box", rr.Boxes3D(
                centers=[m.center], half_sizes=[np.asarray(m.extent) / 2],
                quaternions=[_quaternion_xyzw(np.asarray(m.R))],
                colors=[(np.array(BOX_COLOUR) * 255).astype(np.uint8)], labels=[label]))
            stream.log(f"{path}/measurement", rr.AnyValues(
                rank=m.rank, height_mm=m.height_mm, width_mm=m.width_mm, depth_mm=m.depth_mm, n_points=m.n_points))
        paths.append(path)
    return paths


def log_clouds(trace, recording, stream, *, timeline: str = "frame", root: str = "world/detections",
               voxel_m: float = 0.004) -> int:
    """Log every processed frame's detection clouds (``log_frame_clouds``) on ``timeline`` (sequence = frame index),
    clearing each frame's detection entities at the next processed frame so that none lingers. Returns the number of
    clouds logged; 0 (and nothing logged) for a recording without intrinsics."""
    import rerun as rr

    if skip_reason(recording):
        return 0
    dets = trace.detections
    with_dets = sorted({int(f) for f in dets.frame[trace.active()]})
    processed = [int(f) for f in trace.frames]
    n = 0
    shown: list[str] = []
    for frame in recording.frames(indices=sorted(set(with_dets) | set(processed))):
        stream.set_time(timeline, sequence=frame.index)
        for p in shown:
            stream.log(p, rr.Clear(recursive=True))
        shown = log_frame_clouds(trace, frame, recording.intrinsics, stream, root=root, voxel_m=voxel_m) \
            if frame.index in with_dets else []
        n += len(shown)
    return n


def _quaternion_xyzw(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w) of a rotation matrix."""
    m = np.asarray(R, float)
    w = math.sqrt(max(0.0, 1 + m[0, 0] + m[1, 1] + m[2, 2])) / 2
    x = math.copysign(math.sqrt(max(0.0, 1 + m[0, 0] - m[1, 1] - m[2, 2])) / 2, m[2, 1] - m[1, 2])
    y = math.copysign(math.sqrt(max(0.0, 1 - m[0, 0] + m[1, 1] - m[2, 2])) / 2, m[0, 2] - m[2, 0])
    z = math.copysign(math.sqrt(max(0.0, 1 - m[0, 0] - m[1, 1] + m[2, 2])) / 2, m[1, 0] - m[0, 1])
    q = np.array([x, y, z, w])
    return q / np.linalg.norm(q)


__all__ = [
    "DEPTH_TRUNC_M", "skip_reason", "require_intrinsics", "pinhole", "rgbd_cloud", "scene_cloud", "masked_cloud",
    "detection_cloud", "Size", "oriented_box", "vertical_axis", "view_aligned_box", "measure_cloud", "Measurement", "ground_truth_size",
    "annotation_size", "compare", "measure", "with_measurements", "measurements_of", "save_cloud", "write_ply", "write_ply_or_skip",
    "box_lineset", "frame_geometries", "render_png", "render_geometries", "view_extrinsic", "has_display",
    "require_display", "show",
    "log_frame_clouds", "log_clouds"]
