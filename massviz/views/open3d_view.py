"""Open3D as a sink: .ply files, the offscreen renderer and the interactive window, all drawn from a trace.

The clouds and measured boxes come from the measure stage (``massviz.measure3d.stage.MeasureStage``): this module only
writes and draws them (the scene around them is back-projected here, for the picture).
Axes are the camera frame (RDF: x right, y down, z forward); Open3D's viewers look down -z with y up, so the renderers
set their cameras accordingly.
"""
from __future__ import annotations

import math
import os
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from massviz._open3d import o3d
from massviz.core.types import Intrinsics
from massviz.errors import MassvizError
from massviz.io.atomic import atomic_path, native_stderr
from massviz.measure3d.geometry import DEPTH_TRUNC_M, measured_box, require_intrinsics, rgbd_cloud
from massviz.views.palette import BOX_COLOUR, CHOSEN_COLOUR, FLAGGED_COLOUR, rgb255


# ------------------------------------------------------------------------------------------------ files
def save_cloud(path: str | Path, pcd: o3d.geometry.PointCloud) -> Path:
    """Write a binary .ply atomically (a reader never sees half a file)."""
    path = Path(path)
    with atomic_path(path) as tmp:
        with native_stderr() as native:  # RPly prints one line per failed vertex (thousands on a full disk)
            ok = o3d.io.write_point_cloud(str(tmp), pcd, write_ascii=False)
        if not ok or native:
            import shutil

            why = native[0].strip()[:120] if native else "Open3D could not write the point cloud"
            raise MassvizError(f"cannot write the point cloud ({why}; {shutil.disk_usage(path.parent).free} bytes "
                               "free on its disk)", path)
    return path


class PlyFiles(dict):
    """{file name: point count} of the .ply files written, and ``empty``: the names of the clouds that had no point
    (a detection whose mask has no depth, a frame without depth within range), which are not written: a .ply of no
    point is no cloud, and Open3D refuses to write one."""

    def __init__(self):
        super().__init__()
        self.empty: list[str] = []

    def describe(self) -> str:
        """``12 .ply files`` (+ ``; detection_3.ply not written: no depth points`` for the empty ones)."""
        text = f"{len(self)} .ply files"
        if self.empty:
            text += f" ({', '.join(self.empty)} not written: no depth points)"
        return text


def write_ply(out_dir: str | Path, clouds) -> PlyFiles:
    """Write ``clouds`` ((file name, cloud) pairs, ``MeasureStage.ply_clouds``: the scene, each detection and the
    chosen ones of the chosen frames) into ``out_dir`` as binary .ply files and return them (``PlyFiles``: {file
    name: point count}, and the empty clouds left unwritten in ``.empty``). ``clouds`` None (a recording without
    intrinsics): nothing written, not even ``out_dir``."""
    written = PlyFiles()
    if clouds is None:
        return written
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    for name, pcd in clouds:
        if len(pcd.points) == 0:
            written.empty.append(name)
        else:
            written[save_cloud(out_dir / name, pcd).name] = len(pcd.points)
    return written


def write_ply_or_skip(out_dir: str | Path, clouds, *, recording_id: str, skip: str | None) -> str:
    """``write_ply``; returns the one line to print (what was written, or ``skip``: why nothing)."""
    if skip:
        return skip
    written = write_ply(out_dir, clouds)
    return f"{recording_id}: wrote {written.describe()} to {out_dir}"


def box_lineset(obb: o3d.geometry.OrientedBoundingBox, colour=BOX_COLOUR) -> o3d.geometry.LineSet:
    ls = o3d.geometry.LineSet.create_from_oriented_bounding_box(obb)
    ls.paint_uniform_color(colour)
    return ls


