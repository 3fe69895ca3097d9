"""The one detector interface every detector implements (``massviz.detect`` holds the detectors)."""
from __future__ import annotations

from typing import Protocol, runtime_checkable

from massviz.core.types import Detections, Frame

#: the paper's score cut (Mask R-CNN's calibration): Mask R-CNN's default, the faithful mode's
PAPER_THRESHOLD = 0.4
#: each detector's default score cut (``--threshold`` overrides it), chosen from measurements on CCM 618 (its 8 RGB-D
#: frames and 77-frame video), CCM view1 and the samples (docs/detectors.md). A replay's default is
#: the cut of the run it replays (``massviz.detect.saved``).
DEFAULT_THRESHOLDS = {"maskrcnn": PAPER_THRESHOLD, "nanodet": 0.3, "depth": 0.4}


def describe_cut(detector: str, threshold: float) -> str:
    """The score cut in words, for the trace's events: ``score > 0.3 (nanodet's default)``, or ``score > 0.35
    (nanodet's default: 0.3)`` when another was asked for."""
    default = DEFAULT_THRESHOLDS.get(detector)
    if default is None:
        return f"score > {threshold:g}"
    if abs(float(threshold) - default) <= 1e-9:
        return f"score > {threshold:g} ({detector}'s default)"
    return f"score > {threshold:g} ({detector}'s default: {default:g})"


def detector_info(detector) -> dict:
    """What a trace records of its detector and what keys its traces in the cache: the detector's name and
    ``settings()`` (every setting that changes its output but the score cut)."""
    return {"name": detector.name, **detector.settings()}


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


__all__ = ["Detector", "PAPER_THRESHOLD", "DEFAULT_THRESHOLDS", "describe_cut", "detector_info"]
