"""Synthetic hand-over recordings with ground truth, rendered on the CPU with Open3D's ``RaycastingScene``.

Each sample is a short RGB-D recording from a fixed frontal camera (a RealSense-like camera scaled to 480×270): a
person walks towards the camera and hands over a container (cup, glass or box) while a pitcher stands on the table
between them. Early in the hand-over the pitcher is nearer to the camera than the container — the failure case of
"the manipulated container is the nearest object" — and late in it the container is the nearest object. The person
holds the container from behind, so the camera sees all of it (``container_occluded`` in meta.json). In
``cup_handover`` a hand lifts the pitcher towards the camera for a few frames, nearer than the cup ever comes: there
the K nearest detections include pitcher patches.

Everything is built from a handful of primitives (surfaces of revolution, cuboids). Per frame one ray per pixel is
cast (``cast_rays`` → ``t_hit``, ``geometry_ids``, ``primitive_ids``, ``primitive_normals``); RGB is shaded here
(Lambert with a point light near the camera, per-triangle albedo) and depth gets a stereo-camera error model:
disparity noise and quantisation (depth error grows with the square of the distance), stereo shadows (no depth beside
the left edge of foreground objects), random dropouts, and a transparent glass that returns depth only at its rim,
its silhouette and its thick base.

The output follows massviz's recording layout (see ``write_sample``) plus ground truth: per-frame instance masks and
``meta.json``. Generation is deterministic: the same code writes the same bytes.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable

import cv2
import numpy as np

from massviz import __version__
from massviz._open3d import o3d
from massviz.core.types import Intrinsics
from massviz.io.atomic import atomic_dir, check_replaceable
from massviz.io.formats.folder import FolderFrameWriter
from massviz.samples.specs import (  # noqa: F401
    CONTAINER,
    FPS,
    HAND,
    INSTANCES,
    INTRINSICS,
    N_FRAMES,
    PERSON,
    PITCHER,
    PITCHER_LIFT,
    SAMPLES,
    TABLE,
    Container,
    SampleSpec,
)

# Stereo depth model. The sensor's disparity is computed at its native resolution (focal 640 px, 50 mm baseline) and
# quantised to 1/8 px, so depth steps and noise grow with z²: about 4 mm / 2.5 mm at 1 m, 10 mm / 6 mm at 1.6 m.
_SENSOR_FB = 640.0 * 0.050  # focal length (px) × baseline (m)
_SUBPIXEL = 1.0 / 8.0
_DISPARITY_NOISE = 0.08  # px, smooth (spatially correlated) part
_SHADOW_FB = INTRINSICS.fx * 0.035  # width of the stereo shadow, in output pixels × m
_DROPOUT = 0.004  # fraction of pixels lost at random, as single pixels
_MAX_RANGE = 3.0  # m; farther returns are dropped

_LIGHT = np.array([-0.5, -0.9, 0.1])  # point light, camera coordinates (m): up and left of the camera
_AMBIENT = 0.3


# --------------------------------------------------------------------------------------------------- geometry


@dataclass
class Part:
    """A triangle mesh in camera coordinates (m; x right, y down, z forward) with per-triangle albedo."""

    vertices: np.ndarray  # V×3 float
    triangles: np.ndarray  # T×3 int
    albedo: np.ndarray  # T×3 uint8
    instance: int
    glass: bool = False


def _rot_x(deg: float) -> np.ndarray:
    return o3d.geometry.get_rotation_matrix_from_axis_angle(np.array([np.radians(deg), 0.0, 0.0]))


def _rot_y(deg: float) -> np.ndarray:
    return o3d.geometry.get_rotation_matrix_from_axis_angle(np.array([0.0, np.radians(deg), 0.0]))


#: Local "up" (+y, heights of lathe profiles) to camera coordinates (y down): half a turn about x.
_UPRIGHT = _rot_x(180.0)


def _rotation_to(direction: np.ndarray) -> np.ndarray:
    """A rotation taking local +y onto ``direction`` (Open3D's axis-angle rotation about their cross product)."""
    a = np.array([0.0, 1.0, 0.0])
    b = direction / np.linalg.norm(direction)
    v, c = np.cross(a, b), float(np.clip(a @ b, -1.0, 1.0))
    if np.linalg.norm(v) < 1e-9:
        return np.eye(3) if c > 0 else _rot_x(180.0)
    return o3d.geometry.get_rotation_matrix_from_axis_angle(v / np.linalg.norm(v) * np.arccos(c))


def lathe(profile: Iterable[tuple[float, float]], segments: int = 48):
    """Surface of revolution about local +y of a closed profile of (radius, height) points (m).

    Returns vertices (V×3), triangles (T×3) and, per triangle, the index of the profile segment it comes from.
    A profile that starts and ends on the axis (radius 0) gives a closed solid.
    """
    prof = np.asarray(list(profile), dtype=np.float64)
    ang = 2 * np.pi * np.arange(segments) / segments
    verts = np.stack([prof[:, None, 0] * np.cos(ang), np.repeat(prof[:, None, 1], segments, 1),
                      prof[:, None, 0] * np.sin(ang)], axis=-1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(len(prof) - 1), np.arange(segments), indexing="ij")
    a, b = i * segments + j, i * segments + (j + 1) % segments
    c, d = a + segments, b + segments
    tris = np.concatenate([np.stack([a, c, b], -1), np.stack([b, c, d], -1)], axis=1).reshape(-1, 3)
    seg = np.repeat(i.reshape(-1), 2)
    return verts, tris, seg


def cuboid(size: tuple[float, float, float]):
    """Axis-aligned box centred on the origin; per triangle the index of its face (-x, +x, -y, +y, -z, +z)."""
    h = np.asarray(size, dtype=np.float64) / 2
    verts = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * h
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    tris = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])
    return verts, tris, np.repeat(np.arange(6), 2)