# ------------------------------------------------------------------------------------------------ views
def frame_geometries(trace, recording, clouds: dict, frame_index: int | None = None, *,
                     depth_trunc: float = DEPTH_TRUNC_M) -> tuple[int, list[tuple[str, object]]]:
    """(frame, [(name, geometry)]) to draw: the scene cloud with the chosen detections' clouds (``clouds``:
    {detection: cleaned cloud} of the chosen ones, ``MeasureStage.clouds_of``) recoloured
    (``CHOSEN_COLOUR``, flagged ones ``FLAGGED_COLOUR``: the palette the Rerun and notebook views use) and their
    oriented boxes as line sets (a flagged one's in ``FLAGGED_COLOUR``). ``frame_index`` defaults to the frame of the
    nearest chosen detection; a frame without a chosen patch (or a trace without any) is a ``MassvizError`` naming
    the frames that have one (a view orbiting nothing in particular is unreadable)."""
    intr = require_intrinsics(recording)
    dets = trace.detections
    chosen_frames = sorted({int(dets.frame[i]) for i in trace.selection})
    if not chosen_frames:
        raise MassvizError("no patch was chosen in this recording (not estimated): there is no container to show",
                           recording.path)
    if frame_index is None:
        frame_index = int(dets.frame[trace.selection[0]])
    elif int(frame_index) not in chosen_frames:
        raise MassvizError(f"frame {int(frame_index)} has no chosen patch, so there is no container to centre the "
                           f"view on; chosen patches are in frame(s) {', '.join(map(str, chosen_frames))} (or leave "
                           "out the frame for the nearest one)", recording.path)
    frame = recording.read_frame(int(frame_index))
    chosen = [int(i) for i in trace.selection if int(dets.frame[i]) == frame.index]
    highlight = np.zeros((frame.height, frame.width), bool)
    for i in chosen:
        highlight |= dets.full_mask(i, frame.height, frame.width)
    depth = frame.depth
    scene = rgbd_cloud(frame.rgb, np.where(highlight, 0, depth).astype(np.uint16), intr, depth_trunc=depth_trunc)
    geoms: list[tuple[str, object]] = [("scene", scene)]
    stored = {m.detection: m for m in trace.measurements}
    for i in chosen:
        pcd = o3d.geometry.PointCloud(clouds[i])  # a copy: the stage's cloud keeps its colours
        flag = trace.flags.of(i)
        flagged = flag is not None and flag.flagged
        pcd.paint_uniform_color(FLAGGED_COLOUR if flagged else CHOSEN_COLOUR)
        geoms.append((f"chosen_{i}", pcd))
        m = stored.get(i)  # measured by the measure stage (``Trace.measurements``): a view never measures
        if m is not None:
            geoms.append((f"box_{i}", box_lineset(measured_box(m), FLAGGED_COLOUR if flagged else BOX_COLOUR)))
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


def render_png(trace, recording, clouds: dict, out: str | Path, *, frame_index: int | None = None, width: int = 960,
               height: int = 540, yaw_deg: float = 25.0, pitch_deg: float = 15.0, point_size: float = 2.0,
               background=(1.0, 1.0, 1.0)) -> dict:
    """Draw ``frame_geometries`` (``clouds``: see there) with Open3D's offscreen renderer (CPU: Filament on Mesa's llvmpipe, no display)
    into ``out`` (.png, atomically). The camera orbits the nearest chosen detection (or the scene's median point)
    from the recording camera's viewpoint by ``yaw_deg``/``pitch_deg``; 0/0 reproduces the recording's view.
    A caption names the frame and each chosen patch drawn, a flagged one as FLAGGED with why (``trace.flags``).
    Returns {"frame", "path", "seconds", "chosen" (ranks drawn), "flagged" (their ``PatchFlag``s)}."""
    t0 = time.perf_counter()
    intr = require_intrinsics(recording)
    frame, geoms = frame_geometries(trace, recording, clouds, frame_index)
    image = render_geometries(geoms, intr, width=width, height=height, yaw_deg=yaw_deg, pitch_deg=pitch_deg,
                              point_size=point_size, background=background)
    here = [p for p in trace.flags.patches if p.frame == frame]
    image = _caption(image, f"{recording.id} - frame {frame}", here)
    out = Path(out)
    with atomic_path(out) as tmp:
        if not o3d.io.write_image(str(tmp), o3d.geometry.Image(image)):
            raise MassvizError("Open3D could not write the image", out)
    return {"frame": frame, "path": str(out), "seconds": time.perf_counter() - t0, "chosen": [p.rank for p in here],
            "flagged": [p for p in here if p.flagged]}


