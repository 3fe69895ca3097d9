"""Detectors behind one interface (``massviz.core.detector.Detector``) and the factory the CLI uses.

* ``maskrcnn``: the paper's torchvision Mask R-CNN (COCO; cup, book, wine glass, bottle).
* ``depth``: no weights; the nearest object(s) in the depth map (works offline).
* ``replay``: detections saved by an earlier run or given in a documented JSON file.
* ``auto``: maskrcnn when its weights are available locally or downloadable, else depth (saying so).
"""
from __future__ import annotations

import sys
import urllib.request
from pathlib import Path

from massviz.detect.base import Detector
from massviz.errors import MassvizError

DETECTORS = ("auto", "maskrcnn", "depth", "replay")


def maskrcnn_weights_reachable(timeout: float = 3.0) -> bool:
    """True when torchvision's COCO Mask R-CNN checkpoint is cached locally or its URL answers."""
    from massviz.detect.maskrcnn import torchvision_weights_cached
    from torchvision.models.detection import MaskRCNN_ResNet50_FPN_Weights

    if torchvision_weights_cached() is not None:
        return True
    try:
        req = urllib.request.Request(MaskRCNN_ResNet50_FPN_Weights.COCO_V1.url, method="HEAD")
        with urllib.request.urlopen(req, timeout=timeout) as resp:
            return 200 <= resp.status < 400
    except Exception:  # noqa: BLE001 - offline, DNS, proxy: not reachable
        return False


def make_detector(name: str = "auto", threshold: float = 0.4, *, detector_weights: str | Path | None = None,
                  replay: str | Path | None = None, quiet: bool = False, precision: str = "fp32") -> Detector:
    """Build a detector by name (see module docstring). ``precision`` (fp32, bf16, fp16) is Mask R-CNN's; the other
    detectors have only fp32."""
    if name not in DETECTORS:
        raise MassvizError(f"unknown detector {name!r} (choose from {', '.join(DETECTORS)})")
    if name == "auto":
        if replay is not None:
            name = "replay"
        elif detector_weights is not None or maskrcnn_weights_reachable():
            name = "maskrcnn"
        else:
            name = "depth"
            if not quiet:
                print("massviz: Mask R-CNN weights are neither cached nor downloadable; using the depth detector "
                      "(pass --detector-weights PATH for an offline copy)", file=sys.stderr)
    if name == "maskrcnn":
        from massviz.detect.maskrcnn import MaskRCNNDetector

        return MaskRCNNDetector(threshold=threshold, weights=detector_weights, precision=precision)
    if precision != "fp32":
        raise MassvizError(f"--precision {precision} is a Mask R-CNN mode; the {name} detector runs in fp32 only "
                           "(use --detector maskrcnn, or leave --precision at fp32)")
    if name == "depth":
        from massviz.detect.depth import DepthDetector

        return DepthDetector(threshold=threshold)
    if replay is None:
        raise MassvizError("--detector replay needs --replay PATH (a saved trace .npz or a detections JSON file)")
    from massviz.detect.replay import ReplayDetector

    return ReplayDetector(replay, threshold=threshold)


__all__ = ["Detector", "DETECTORS", "make_detector", "maskrcnn_weights_reachable"]