def _part(verts, tris, albedo, instance, rotation=None, translation=(0, 0, 0), glass=False) -> Part:
    albedo = np.asarray(albedo, dtype=np.uint8)
    if albedo.ndim == 1:
        albedo = np.tile(albedo, (len(tris), 1))
    rotation = np.eye(3) if rotation is None else np.asarray(rotation)
    return Part(verts @ rotation.T + np.asarray(translation), tris, albedo, instance, glass)


def _ellipsoid(radii, albedo, instance, rotation, centre) -> Part:
    t = np.linspace(-np.pi / 2, np.pi / 2, 13)
    v, f, _ = lathe(zip(np.cos(t), np.sin(t)), segments=24)
    return _part(v * np.asarray(radii), f, albedo, instance, rotation, centre)


def _capsule(a, b, radius, albedo, instance) -> Part:
    """Cylinder with rounded ends from point ``a`` to point ``b``."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    length = float(np.linalg.norm(b - a))
    t = np.linspace(-np.pi / 2, 0, 5)
    bottom = [(radius * np.cos(x), radius * np.sin(x)) for x in t]
    top = [(r, length - h) for r, h in reversed(bottom)]
    v, f, _ = lathe(bottom + top, segments=20)
    return _part(v, f, albedo, instance, _rotation_to(b - a), a)


def container_parts(c: Container, centre: np.ndarray, yaw_deg: float) -> list[Part]:
    """The container, upright with its centre at ``centre``, turned by ``yaw_deg`` about the vertical."""
    w_top, w_bot, h = c.width_top_mm / 1000, c.width_bottom_mm / 1000, c.height_mm / 1000
    rot = _rot_y(yaw_deg) @ _UPRIGHT
    origin = centre + np.array([0.0, h / 2, 0.0])  # profiles start at the bottom (y down: + h/2)
    if c.cls == "box":
        v, f, face = cuboid((w_top, h, c.depth_mm / 1000))
        albedo = np.where((face == 4)[:, None], c.accent, c.colour)  # face -z faces the camera
        return [_part(v, f, albedo, CONTAINER, _rot_y(yaw_deg), centre)]
    wall, base = (0.0015, 0.003) if c.cls == "cup" else (0.003, 0.018)
    rb, rt = w_bot / 2, w_top / 2
    inner_b = rb + (rt - rb) * base / h - wall
    band = (0.35, 0.6)  # printed band on the outside of a cup, between these fractions of its height
    outside = [(rb + (rt - rb) * f, f * h) for f in (0.0, *band, 1.0)]
    profile = [(0, 0), *outside, (rt - wall, h), (inner_b, base), (0, base)]
    v, f, seg = lathe(profile, segments=64)
    if c.cls == "cup":
        albedo = np.where((seg == 2)[:, None], c.accent, c.colour)
    else:
        albedo = c.colour
    return [_part(v, f, albedo, CONTAINER, rot, origin, glass=c.cls == "glass")]


def pitcher_parts(x: float, z: float, base_y: float) -> list[Part]:
    """A 21 cm plastic pitcher with its base at height ``base_y`` (the table top when it stands), handle on its left."""
    profile = [(0, 0), (0.058, 0), (0.066, 0.06), (0.062, 0.14), (0.052, 0.19), (0.058, 0.21), (0, 0.21)]
    v, f, _ = lathe(profile, segments=48)
    body = _part(v, f, (120, 170, 205), PITCHER, _UPRIGHT, (x, base_y, z))
    handle = _capsule((x - 0.05, base_y - 0.17, z + 0.01), (x - 0.095, base_y - 0.11, z + 0.01), 0.011,
                      (100, 150, 190), PITCHER)
    grip = _capsule((x - 0.095, base_y - 0.11, z + 0.01), (x - 0.06, base_y - 0.04, z + 0.01), 0.011,
                    (100, 150, 190), PITCHER)
    return [body, handle, grip]


def lifting_hand_parts(x: float, z: float, base_y: float, shirt) -> list[Part]:
    """The hand lifting the pitcher at (``x``, ``base_y``, ``z``): its palm on the back of the pitcher and its forearm
    straight back along the line of sight, so the pitcher hides both (like the container, it is seen whole)."""
    palm = np.array([x, base_y - 0.1, z + 0.066 + 0.018])
    ray = palm / np.linalg.norm(palm)
    return [
        _ellipsoid((0.036, 0.045, 0.016), (214, 168, 140), HAND, np.eye(3), palm),
        _capsule(palm + 0.03 * ray, palm + 0.3 * ray, 0.03, shirt, PERSON),
    ]


def _elbow(shoulder: np.ndarray, wrist: np.ndarray, upper: float, fore: float) -> np.ndarray:
    """Two-link inverse kinematics: the elbow, bent outwards and down (the wrist is clamped into reach)."""
    d = wrist - shoulder
    dist = float(np.clip(np.linalg.norm(d), 1e-3, upper + fore - 1e-3))
    u = d / np.linalg.norm(d)
    along = (upper**2 - fore**2 + dist**2) / (2 * dist)
    off = np.sqrt(max(upper**2 - along**2, 0.0))
    bend = np.array([0.4, 1.0, 0.0])  # outwards (+x) and down (+y)
    bend = bend - (bend @ u) * u
    return shoulder + along * u + off * bend / np.linalg.norm(bend)


def person_parts(palm: np.ndarray, shoulder: np.ndarray, shirt) -> list[Part]:
    """Hand holding the container from behind (palm centred at ``palm``, just behind the container's back as seen
    from the camera, so the camera sees all of the container), arm to ``shoulder``, torso and head."""
    skin = (214, 168, 140)
    wrist = palm + np.array([0.015, 0.03, 0.065])
    elbow = _elbow(shoulder, wrist, 0.30, 0.27)
    torso_c = shoulder + np.array([-0.19, 0.26, 0.06])
    parts = [
        _ellipsoid((0.036, 0.045, 0.016), skin, HAND, np.eye(3), palm),
        _ellipsoid((0.011, 0.025, 0.011), skin, HAND, _rot_x(-25), palm + np.array([0.02, -0.025, 0.006])),
        _capsule(wrist, elbow, 0.036, shirt, PERSON),
        _capsule(elbow, shoulder, 0.045, shirt, PERSON),
        _ellipsoid((0.2, 0.3, 0.11), shirt, PERSON, np.eye(3), torso_c),
        _ellipsoid((0.085, 0.11, 0.1), skin, PERSON, np.eye(3), torso_c + np.array([0.0, -0.42, 0.0])),
    ]
    return parts


def static_parts(table_y: float) -> list[Part]:
    """Table (top at ``table_y``) and the back wall."""
    v, f, face = cuboid((1.6, 0.04, 1.6))
    table_albedo = np.where((face == 2)[:, None], (150, 112, 76), (120, 86, 58))  # -y: the top
    wall_v, wall_f, _ = cuboid((6.0, 4.0, 0.02))
    return [
        _part(v, f, table_albedo, TABLE, np.eye(3), (0.0, table_y + 0.02, 1.5)),
        _part(wall_v, wall_f, (190, 196, 188), 0, np.eye(3), (0.0, 0.0, 2.6)),
    ]


_TABLE_Y = 0.27  # table top, 27 cm below the camera


def frame_parts(spec: SampleSpec, t: float) -> list[Part]:
    """Every part of the scene at hand-over time ``t`` in [0, 1]."""
    s = float(np.clip(t / 0.85, 0, 1))
    s = s * s * (3 - 2 * s)  # ease in and out, then hold while the robot grasps
    start, end = np.asarray(spec.start), np.asarray(spec.end)
    centre = start + s * (end - start) + np.array([0.0, -0.05 * np.sin(np.pi * s), 0.0])
    yaw = spec.yaw_deg[0] + s * (spec.yaw_deg[1] - spec.yaw_deg[0])
    c = spec.container
    if c.cls == "box":  # half its extent along the line of sight, turned by yaw
        back = (c.width_top_mm * abs(np.sin(np.radians(yaw))) + c.depth_mm * abs(np.cos(np.radians(yaw)))) / 2000
    else:
        back = max(c.width_top_mm, c.width_bottom_mm) / 2000
    shoulder = np.array([0.22, -0.17, 1.9 + s * (1.02 - 1.9)])
    # 2 cm behind the back of the container (depth cannot tell a hand touching it from the container)
    palm = centre + np.array([0.005, 0.0, back + 0.036])
    return [*container_parts(c, centre, yaw), *person_parts(palm, shoulder, spec.shirt),
            *static_parts(_TABLE_Y), *pitcher_at(spec, t)]


def pitcher_at(spec: SampleSpec, t: float) -> list[Part]:
    """The pitcher at hand-over time ``t``: on the table, or lifted (with the hand lifting it) during ``pitcher_lift``."""
    x, z = spec.pitcher_xz
    if spec.pitcher_lift is None or not spec.pitcher_lift[0] < t < spec.pitcher_lift[1]:
        return pitcher_parts(x, z, _TABLE_Y)
    t0, t1, peak = spec.pitcher_lift
    u = np.sin(np.pi * (t - t0) / (t1 - t0)) ** 2  # 0 → 1 → 0, smoothly
    px, py, pz = np.array([x, _TABLE_Y, z]) + u * (np.asarray(peak) - np.array([x, _TABLE_Y, z]))
    return [*pitcher_parts(px, pz, py), *lifting_hand_parts(px, pz, py, spec.shirt)]


# --------------------------------------------------------------------------------------------------- rendering


@dataclass
class Hits:
    """Per-pixel result of casting one ray per pixel: z-depth (m, inf = miss), part index (-1), normal."""

    z: np.ndarray
    part: np.ndarray
    triangle: np.ndarray
    normal: np.ndarray


def _rays(k: Intrinsics) -> o3d.core.Tensor:
    return o3d.t.geometry.RaycastingScene.create_rays_pinhole(
        o3d.core.Tensor(k.matrix), o3d.core.Tensor(np.eye(4)), k.width, k.height)


def cast(parts: list[Part], rays: o3d.core.Tensor) -> Hits:
    """Ray-cast ``parts``; the pinhole rays have unit z, so ``t_hit`` is the z-depth."""
    scene = o3d.t.geometry.RaycastingScene()
    ids = [scene.add_triangles(o3d.core.Tensor(p.vertices.astype(np.float32)),
                               o3d.core.Tensor(p.triangles.astype(np.uint32))) for p in parts]
    out = scene.cast_rays(rays)
    gid = out["geometry_ids"].numpy().astype(np.int64)
    lookup = np.full(max(ids) + 2, -1, dtype=np.int64)
    lookup[ids] = np.arange(len(parts))
    part = np.where(gid == o3d.t.geometry.RaycastingScene.INVALID_ID, -1, lookup[np.minimum(gid, max(ids) + 1)])
    return Hits(out["t_hit"].numpy(), part, out["primitive_ids"].numpy().astype(np.int64),
                out["primitive_normals"].numpy())


def _view_rays(k: Intrinsics) -> np.ndarray:
    """H×W×3 direction of each pixel's ray, with unit z."""
    v, u = np.mgrid[0:k.height, 0:k.width]
    return np.stack([(u + 0.5 - k.cx) / k.fx, (v + 0.5 - k.cy) / k.fy, np.ones(u.shape)], -1)


