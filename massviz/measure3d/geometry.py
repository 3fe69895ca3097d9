"""The measure stage's geometry, through Open3D: back-projected clouds, each detection's masked cloud, its measured
size. ``massviz.measure3d.stage`` runs it on a recording; nothing in ``massviz.core`` imports it, so a run that does
not measure never loads Open3D.

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

A recording without intrinsics has no metric 3D: the measure stage measures nothing and ``skip_reason`` says why
in one line.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from massviz._open3d import o3d
from massviz.core.measurement import Measurement
from massviz.core.types import Detections, Frame, GroundTruth, Intrinsics
from massviz.io.ccm_annotations import annotation_of
from massviz.measure3d.settings import BAND_M, DEPTH_TRUNC_M, require_intrinsics, skip_reason

#: ``remove_statistical_outlier`` settings: neighbours, standard-deviation ratio.
SOR_NEIGHBOURS = 20
SOR_STD_RATIO = 2.0


# ------------------------------------------------------------------------------------------------ intrinsics
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
    median and statistical outlier removal (module docstring). Only the mask's bounding rectangle is back-projected
    (``Crop``): the same points, in the same order, as the whole frame would give."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if rows.size == 0:
        return o3d.geometry.PointCloud()
    crop = Crop.of(frame, (int(cols[0]), int(rows[0]), int(cols[-1]) + 1, int(rows[-1]) + 1),
                   mask[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1])
    return crop.cloud(intr, depth_trunc=depth_trunc, band_m=band_m, clean=clean)


def detection_cloud(frame: Frame, dets: Detections, i: int, intr: Intrinsics, **kw) -> o3d.geometry.PointCloud:
    """Cleaned cloud of detection ``i`` (its box's pixels under its mask)."""
    return Crop.of_detection(frame, dets, i).cloud(intr, **kw)


@dataclass
class Crop:
    """What the measure stage needs of one detection: the RGB and depth inside a rectangle ``xyxy`` of frame
    ``frame`` (copies, so a reader may reuse its buffers) and the boolean mask over it. Back-projecting the crop with
    the principal point shifted by the rectangle's corner gives exactly the points of the same pixels in the full
    frame (pixel (u, v) of the crop is (u + x1, v + y1) of the frame), so a crop can be kept from a frame and its
    cloud made later."""

    frame: int
    xyxy: tuple[int, int, int, int]
    rgb: np.ndarray
    depth: np.ndarray
    mask: np.ndarray

    @classmethod
    def of(cls, frame: Frame, xyxy, mask: np.ndarray) -> "Crop":
        x1, y1, x2, y2 = (int(v) for v in xyxy)
        return cls(frame.index, (x1, y1, x2, y2), frame.rgb[y1:y2, x1:x2].copy(), frame.depth[y1:y2, x1:x2].copy(),
                   np.asarray(mask, dtype=bool))

    @classmethod
    def of_detection(cls, frame: Frame, dets: Detections, i: int) -> "Crop":
        return cls.of(frame, dets.xyxy[i], dets.mask(i))

    def cloud(self, intr: Intrinsics, *, depth_trunc: float = DEPTH_TRUNC_M, band_m: float | None = BAND_M,
              clean: bool = True) -> o3d.geometry.PointCloud:
        x1, y1, x2, y2 = self.xyxy
        if x2 <= x1 or y2 <= y1:
            return o3d.geometry.PointCloud()
        depth = np.where(self.mask, self.depth, 0).astype(np.uint16)
        if clean and band_m is not None:
            z = depth[depth > 0]
            if z.size:
                med = float(np.median(z))
                depth[np.abs(depth.astype(np.float64) - med) > band_m * 1000.0] = 0
        shifted = Intrinsics(intr.fx, intr.fy, intr.cx - x1, intr.cy - y1, x2 - x1, y2 - y1)
        pcd = rgbd_cloud(self.rgb, depth, shifted, depth_trunc=depth_trunc)
        if clean and len(pcd.points) > SOR_NEIGHBOURS:
            pcd, _ = pcd.remove_statistical_outlier(nb_neighbors=SOR_NEIGHBOURS, std_ratio=SOR_STD_RATIO)
        return pcd


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


def measurement_of(size: Size, *, rank: int, detection: int, frame: int) -> Measurement:
    """A ``Size`` as the ``Measurement`` a trace carries (lengths rounded to 0.1 mm, plain lists)."""
    return Measurement(rank=int(rank), detection=int(detection), frame=int(frame),
                       height_mm=round(float(size.height_mm), 1), width_mm=round(float(size.width_mm), 1),
                       depth_mm=round(float(size.depth_mm), 1), center=[float(v) for v in size.center],
                       extent=[float(v) for v in size.extent], R=np.asarray(size.R, float).tolist(),
                       n_points=int(size.n_points))


def measured_box(m: Measurement) -> o3d.geometry.OrientedBoundingBox:
    """A measurement's box as an Open3D ``OrientedBoundingBox``."""
    return o3d.geometry.OrientedBoundingBox(np.asarray(m.center, float), np.asarray(m.R, float),
                                            np.asarray(m.extent, float))


def measure_cloud_as(pcd: o3d.geometry.PointCloud, *, rank: int, detection: int, frame: int) -> Measurement | None:
    """``measure_cloud`` as a ``Measurement``; None with fewer than 10 points."""
    size = measure_cloud(pcd)
    return None if size is None else measurement_of(size, rank=rank, detection=detection, frame=frame)


def measure_detection(frame: Frame, dets: Detections, i: int, intr: Intrinsics, *, detection: int | None = None,
                      rank: int = -1, depth_trunc: float = DEPTH_TRUNC_M, band_m: float | None = BAND_M
                      ) -> Measurement | None:
    """The measured size of detection ``i`` of ``dets`` (detections of ``frame``) from its cleaned cloud, as a
    ``Measurement`` (``detection``: its index in the trace, default ``i``; ``rank`` its rank in the selection, -1
    unknown); None when its cloud has fewer than 10 points."""
    return measure_crop(Crop.of_detection(frame, dets, i), intr, detection=i if detection is None else detection,
                        rank=rank, depth_trunc=depth_trunc, band_m=band_m)


def measure_crop(crop: Crop, intr: Intrinsics, *, detection: int, rank: int = -1,
                 depth_trunc: float = DEPTH_TRUNC_M, band_m: float | None = BAND_M) -> Measurement | None:
    """``measure_detection`` on a kept ``Crop``."""
    return measure_cloud_as(crop.cloud(intr, depth_trunc=depth_trunc, band_m=band_m), rank=rank,
                            detection=detection, frame=crop.frame)


def ground_truth_size(meta: dict | None) -> dict | None:
    """The container's annotated size (mm) from a recording's meta (``GroundTruth.size``: height, top/bottom
    widths, ``width_mm`` the larger of the two, depth), or None when unknown."""
    gt = GroundTruth.from_meta(meta)
    return None if gt is None else gt.size()


def annotation_size(annotations, config_id) -> dict | None:
    """The annotated size (``ground_truth_size``) of recording ``config_id`` in a CCM annotation table
    (``massviz.io.ccm_annotations.read_annotations``), or None when it has no row (or no integer id)."""
    try:
        row = annotation_of(annotations, int(config_id))
    except (TypeError, ValueError):
        return None
    if row is None:
        return None
    return ground_truth_size({"container": {"width_top_mm": row.width_top_mm, "width_bottom_mm": row.width_bottom_mm,
                                            "height_mm": row.height_mm,
                                            "depth_mm": -1 if math.isnan(row.depth_mm) else row.depth_mm}})


def compare(m: Measurement, gt: dict | None) -> dict:
    """Measured vs annotated size: relative errors (%) of height and width, None where unknown."""
    if not gt:
        return {"height_err_pct": None, "width_err_pct": None}
    return {"height_err_pct": round(100 * (m.height_mm - gt["height_mm"]) / gt["height_mm"], 1),
            "width_err_pct": round(100 * (m.width_mm - gt["width_mm"]) / gt["width_mm"], 1)}


def depth_to_points(depth: np.ndarray, intrinsics: Intrinsics, rgb: np.ndarray | None = None,
                    step: int = 4) -> tuple[np.ndarray, np.ndarray | None]:
    """Back-project every ``step``-th pixel with depth through Open3D (``rgbd_cloud``, the same
    back-projection as the 3D stage, within its ``DEPTH_TRUNC_M``): (N×3 float32 metres in the RDF camera frame,
    N×3 uint8 RGB colours or None). Subsampling scales the intrinsics, so a point is exactly its full-size pixel's."""
    sub = depth[::step, ::step]
    intr = Intrinsics(intrinsics.fx / step, intrinsics.fy / step, intrinsics.cx / step, intrinsics.cy / step,
                      sub.shape[1], sub.shape[0])
    colour = np.zeros((*sub.shape, 3), np.uint8) if rgb is None else rgb[::step, ::step]
    pcd = rgbd_cloud(colour, sub, intr)
    points = np.asarray(pcd.points, dtype=np.float32)
    colours = None if rgb is None else np.round(np.asarray(pcd.colors) * 255).astype(np.uint8)
    return points, colours


__all__ = [
    "DEPTH_TRUNC_M", "BAND_M", "skip_reason", "require_intrinsics", "pinhole", "rgbd_cloud", "scene_cloud",
    "masked_cloud", "detection_cloud", "Crop", "Size", "oriented_box", "vertical_axis", "view_aligned_box",
    "measure_cloud", "measurement_of", "measured_box", "measure_cloud_as", "measure_detection", "measure_crop",
    "ground_truth_size", "annotation_size", "compare", "depth_to_points"]