def _caption(image: np.ndarray, title: str, patches) -> np.ndarray:
    """The rendered image with a caption strip on top: ``title`` and one line per chosen patch of the frame, in the
    palette's chosen colour, or its flagged colour with "FLAGGED" and why (OpenCV's fonts are ASCII-only)."""
    import cv2

    scale = max(image.shape[1] / 960, 0.5)
    line_h = int(round(22 * scale))
    lines = [(title, (40, 40, 40))]
    for p in patches:
        if p.flagged:
            why = (f"ground truth: the {p.ground_truth}" if p.ground_truth is not None
                   else "cues: " + ", ".join(k.replace("_", " ") for k in p.cue_kinds))
            lines.append((f"chosen patch rank {p.rank} (track {p.track}): FLAGGED, probably not the container ({why})",
                          rgb255(FLAGGED_COLOUR)))
        else:
            lines.append((f"chosen patch rank {p.rank} (track {p.track})", rgb255(CHOSEN_COLOUR)))
    out = np.ascontiguousarray(image[..., :3]).copy()
    strip = out[: line_h * len(lines) + line_h // 2]
    strip[:] = (0.35 * strip + 0.65 * 255).astype(np.uint8)
    for n, (text, colour) in enumerate(lines):
        cv2.putText(out, text.encode("ascii", "replace").decode(), (int(8 * scale), line_h * (n + 1)),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.5 * scale, tuple(int(c) for c in colour), max(1, int(round(scale))),
                    cv2.LINE_AA)
    return out


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
    with _native_output_captured():
        renderer = rendering.OffscreenRenderer(int(width), int(height))
        points = rendering.MaterialRecord()
        points.shader, points.point_size = "defaultUnlit", float(point_size) * width / 960
        lines = rendering.MaterialRecord()
        lines.shader, lines.line_width = "unlitLine", 3.0
        for name, g in geoms:
            renderer.scene.add_geometry(name, g, lines if isinstance(g, o3d.geometry.LineSet) else points)
        renderer.scene.set_background(list(background) + [1.0])
        # no post-processing: the palette's and the frame's colours come out as they are (Filament's default tone
        # mapping washes them out: the flagged red (255, 59, 48) became (235, 159, 141), unlike the other views)
        renderer.scene.view.set_post_processing(False)
        s = min(width / intr.width, height / intr.height)
        K = np.array([[intr.fx * s, 0, width / 2 + (intr.cx - intr.width / 2) * s],
                      [0, intr.fy * s, height / 2 + (intr.cy - intr.height / 2) * s], [0, 0, 1]])
        renderer.setup_camera(K, view_extrinsic(_orbit_target(geoms), yaw_deg, pitch_deg), int(width), int(height))
        image = np.asarray(renderer.render_to_image()).copy()
        del renderer
    return image


@contextmanager
def _native_output_captured():
    """Capture what native code prints on stdout and stderr while the block runs (Filament's start-up lines:
    "FEngine ...", "Vulkan device driver ..."), so that neither a command's output nor a notebook cell is cluttered
    with them; when the block fails they are written to stderr, where they may explain why."""
    import tempfile

    sys.stdout.flush()
    sys.stderr.flush()
    saved = os.dup(1), os.dup(2)
    with tempfile.TemporaryFile() as log:
        failed = False
        try:
            os.dup2(log.fileno(), 1)
            os.dup2(log.fileno(), 2)
            yield
        except BaseException:
            failed = True
            raise
        finally:
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            os.close(saved[0])
            os.close(saved[1])
            if failed:
                log.seek(0)
                sys.stderr.write(log.read().decode(errors="replace"))


def has_display() -> bool:
    """Whether an interactive window can open (X11 ``DISPLAY`` or ``WAYLAND_DISPLAY`` is set)."""
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def require_display() -> None:
    """``MassvizError`` (one line) when no interactive window can open."""
    if not has_display():
        raise MassvizError("no display (DISPLAY and WAYLAND_DISPLAY are unset): use 'massviz render REC --out "
                           "view.png' for a headless picture")


def show(trace, recording, clouds: dict, frame_index: int | None = None) -> int:
    """Open Open3D's interactive window on ``frame_geometries``; ``MassvizError`` when there is no display."""
    require_display()
    frame, geoms = frame_geometries(trace, recording, clouds, frame_index)
    o3d.visualization.draw_geometries([g for _, g in geoms], window_name=f"massviz {recording.id} frame {frame}",
                                      front=[0, 0, -1], up=[0, -1, 0], lookat=_orbit_target(geoms), zoom=0.5)
    return frame



__all__ = ["save_cloud", "PlyFiles", "write_ply", "write_ply_or_skip", "box_lineset", "frame_geometries", "render_png",
           "render_geometries", "view_extrinsic", "has_display", "require_display", "show"]