def shade(parts: list[Part], hits: Hits, k: Intrinsics) -> np.ndarray:
    """Lambert shading (two-sided) under a point light near the camera; H×W×3 float RGB in [0, 255]."""
    view = _view_rays(k)
    z = np.where(np.isfinite(hits.z), hits.z, 0.0)
    point = view * z[..., None]
    n = hits.normal * np.where((hits.normal * view).sum(-1, keepdims=True) > 0, -1.0, 1.0)
    to_light = _LIGHT - point
    dist = np.linalg.norm(to_light, axis=-1, keepdims=True)
    lambert = np.clip((n * to_light).sum(-1, keepdims=True) / dist, 0, 1) / (1 + (dist / 2.5) ** 2)
    albedo = np.zeros(z.shape + (3,))
    for i, p in enumerate(parts):
        sel = hits.part == i
        albedo[sel] = p.albedo[hits.triangle[sel]]
    return albedo * (_AMBIENT + (1 - _AMBIENT) * 1.4 * lambert)


def _smooth_noise(rng: np.random.Generator, shape: tuple[int, int], cell: int) -> np.ndarray:
    """Unit-variance-ish noise correlated over ``cell`` pixels (bilinear upsampling of a coarse grid)."""
    coarse = rng.standard_normal((shape[0] // cell + 2, shape[1] // cell + 2)).astype(np.float32)
    return cv2.resize(coarse, (shape[1] + 2 * cell, shape[0] + 2 * cell), interpolation=cv2.INTER_LINEAR)[
        cell:cell + shape[0], cell:cell + shape[1]]


def stereo_shadow(z: np.ndarray) -> np.ndarray:
    """Pixels the second stereo view cannot see: beside the left edge of anything in front of them.

    A pixel is shadowed when a pixel ``s`` columns to its right is nearer by a disparity of more than ``s``.
    """
    disp = np.where(np.isfinite(z), _SHADOW_FB / np.maximum(z, 1e-6), 0.0)
    shadow = np.zeros(z.shape, dtype=bool)
    for s in range(1, int(np.ceil(disp.max())) + 1):
        shadow[:, :-s] |= disp[:, s:] - disp[:, :-s] > s
    return shadow


def sensor_depth(z: np.ndarray, valid: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Depth in mm (uint16, 0 = none) as a stereo camera reports true z-depth ``z`` (m) where ``valid``."""
    ok = valid & np.isfinite(z) & (z < _MAX_RANGE)
    disp = _SENSOR_FB / np.where(ok, z, 1.0)
    disp = disp + _DISPARITY_NOISE * _smooth_noise(rng, z.shape, 6)
    disp = np.round(disp / _SUBPIXEL) * _SUBPIXEL
    ok &= rng.random(z.shape) > _DROPOUT
    ok &= _smooth_noise(rng, z.shape, 10) < 2.3  # rare blotches without depth
    return np.where(ok, np.round(1000 * _SENSOR_FB / disp), 0).astype(np.uint16)


def glass_returns(parts: list[Part], hits: Hits, k: Intrinsics, rng: np.random.Generator) -> np.ndarray:
    """Where the depth camera sees a transparent glass: its silhouette (grazing view), its rim and its thick base.

    Elsewhere on the glass the projected pattern goes through or is refracted away, and the sensor reports nothing.
    """
    glass = np.isin(hits.part, [i for i, p in enumerate(parts) if p.glass])
    if not glass.any():
        return glass
    view = _view_rays(k)
    cos = np.abs((hits.normal * view).sum(-1)) / np.linalg.norm(view, axis=-1)
    height = view[..., 1] * np.where(glass, hits.z, np.nan)  # y of the hit point (m, down)
    rim = height <= np.nanmin(height) + 0.004  # the top 4 mm: the rim
    base = height >= np.nanmax(height) - 0.018  # the thick bottom
    edge = cv2.morphologyEx(glass.astype(np.uint8), cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8)) > 0
    p = np.where(cos < 0.35, 0.6, 0.03)
    p = np.where(rim | base, 0.8, p)
    p = np.where(edge, np.maximum(p, 0.5), p)
    return glass & (rng.random(glass.shape) < p)


@dataclass
class RenderedFrame:
    rgb: np.ndarray  # H×W×3 uint8
    depth: np.ndarray  # H×W uint16 mm
    instances: np.ndarray  # H×W uint8
    container_visible_fraction: float
    container_distance_mm: float
    pitcher_distance_mm: float
    container_occluded: bool  # some pixel of the container's own silhouette shows another instance


def render_frame(parts: list[Part], rays: o3d.core.Tensor, k: Intrinsics, rng: np.random.Generator) -> RenderedFrame:
    """Render one frame: shaded RGB, sensor depth, instance ids and the container's ground-truth distance."""
    hits = cast(parts, rays)
    instances = np.where(hits.part >= 0, np.array([p.instance for p in parts] + [0])[hits.part], 0).astype(np.uint8)
    rgb = shade(parts, hits, k)
    opaque_parts = [p for p in parts if not p.glass]
    behind = cast(opaque_parts, rays) if len(opaque_parts) < len(parts) else hits
    glass = np.isin(hits.part, [i for i, p in enumerate(parts) if p.glass])
    if glass.any():  # a faint glass: what is behind it, a little brighter and tinted, with bright edges
        seen = shade(opaque_parts, behind, k)
        view = _view_rays(k)
        cos = np.abs((hits.normal * view).sum(-1)) / np.linalg.norm(view, axis=-1)
        glint = (1 - cos)[..., None] ** 3
        tinted = 0.82 * seen + 0.18 * np.array([225.0, 240.0, 245.0]) + 90 * glint
        rgb = np.where(glass[..., None], tinted, rgb)
    # The projector and second camera see past the glass: the glass casts no stereo shadow, shadows come from the
    # opaque scene. Where the glass itself returns depth, what is nearer than the glass can shadow it (what is behind
    # it, e.g. the hand holding it, cannot).
    valid = np.where(glass, glass_returns(parts, hits, k, rng) & ~stereo_shadow(hits.z), ~stereo_shadow(behind.z))
    depth = sensor_depth(hits.z, valid, rng)

    alone = cast([p for p in parts if p.instance == CONTAINER], rays)
    silhouette = int(np.isfinite(alone.z).sum())
    visible = instances == CONTAINER
    pitcher = instances == PITCHER
    return RenderedFrame(
        rgb=np.clip(np.round(rgb), 0, 255).astype(np.uint8),
        depth=depth,
        instances=instances,
        container_visible_fraction=round(float(visible.sum()) / silhouette, 4) if silhouette else 0.0,
        container_distance_mm=round(1000 * float(hits.z[visible].mean()), 1) if visible.any() else -1.0,
        pitcher_distance_mm=round(1000 * float(hits.z[pitcher].mean()), 1) if pitcher.any() else -1.0,
        container_occluded=bool((np.isfinite(alone.z) & ~visible).any()),
    )


# --------------------------------------------------------------------------------------------------- writing


def _meta(spec: SampleSpec, frames: list[dict]) -> dict:
    c = spec.container
    instances = {str(i): {"name": name} for i, name in INSTANCES.items()}
    instances[str(CONTAINER)]["class"] = c.cls
    return {
        "id": spec.name,
        "synthetic": True,
        "generator": {"massviz_version": __version__, "seed": spec.seed},
        "fps": FPS,
        "container": {"class": c.cls, "mass_g": c.mass_g, "width_top_mm": c.width_top_mm,
                      "width_bottom_mm": c.width_bottom_mm, "height_mm": c.height_mm, "depth_mm": c.depth_mm,
                      "capacity_ml": c.capacity_ml},
        "instances": instances,
        "instance_masks": "gt/{frame:06d}.png",
        "frames": frames,
    }


#: what a sample recording folder holds (relative paths): all that regenerating it replaces.
SAMPLE_FILES = ("rgb", "depth", "gt", "rgb/*.png", "depth/*.png", "gt/*.png", "intrinsics.json", "meta.json")


def write_sample(spec: SampleSpec, out_dir: Path, progress: Callable[[int], None] = lambda n: None) -> Path:
    """Render ``spec`` into ``out_dir/<name>`` and return that path.

    Layout::

        rgb/000000.png      8-bit RGB (lossless PNG)
        depth/000000.png    16-bit depth, mm, 0 = no depth, aligned to RGB
        gt/000000.png       uint8 instance ids (0 = background; ids in meta.json "instances")
        intrinsics.json     {"fx", "fy", "cx", "cy", "width", "height"}
        meta.json           container annotation, instances and per-frame ground truth

    The recording is rendered into a temporary folder next to the target and renamed into place at the end, so an
    error leaves the previous recording (or nothing) behind, never a half-written one. ``progress(1)`` is called
    after each frame.
    """
    target = out_dir / spec.name
    check_replaceable(target, SAMPLE_FILES, "sample recording", link_ok=False)
    with atomic_dir(target) as tmp:
        writer = FolderFrameWriter(tmp, compression=7, extra=("gt",))  # the folder format's writer
        rng = np.random.default_rng(spec.seed)
        rays = _rays(INTRINSICS)
        frames = []
        for i in range(N_FRAMES):
            r = render_frame(frame_parts(spec, i / (N_FRAMES - 1)), rays, INTRINSICS, rng)
            writer.write(i, r.rgb, r.depth, gt=r.instances)
            frames.append({
                "index": i,
                "container_nearest": bool(0 < r.container_distance_mm
                                          and (r.pitcher_distance_mm < 0
                                               or r.container_distance_mm < r.pitcher_distance_mm)),
                "container_visible_fraction": r.container_visible_fraction,
                "container_distance_mm": r.container_distance_mm,
                "container_occluded": r.container_occluded,
            })
            progress(1)
        writer.finish(INTRINSICS, _meta(spec, frames))
    return target


__all__ = ["INTRINSICS", "FPS", "N_FRAMES", "INSTANCES", "Container", "SampleSpec", "SAMPLES", "write_sample",
           "render_frame", "frame_parts"]
