"""What the bundled synthetic recordings are (pure data, no rendering): the camera, the containers, where things
stand. ``massviz.samples.generator`` renders them; the CLI reads the names from here without loading Open3D."""
from __future__ import annotations

from dataclasses import dataclass

from massviz.core.types import Intrinsics

#: A RealSense D435 colour camera at 1280×720 (fx≈fy≈924) scaled by 0.375.
INTRINSICS = Intrinsics(fx=346.4, fy=346.3, cx=243.7, cy=135.4, width=480, height=270)
FPS = 30
N_FRAMES = 36

# Instance ids of the ground-truth masks (0 is the background wall).
CONTAINER, PITCHER, HAND, PERSON, TABLE = 1, 2, 3, 4, 5
INSTANCES = {CONTAINER: "container", PITCHER: "pitcher", HAND: "hand", PERSON: "person", TABLE: "table"}


@dataclass(frozen=True)
class Container:
    """The handed-over container: CCM-style annotation (mm, mL, g) and how it looks."""

    cls: str  # "cup", "glass" or "box"
    mass_g: float
    width_top_mm: float
    width_bottom_mm: float
    height_mm: float
    depth_mm: float  # -1 unless a box
    capacity_ml: float
    colour: tuple[int, int, int]
    accent: tuple[int, int, int]  # band on the cup, front face of the box


@dataclass(frozen=True)
class SampleSpec:
    """One synthetic recording: its container, where things stand and the seed of its sensor noise."""

    name: str
    container: Container
    seed: int
    pitcher_xz: tuple[float, float]  # pitcher position on the table (m, camera coordinates)
    start: tuple[float, float, float]  # container centre at the start of the hand-over (m)
    end: tuple[float, float, float]  # ... and when it is handed to the robot
    yaw_deg: tuple[float, float]  # container rotation about the vertical, start and end
    shirt: tuple[int, int, int]
    #: ``(t_start, t_end, (x, y, z))``: between hand-over times ``t_start`` and ``t_end`` a hand (behind the pitcher,
    #: hidden by it) lifts the pitcher from the table towards the camera, its base up to ``(x, y, z)`` (m) half-way,
    #: and puts it back. None: the pitcher stays on the table.
    pitcher_lift: tuple[float, float, tuple[float, float, float]] | None = None


#: Hand-over times (strictly between frames 6 and 12 of 36, so every 6th frame shows it on the table) and peak base
#: position of the lifted pitcher: in frames 8-10 it is nearer than the container ever comes, so the K = 5 nearest
#: detections of the whole recording include three pitcher patches.
PITCHER_LIFT = (6 / 35, 12 / 35, (-0.16, 0.13, 0.42))

SAMPLES: dict[str, SampleSpec] = {
    spec.name: spec
    for spec in [
        SampleSpec(
            "cup_handover",
            Container("cup", 9.0, 92.0, 60.0, 110.0, -1.0, 480.0, (236, 232, 222), (196, 64, 52)),
            seed=101, pitcher_xz=(-0.20, 0.86), start=(0.13, 0.02, 1.45), end=(0.04, 0.0, 0.56),
            yaw_deg=(0.0, 0.0), shirt=(54, 84, 140), pitcher_lift=PITCHER_LIFT),
        SampleSpec(
            "glass_handover",
            Container("glass", 118.0, 78.0, 62.0, 128.0, -1.0, 400.0, (215, 228, 235), (215, 228, 235)),
            seed=202, pitcher_xz=(-0.22, 0.84), start=(0.14, 0.0, 1.40), end=(0.05, -0.01, 0.55),
            yaw_deg=(0.0, 0.0), shirt=(120, 60, 60)),
        SampleSpec(
            "box_handover",
            Container("box", 33.0, 150.0, 150.0, 160.0, 60.0, 1400.0, (222, 180, 60), (40, 110, 170)),
            seed=303, pitcher_xz=(-0.24, 0.88), start=(0.15, 0.0, 1.45), end=(0.05, -0.02, 0.60),
            yaw_deg=(30.0, 12.0), shirt=(70, 120, 80)),
    ]
}
