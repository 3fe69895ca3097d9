"""The one detector interface every detector implements."""
from __future__ import annotations

from typing import Protocol, runtime_checkable

from massviz.core.types import Detections, Frame


@runtime_checkable
class Detector(Protocol):
    """A detector turns one frame into detections.

    ``detect`` returns ``Detections`` with ``frame``, ``xyxy`` (int, x2/y2 exclusive), ``score``, ``class_id`` and
    ``masks`` (bool, cropped to the box) filled; features (d, a, b), patches and predictions are added by the
    pipeline. Detections must already be filtered by ``threshold`` (score > threshold, strict, as the paper's code).
    ``settings()`` returns every setting that changes the output *except* the threshold: it keys the cache.
    """

    name: str
    threshold: float

    def detect(self, frame: Frame) -> Detections: ...

    def settings(self) -> dict: ...
