"""``Measurement``: the measured size of one chosen detection, as the measure stage (``massviz.measure3d``) makes it
and a ``Trace`` carries it (``Trace.measurements``). Plain data: building or reading one needs no Open3D."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass


@dataclass(frozen=True)
class Measurement:
    """Measured size of one chosen detection (``rank`` in the selection, ``detection`` its index in the trace,
    ``frame`` its frame): height, width and depth in mm and the measured box in metres in the camera frame (RDF):
    ``center``, ``extent`` (width, height, depth) and ``R`` (3×3 rows; its columns are the width, height and depth
    directions). ``n_points``: the points of the cleaned cloud it was measured on."""

    rank: int
    detection: int
    frame: int
    height_mm: float
    width_mm: float
    depth_mm: float
    center: list
    extent: list
    R: list
    n_points: int

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "Measurement":
        return cls(**{f.name: d[f.name] for f in dataclasses.fields(cls)})

    def ranked(self, rank: int) -> "Measurement":
        return dataclasses.replace(self, rank=int(rank))


def ranked_measurements(measurements, selection) -> list[Measurement]:
    """The measurements of the detections in ``selection``, in its order, with ``rank`` their rank in it: what a
    re-selected trace keeps (a newly chosen detection has none until measured)."""
    by_detection = {int(m.detection): m for m in measurements}
    return [by_detection[int(i)].ranked(r) for r, i in enumerate(selection) if int(i) in by_detection]


__all__ = ["Measurement", "ranked_measurements"]
