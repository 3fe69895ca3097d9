"""The paper's detector: torchvision Mask R-CNN ResNet50-FPN trained on COCO.

It keeps *cup, book, wine glass, bottle* with score > threshold (0.4) and binarises masks at probability > 0.5,
as CORSMAL/Visual's ``get_outputs`` + ``filter_results``. Boxes are truncated to integers (``int(x)``) as there.

Cost: torchvision computes masks for every box that survives its box post-processing (score threshold, NMS, top
100). We set that score threshold to ours and drop the other classes right after post-processing, before the mask
head, so boxes the threshold or the class filter drops never cost mask computation. Per-box masks do not depend on
the other boxes, so the result equals running the full model and filtering afterwards.

Deliberate difference: the original's ``masks.squeeze()`` turned a single detection's (1, 1, H, W) masks into
(H, W) and then took its first *row* as the mask; here the instance axis is kept.
"""
from __future__ import annotations

import types
from pathlib import Path

import numpy as np
import torch

from massviz.errors import WeightsError
from massviz.core.types import COCO_KEEP, Detections, Frame

MASK_THRESHOLD = 0.5


def torchvision_weights_cached() -> Path | None:
    """Path of torchvision's cached COCO Mask R-CNN checkpoint, if it was downloaded before."""
    from torchvision.models.detection import MaskRCNN_ResNet50_FPN_Weights

    url = MaskRCNN_ResNet50_FPN_Weights.COCO_V1.url
    path = Path(torch.hub.get_dir()) / "checkpoints" / Path(url).name
    return path if path.is_file() else None


def build_model(threshold: float, weights: str | Path | None = None, pretrained: bool = True,
                classes=tuple(COCO_KEEP.values())) -> torch.nn.Module:
    """Mask R-CNN in eval mode whose box post-processing keeps only ``classes`` with score > ``threshold``.

    ``weights``: a local state_dict file (offline copy); else torchvision's COCO weights through its own
    download/cache (``pretrained``); ``pretrained=False`` leaves the weights random (tests).
    """
    from torchvision.models.detection import MaskRCNN_ResNet50_FPN_Weights, maskrcnn_resnet50_fpn

    model = maskrcnn_resnet50_fpn(weights=None, weights_backbone=None, num_classes=91, box_score_thresh=threshold)
    if weights is not None:
        try:
            state = torch.load(weights, map_location="cpu", weights_only=True)
            model.load_state_dict(state.get("model", state) if isinstance(state, dict) else state)
        except FileNotFoundError:
            raise WeightsError("Mask R-CNN weights file not found", weights) from None
        except Exception as err:  # noqa: BLE001 - wrong/corrupt file
            raise WeightsError(f"not a Mask R-CNN ResNet50-FPN state_dict ({type(err).__name__})", weights) from None
    elif pretrained:
        try:
            state = MaskRCNN_ResNet50_FPN_Weights.COCO_V1.get_state_dict(progress=True)
        except Exception as err:  # noqa: BLE001 - no network, proxy, ...
            raise WeightsError(f"could not download torchvision's COCO Mask R-CNN weights ({err}); pass "
                               "--detector-weights PATH (an offline copy) or use --detector depth") from None
        model.load_state_dict(state)
    keep = torch.tensor(sorted(int(c) for c in classes))
    original = model.roi_heads.postprocess_detections

    def postprocess_detections(self, *args, **kwargs):
        boxes, scores, labels = original(*args, **kwargs)
        out = [torch.isin(lab, keep.to(lab.device)) for lab in labels]
        return [b[m] for b, m in zip(boxes, out)], [s[m] for s, m in zip(scores, out)], [lab[m] for lab, m in
                                                                                         zip(labels, out)]

    model.roi_heads.postprocess_detections = types.MethodType(postprocess_detections, model.roi_heads)
    return model.eval()


def outputs_to_detections(output: dict, frame_index: int, threshold: float, classes) -> Detections:
    """torchvision output dict (one image) → Detections: score > threshold, kept classes, int boxes, masks > 0.5."""
    scores = output["scores"].detach().cpu().numpy()
    labels = output["labels"].detach().cpu().numpy()
    keep = (scores > threshold) & np.isin(labels, list(classes))
    boxes = output["boxes"].detach().cpu().numpy()[keep]
    probs = output["masks"].detach().cpu()[torch.from_numpy(keep)]  # (N, 1, H, W): the instance axis is kept
    xyxy = np.array([[int(v) for v in box] for box in boxes], dtype=np.int32).reshape(-1, 4)
    masks = [(probs[i, 0, y1:y2, x1:x2] > MASK_THRESHOLD).numpy() for i, (x1, y1, x2, y2) in enumerate(xyxy)]
    return Detections(frame=np.full(len(xyxy), frame_index), xyxy=xyxy, score=scores[keep],
                      class_id=labels[keep], masks=masks)


class MaskRCNNDetector:
    """``--detector maskrcnn``: the paper's Mask R-CNN (loaded lazily on the first frame)."""

    name = "maskrcnn"

    def __init__(self, threshold: float = 0.4, weights: str | Path | None = None, device: str | None = None,
                 pretrained: bool = True, classes=tuple(COCO_KEEP.values())):
        self.threshold = float(threshold)
        self.weights = None if weights is None else Path(weights)
        self.pretrained = pretrained
        self.classes = tuple(sorted(int(c) for c in classes))
        self.device = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
        self._model = None

    def settings(self) -> dict:
        if self.weights is not None:  # by content: another file under the same name is another cache key
            from massviz.io.filehash import file_digest

            if getattr(self, "_weights_digest", None) is None:  # hashed once per detector (the file is ~170 MB)
                self._weights_digest = file_digest(self.weights) if self.weights.is_file() else "missing"
            src = f"{self.weights.resolve()}:{self._weights_digest}"
        else:
            src = "torchvision:COCO_V1" if self.pretrained else "random-init"
        return {"weights": src, "classes": list(self.classes), "mask_threshold": MASK_THRESHOLD}

    @property
    def model(self) -> torch.nn.Module:
        if self._model is None:
            self._model = build_model(self.threshold, self.weights, self.pretrained, self.classes).to(self.device)
        return self._model

    @torch.no_grad()
    def detect(self, frame: Frame) -> Detections:
        image = torch.from_numpy(frame.rgb).permute(2, 0, 1).float().div(255).to(self.device)  # = ToTensor()
        output = self.model([image])[0]
        return outputs_to_detections(output, frame.index, self.threshold, self.classes)
