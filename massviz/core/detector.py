"""The one detector interface every detector implements (``massviz.detect`` holds the detectors)."""
from __future__ import annotations

from typing import Protocol, runtime_checkable

from massviz.core.types import Detections, Frame


@runtime_checkable
class Detector(Protocol):
    """A detector turns one frame into detections.

    ``detect`` returns ``Detections`` with ``frame``, ``xyxy`` (int, x2/y2 exclusive), ``score``, ``class_id`` and
    ``masks`` (bool, cropped to the box) filled; features (d, a, b), patches and predictions are added by the
    pipeline, in new arrays (the detector's output is never changed). ``threshold`` is the detector's own score cut:
    detections are already filtered by it (score > threshold, strict, as the paper's code); the selection's
    threshold travels separately (``massviz.core.selection.Selection``). ``settings()`` returns every setting that
    changes the output *except* the threshold: it keys the cache.
    """

    name: str
    threshold: float

    def detect(self, frame: Frame) -> Detections: ...

    def settings(self) -> dict: ...


__all__ = ["Detector"]
