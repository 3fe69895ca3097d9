"""Detectors behind one interface (``massviz.core.detector.Detector``) and the factory the CLI uses.

* ``maskrcnn``: the paper's torchvision Mask R-CNN (COCO; cup, book, wine glass, bottle).
* ``nanodet``: OpenCV Zoo's NanoDet through ``cv2.dnn`` (COCO boxes, the same classes; masks from depth in the box):
  fast on a CPU, offline once its 3.8 MB model file is there.
* ``depth``: no weights; the nearest object(s) in the depth map (works offline).
* ``replay``: detections saved by an earlier run or given in a documented JSON file.
* ``auto``: Mask R-CNN when its weights are given or already cached, else NanoDet when its model is given or cached,
  else depth; it never touches the network (no probe, no download) and always says on stderr which it chose and why,
  ``--quiet`` or not.
"""
from __future__ import annotations

import logging
import os
from pathlib import Path

from massviz.core.detector import Detector
from massviz.errors import MassvizError

DETECTORS = ("auto", "maskrcnn", "nanodet", "depth", "replay")
#: the file name torchvision caches the COCO Mask R-CNN checkpoint under (MaskRCNN_ResNet50_FPN_Weights.COCO_V1.url).
MASKRCNN_COCO_FILE = "maskrcnn_resnet50_fpn_coco-bf2d0c1e.pth"

_LOG = logging.getLogger(__name__)


def maskrcnn_weights_cached() -> Path | None:
    """torchvision's cached COCO Mask R-CNN checkpoint, if downloaded before; looked up the way ``torch.hub.get_dir``
    does ($TORCH_HOME, else $XDG_CACHE_HOME/torch, else ~/.cache/torch; then hub/checkpoints) without importing torch
    and without any network access."""
    home = os.environ.get("TORCH_HOME") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"), "torch")
    path = Path(os.path.expanduser(home)) / "hub" / "checkpoints" / MASKRCNN_COCO_FILE
    return path if path.is_file() else None


def choose_auto(detector_weights: str | Path | None = None) -> tuple[str, str]:
    """``--detector auto``'s choice and the reason, from local files only (module docstring)."""
    from massviz.detect.nanodet import cached_model

    if detector_weights is not None:
        if Path(detector_weights).suffix.lower() == ".onnx":
            return "nanodet", f"--detector-weights {detector_weights} is an ONNX file (NanoDet)"
        return "maskrcnn", f"--detector-weights {detector_weights} given (Mask R-CNN state_dict)"
    cached = maskrcnn_weights_cached()
    if cached is not None:
        return "maskrcnn", f"the COCO Mask R-CNN weights are cached ({cached})"
    nano = cached_model()
    if nano is not None:
        return "nanodet", (f"the Mask R-CNN COCO weights are not cached; the NanoDet model is ({nano}); "
                           "--detector maskrcnn downloads the paper's detector")
    return "depth", ("neither the Mask R-CNN COCO weights nor the NanoDet model is cached (auto never downloads); "
                     "--detector nanodet or --detector maskrcnn downloads one once, --detector-weights PATH uses an "
                     "offline copy")


def announce_auto(name: str, why: str) -> None:
    """The line ``--detector auto`` always says (an INFO record of the ``massviz`` logger: on stderr from the command
    line), ``--quiet`` or not, whether its detector is built or its traces are served from the cache."""
    _LOG.info("massviz: --detector auto: using %s: %s", name, why)


def make_detector(name: str = "auto", threshold: float | None = None, *, detector_weights: str | Path | None = None,
                  replay: str | Path | None = None, quiet: bool = False, precision: str = "fp32",
                  device=None) -> Detector:
    """Build a detector by name (see module docstring). ``precision`` (fp32, bf16, fp16) is Mask R-CNN's; the other
    detectors have only fp32. ``device``: Mask R-CNN's (default: CUDA when present); the other detectors run on the
    CPU. ``quiet`` hides progress bars only: auto's choice is always printed (stderr). ``threshold`` None: the
    detector's own default cut (``massviz.core.detector.DEFAULT_THRESHOLDS``; a replay's: the replayed run's)."""
    from massviz.core.detector import DEFAULT_THRESHOLDS

    if name not in DETECTORS:
        raise MassvizError(f"unknown detector {name!r} (choose from {', '.join(DETECTORS)})")
    if name == "auto":
        if replay is not None:
            name, why = "replay", f"--replay {replay} given"
        else:
            name, why = choose_auto(detector_weights)
        announce_auto(name, why)
    if threshold is None and name in DEFAULT_THRESHOLDS:
        threshold = DEFAULT_THRESHOLDS[name]
    if name == "maskrcnn":
        from massviz.detect.maskrcnn import MaskRCNNDetector

        return MaskRCNNDetector(threshold=threshold, weights=detector_weights, precision=precision,
                                device=None if device is None else str(device))
    if precision != "fp32":
        raise MassvizError(f"--precision {precision} is a Mask R-CNN mode; the {name} detector runs in fp32 only "
                           "(use --detector maskrcnn, or leave --precision at fp32)")
    if name == "nanodet":
        from massviz.detect.nanodet import NanoDetDetector

        return NanoDetDetector(threshold=threshold, weights=detector_weights, progress=not quiet).load()
    if name == "depth":
        from massviz.detect.depth import DepthDetector

        return DepthDetector(threshold=threshold)
    if replay is None:
        raise MassvizError("--detector replay needs --replay PATH (a saved trace .npz or a detections JSON file)")
    from massviz.detect.saved import ReplayDetector

    return ReplayDetector(replay, threshold=threshold)


__all__ = ["Detector", "DETECTORS", "make_detector", "choose_auto", "announce_auto", "maskrcnn_weights_cached", "MASKRCNN_COCO_FILE"]
