"""The paper's detector: torchvision Mask R-CNN ResNet50-FPN trained on COCO.

It keeps *cup, book, wine glass, bottle* with score > threshold (0.4) and binarises masks at probability > 0.5,
as CORSMAL/Visual's ``get_outputs`` + ``filter_results``. Boxes are truncated to integers (``int(x)``) as there.

Cost: torchvision computes masks for every box that survives its box post-processing (score threshold, NMS, top
100). We set that score threshold to ours and drop the other classes right after post-processing, before the mask
head, so boxes the threshold or the class filter drops never cost mask computation. Per-box masks do not depend on
the other boxes, so the result equals running the full model and filtering afterwards.

Deliberate difference: the original's ``masks.squeeze()`` turned a single detection's (1, 1, H, W) masks into
(H, W) and then took its first *row* as the mask; here the instance axis is kept.

Speed (``MaskRCNNDetector`` runs a *runtime copy* of the torchvision model; ``.model`` stays torchvision's own, so
its ``state_dict`` is the usual one). Faithful: results equal to the torchvision model up to float rounding.

* BatchNorm folded into the preceding convolution (``fold_batchnorm``) and channels_last memory format: the same
  arithmetic in another order (the backbone ~2x faster on a 2-core AVX-512 CPU).
* Masks pasted only inside each kept box (``paste_mask_crops``): torchvision pastes every mask into a full-image
  canvas (100 boxes at 1280x720: 368 MB a frame and ~20 % of the time) and the paper's code then uses the box part;
  the same interpolation is computed, only the box window is kept — bit-identical.
* ``detect_batch``: one forward for several frames of one size. torchvision pads a batch to its largest image, so
  frames of one size get exactly the input they get alone (bit-identical outputs, checked by tests/test_speed.py);
  frames of different sizes are never batched together.
* RoIAlign as one weighted gather over channels_last feature rows (``massviz.detect.roialign``): torchvision's CPU
  ``roi_align`` runs on one core, channel plane by channel plane, after copying channels_last features to NCHW at
  every call (1000 proposals a frame at 1280x720: 0.27 s → 0.02 s here; equal up to float rounding).
* ``torch.inference_mode``.

Reduced precision (``precision="bf16"`` on CPUs with bf16 support or CUDA, ``"fp16"`` on CUDA), opt-in: the convolution
and MLP stages (backbone + FPN, RPN head, box head, mask head and predictor) run under ``torch.autocast`` and hand
float32 on; box regression, box decoding, NMS, RoIAlign and mask pasting stay float32 (under a whole-model autocast
the proposals are decoded in bf16, whose 8-bit mantissa puts a 1000-pixel coordinate on a 4–8 pixel grid). Results
*differ*: measure how much on your data with ``massviz compare`` (docs/speed.md).
"""
from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import torch
from torchvision.models.detection.roi_heads import RoIHeads
from torchvision.models.detection.transform import GeneralizedRCNNTransform, resize_boxes

from massviz.core.detector import PAPER_THRESHOLD
from massviz.core.device import default_batch, faithful_fp32
from massviz.core.resample import to_unit_float
from massviz.core.types import COCO_KEEP, PRECISIONS, Detections, Frame
from massviz.errors import MassvizError, WeightsError

MASK_THRESHOLD = 0.5
_DTYPES = {"bf16": torch.bfloat16, "fp16": torch.float16}


def _construct(threshold: float, skip_init: bool) -> torch.nn.Module:
    """torchvision's Mask R-CNN ResNet50-FPN; ``skip_init``: without its random initialisation (0.35 s of 44 M
    random numbers), for a model whose every parameter and buffer a strict ``load_state_dict`` then overwrites.

    Built on the meta device, then given (uninitialised) CPU storage; the anchor generator's cell anchors are the one
    tensor it makes at construction outside its parameters and buffers, so they are made again."""
    from torchvision.models.detection import maskrcnn_resnet50_fpn

    kwargs = dict(weights=None, weights_backbone=None, num_classes=91, box_score_thresh=threshold)
    if not skip_init:
        return maskrcnn_resnet50_fpn(**kwargs)
    with torch.device("meta"):
        model = maskrcnn_resnet50_fpn(**kwargs)
    model = model.to_empty(device="cpu")
    anchors = model.rpn.anchor_generator
    anchors.cell_anchors = [anchors.generate_anchors(size, ratios)
                            for size, ratios in zip(anchors.sizes, anchors.aspect_ratios)]
    return model


#: the COCO classes the paper keeps (cup, book, wine glass, bottle), as class ids
KEEP_CLASSES = tuple(COCO_KEEP.values())


def build_model(threshold: float, weights: str | Path | None = None, pretrained: bool = True,
                classes=KEEP_CLASSES) -> torch.nn.Module:
    """Mask R-CNN in eval mode whose box post-processing keeps only ``classes`` with score > ``threshold``.

    ``weights``: a local state_dict file (offline copy); else torchvision's COCO weights through its own
    download/cache (``pretrained``); ``pretrained=False`` leaves the weights random (tests).
    """
    from torchvision.models.detection import MaskRCNN_ResNet50_FPN_Weights

    model = _construct(threshold, skip_init=weights is not None or pretrained)
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
    model.roi_heads = ClassFilterRoIHeads.of(model.roi_heads, classes)
    return model.eval()


class ClassFilterRoIHeads(RoIHeads):
    """torchvision's ``RoIHeads`` whose box post-processing keeps only the classes in ``keep_classes``: the other
    boxes are dropped before the mask head runs (module docstring). Same submodules, so the same ``state_dict``."""

    @classmethod
    def of(cls, stock, classes) -> "ClassFilterRoIHeads":
        """A copy of ``stock`` (a torchvision ``RoIHeads`` without keypoints) sharing its submodules."""
        heads = cls(stock.box_roi_pool, stock.box_head, stock.box_predictor,
                    stock.proposal_matcher.high_threshold, stock.proposal_matcher.low_threshold,
                    stock.fg_bg_sampler.batch_size_per_image, stock.fg_bg_sampler.positive_fraction,
                    stock.box_coder.weights, stock.score_thresh, stock.nms_thresh, stock.detections_per_img,
                    mask_roi_pool=stock.mask_roi_pool, mask_head=stock.mask_head,
                    mask_predictor=stock.mask_predictor)
        heads.register_buffer("keep_classes", torch.tensor(sorted(int(c) for c in classes)), persistent=False)
        return heads.train(stock.training)

    def postprocess_detections(self, *args, **kwargs):
        boxes, scores, labels = super().postprocess_detections(*args, **kwargs)
        keep = [torch.isin(lab, self.keep_classes.to(lab.device)) for lab in labels]
        return ([b[m] for b, m in zip(boxes, keep)], [s[m] for s, m in zip(scores, keep)],
                [lab[m] for lab, m in zip(labels, keep)])


# ------------------------------------------------------------------------------------------------ faithful speed-ups
def fold_batchnorm(module: torch.nn.Module) -> int:
    """Fold every batch norm that directly follows a bias-free ``Conv2d`` in the same parent (ResNet's ``conv, bn``
    pairs) into that convolution, replacing the norm by ``Identity``; returns how many were folded.

    Eval-mode statistics are used (``BatchNorm2d`` in eval mode or ``FrozenBatchNorm2d``): y = conv(x) * s + t with
    s = weight / sqrt(var + eps), t = bias - mean * s becomes one convolution with weight * s and bias t, computed by
    ``torch.nn.utils.fuse_conv_bn_weights``. New tensors are created (nothing is modified in place), so a module that
    shares parameters with another is safe to fold.
    """
    from torch.nn.utils import fuse_conv_bn_weights
    from torchvision.ops.misc import FrozenBatchNorm2d

    folded = 0
    for parent in list(module.modules()):
        names = list(parent._modules)
        for prev, name in zip(names, names[1:]):
            conv, bn = parent._modules[prev], parent._modules[name]
            if not isinstance(bn, (torch.nn.BatchNorm2d, FrozenBatchNorm2d)) or not isinstance(conv, torch.nn.Conv2d):
                continue
            if conv.bias is not None or (isinstance(bn, torch.nn.BatchNorm2d) and (bn.training or bn.running_var is None)):
                continue
            with torch.no_grad():
                new = torch.nn.Conv2d(conv.in_channels, conv.out_channels, conv.kernel_size, conv.stride,
                                      conv.padding, conv.dilation, conv.groups, bias=True,
                                      padding_mode=conv.padding_mode, device="meta")
                weight, bias = fuse_conv_bn_weights(conv.weight, None, bn.running_mean, bn.running_var, bn.eps,
                                                    bn.weight, bn.bias)
                new.weight = torch.nn.Parameter(weight, requires_grad=False)
                new.bias = torch.nn.Parameter(bias, requires_grad=False)
            parent._modules[prev], parent._modules[name] = new, torch.nn.Identity()
            folded += 1
    return folded


def paste_mask_crops(masks: torch.Tensor, boxes: torch.Tensor, im_h: int, im_w: int,
                     threshold: float = MASK_THRESHOLD, padding: int = 1) -> list[np.ndarray]:
    """``paste_masks_in_image(masks, boxes, (im_h, im_w))[i, 0, y1:y2, x1:x2] > threshold`` for each box's integer
    window (x1, y1, x2, y2 = int(box)), without the full-image canvases: torchvision's own padding, box expansion and
    bilinear resize, then only the window is kept (bit-identical)."""
    import torch.nn.functional as F
    from torchvision.models.detection.roi_heads import expand_boxes, expand_masks

    if len(boxes) == 0:
        return []
    padded, scale = expand_masks(masks.float(), padding=padding)
    expanded = expand_boxes(boxes, scale).to(dtype=torch.int64).tolist()
    out = []
    for mask, (ex0, ey0, ex1, ey1), box in zip(padded, expanded, boxes.tolist()):
        x1, y1, x2, y2 = (int(v) for v in box)
        w, h = max(int(ex1 - ex0 + 1), 1), max(int(ey1 - ey0 + 1), 1)
        resized = F.interpolate(mask[0].expand((1, 1, -1, -1)), size=(h, w), mode="bilinear", align_corners=False)[0][0]
        # the canvas holds the resized mask on [max(ey0, 0), min(ey1 + 1, H)) x [max(ex0, 0), min(ex1 + 1, W)), 0 elsewhere
        crop = np.zeros((max(y2 - y1, 0), max(x2 - x1, 0)), dtype=bool)
        ya, yb = max(y1, ey0, 0), min(y2, ey1 + 1, im_h)
        xa, xb = max(x1, ex0, 0), min(x2, ex1 + 1, im_w)
        if ya < yb and xa < xb:
            crop[ya - y1:yb - y1, xa - x1:xb - x1] = (resized[ya - ey0:yb - ey0, xa - ex0:xb - ex0] > threshold).cpu().numpy()
        out.append(crop)
    return out


class MaskWindows:
    """Mask R-CNN's masks of a batch of detections kept on the device, pasted only inside their integer boxes when
    asked (``massviz.core.frame_stage``'s device path): ``windows(index, xyxy, height, width)`` is, for each detection
    ``index``, ``paste_mask_crops``' mask as a (height, width) window of a bool tensor (top-left aligned; False past
    its box), for many detections in one set of tensor operations.

    The arithmetic is ``massviz.core.windows``' (torchvision's paste as gathers over all the boxes at once, in
    float32 as PyTorch's CUDA kernel computes it); a pixel can differ from ``paste_mask_crops`` only where its
    probability is within float rounding of 0.5 (tests/test_device_path.py). ``padded``, ``expanded``, ``im_h``,
    ``im_w`` and ``threshold`` are what ``massviz.core.windows.window_features`` takes."""

    def __init__(self, probs: torch.Tensor, boxes: torch.Tensor, im_h: int, im_w: int,
                 threshold: float = MASK_THRESHOLD, padding: int = 1):
        from torchvision.models.detection.roi_heads import expand_boxes, expand_masks

        self.device = probs.device
        if len(probs):
            padded, scale = expand_masks(probs.float(), padding=padding)
            self.padded = padded[:, 0]  # (n, M + 2p, M + 2p)
            self.expanded = expand_boxes(boxes.float(), scale).to(dtype=torch.int64)  # (n, 4) x0, y0, x1, y1
        else:
            self.padded = probs.new_zeros((0, 1, 1))
            self.expanded = boxes.new_zeros((0, 4), dtype=torch.int64)
        self.im_h, self.im_w, self.threshold = int(im_h), int(im_w), float(threshold)

    def __len__(self) -> int:
        return len(self.padded)

    def windows(self, index, xyxy, height: int, width: int) -> torch.Tensor:
        """(len(index), height, width) bool on the device: detection ``index[i]``'s mask in its integer box
        ``xyxy[i]`` (x1, y1, x2, y2; host arrays or tensors), top-left aligned, False past the box
        (``massviz.core.windows.paste_windows``)."""
        from massviz.core.windows import paste_windows

        idx = index if isinstance(index, torch.Tensor) else torch.from_numpy(np.asarray(index, dtype=np.int64))
        box = xyxy if isinstance(xyxy, torch.Tensor) else torch.from_numpy(np.asarray(xyxy, np.int64).reshape(-1, 4))
        idx, box = idx.to(self.device), box.to(self.device, torch.int64)
        return paste_windows(self.padded[idx], self.expanded[idx], box, height, width, self.im_h, self.im_w,
                             self.threshold)


class MaskCropTransform(GeneralizedRCNNTransform):
    """torchvision's ``GeneralizedRCNNTransform`` whose ``postprocess`` uses ``paste_mask_crops`` instead of
    full-image mask pasting: boxes are rescaled as torchvision does; ``masks`` is replaced by ``mask_crops`` (bool
    arrays, one per box). ``postprocess(..., paste=False)`` leaves the masks as the mask head's probabilities
    (n, 1, 28, 28) on the device (``MaskWindows`` pastes them later); ``forward_detections`` calls it so, per call,
    with no state of the module changed."""

    @classmethod
    def of(cls, stock) -> "MaskCropTransform":
        """The same pre-processing as the torchvision transform ``stock``."""
        return cls(stock.min_size, stock.max_size, stock.image_mean, stock.image_std, stock.size_divisible,
                   stock.fixed_size, _skip_resize=stock._skip_resize).train(stock.training)

    def postprocess(self, result, image_shapes, original_image_sizes, paste: bool = True):
        if self.training:
            return result
        for pred, im_s, o_im_s in zip(result, image_shapes, original_image_sizes):
            pred["boxes"] = resize_boxes(pred["boxes"], im_s, o_im_s)
            if "masks" in pred and paste:
                pred["mask_crops"] = paste_mask_crops(pred.pop("masks"), pred["boxes"], *o_im_s)
        return result


def forward_detections(model: torch.nn.Module, images: list[torch.Tensor], paste: bool = True) -> list[dict]:
    """The eval forward of a ``runtime_model`` (torchvision's ``GeneralizedRCNN.forward``: transform, backbone, RPN,
    RoI heads, post-processing) with the masks pasted into their boxes on the host (``paste``) or left on the
    device as probabilities. Nothing shared is changed, so two threads may run it at once."""
    from collections import OrderedDict

    sizes = [tuple(int(v) for v in img.shape[-2:]) for img in images]
    batch, _ = model.transform(images)
    features = model.backbone(batch.tensors)
    if isinstance(features, torch.Tensor):
        features = OrderedDict([("0", features)])
    proposals, _ = model.rpn(batch, features)
    detections, _ = model.roi_heads(features, proposals, batch.image_sizes)
    return model.transform.postprocess(detections, batch.image_sizes, sizes, paste=paste)


def _float32(x):
    if isinstance(x, torch.Tensor):
        return x.float() if x.is_floating_point() else x
    if isinstance(x, dict):
        return type(x)((k, _float32(v)) for k, v in x.items())
    if isinstance(x, (list, tuple)):
        return type(x)(_float32(v) for v in x)
    return x


#: the layers autocast runs in the lower precision: their weights are cast once, not at every call.
_AUTOCAST_LAYERS = (torch.nn.Conv2d, torch.nn.ConvTranspose2d, torch.nn.Linear)


class ReducedPrecision(torch.nn.Module):
    """Runs ``inner`` under ``torch.autocast(device_type, dtype)`` and returns float32 tensors.

    ``inner`` is copied with the weights of its convolutions and linear layers already in ``dtype``: autocast casts
    them to ``dtype`` at every call otherwise (~44 M parameters a frame), and casting a tensor of that dtype is a
    no-op, so the results are the same.
    """

    def __init__(self, inner: torch.nn.Module, device_type: str, dtype: torch.dtype):
        super().__init__()
        inner = copy.deepcopy(inner)
        for m in inner.modules():
            if isinstance(m, _AUTOCAST_LAYERS):
                for name, p in list(m._parameters.items()):
                    if p is not None and p.is_floating_point():
                        m._parameters[name] = torch.nn.Parameter(p.detach().to(dtype), requires_grad=False)
        self.inner, self.device_type, self.dtype = inner, device_type, dtype

    def forward(self, *args, **kwargs):
        with torch.autocast(self.device_type, dtype=self.dtype):
            out = self.inner(*args, **kwargs)
        return _float32(out)


def bf16_supported() -> bool:
    """True when this CPU runs bfloat16 kernels natively (oneDNN: AVX512-BF16 or AMX)."""
    try:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except Exception:  # noqa: BLE001 - older/other builds
        return False


def check_precision(precision: str, device: torch.device) -> None:
    """``MassvizError`` when ``precision`` cannot run on ``device`` (one line naming what would work)."""
    if precision not in PRECISIONS:
        raise MassvizError(f"--precision must be one of {', '.join(PRECISIONS)}, got {precision!r}")
    if precision == "fp16" and device.type != "cuda":
        raise MassvizError("--precision fp16 needs a CUDA GPU (none is available here); on a CPU use --precision "
                           "bf16" + ("" if bf16_supported() else " where the CPU supports it (this one does not)"))
    if precision == "bf16" and device.type == "cpu" and not bf16_supported():
        raise MassvizError("--precision bf16: this CPU has no bfloat16 support (needs AVX512-BF16 or AMX); use "
                           "--precision fp32")
    if precision == "bf16" and device.type == "cuda" and not torch.cuda.is_bf16_supported():
        raise MassvizError("--precision bf16: this GPU has no bfloat16 support; use --precision fp16")


def runtime_model(model: torch.nn.Module, precision: str = "fp32", device=None, fused: bool = True) -> torch.nn.Module:
    """The fast copy of a ``build_model`` model that ``MaskRCNNDetector`` runs (see the module docstring).

    Parameters are shared with ``model`` except the backbone convolutions BatchNorm is folded into and the
    channels_last copies of 4-D weights, so ``model`` itself is left exactly as it was (its ``state_dict`` too).
    On a CPU the RoI poolings gather channels_last rows (``ChannelsLastMultiScaleRoIAlign``). ``fused=False``
    skips all of that: the arithmetic of torchvision's model exactly (fp32 outputs bit-identical to it, slower).
    """
    device = torch.device(device) if device is not None else next(model.parameters()).device
    memo = {id(t): t for t in [*model.parameters(), *model.buffers()]}  # share tensors, copy the modules
    fast = copy.deepcopy(model, memo).eval()
    if fused:
        fold_batchnorm(fast.backbone)
        for m in fast.modules():  # channels_last: new Parameters, the shared originals keep their layout
            for name, p in list(m._parameters.items()):
                if p is not None and p.dim() == 4:
                    m._parameters[name] = torch.nn.Parameter(p.contiguous(memory_format=torch.channels_last),
                                                             requires_grad=False)
    fast.transform = MaskCropTransform.of(fast.transform)
    if fused and device.type == "cpu":
        from massviz.detect.roialign import ChannelsLastMultiScaleRoIAlign

        fast.roi_heads.box_roi_pool = ChannelsLastMultiScaleRoIAlign(fast.roi_heads.box_roi_pool)
        fast.roi_heads.mask_roi_pool = ChannelsLastMultiScaleRoIAlign(fast.roi_heads.mask_roi_pool)
    if precision != "fp32":
        dtype, kind = _DTYPES[precision], device.type
        fast.backbone = ReducedPrecision(fast.backbone, kind, dtype)
        fast.rpn.head = ReducedPrecision(fast.rpn.head, kind, dtype)
        rh = fast.roi_heads
        rh.box_head = ReducedPrecision(rh.box_head, kind, dtype)
        rh.mask_head = ReducedPrecision(rh.mask_head, kind, dtype)
        rh.mask_predictor = ReducedPrecision(rh.mask_predictor, kind, dtype)
    return fast


def outputs_to_detections(output: dict, frame_index: int, threshold: float, classes) -> Detections:
    """torchvision output dict (one image) → Detections: score > threshold, kept classes, int boxes, masks > 0.5.

    ``output`` is torchvision's (full-image ``masks``) or the runtime model's (``mask_crops`` cut to the int boxes)."""
    scores = output["scores"].detach().float().cpu().numpy()
    labels = output["labels"].detach().cpu().numpy()
    keep = (scores > threshold) & np.isin(labels, list(classes))
    boxes = output["boxes"].detach().float().cpu().numpy()[keep]
    xyxy = np.array([[int(v) for v in box] for box in boxes], dtype=np.int32).reshape(-1, 4)
    if "mask_crops" in output:
        masks = [m for m, k in zip(output["mask_crops"], keep) if k]
    else:
        probs = output["masks"].detach().cpu()[torch.from_numpy(keep)]  # (N, 1, H, W): the instance axis is kept
        masks = [(probs[i, 0, y1:y2, x1:x2] > MASK_THRESHOLD).numpy() for i, (x1, y1, x2, y2) in enumerate(xyxy)]
    return Detections(frame=np.full(len(xyxy), frame_index), xyxy=xyxy, score=scores[keep],
                      class_id=labels[keep], masks=masks)


class MaskRCNNDetector:
    """``--detector maskrcnn``: the paper's Mask R-CNN (loaded lazily on the first frame).

    ``precision``: ``fp32`` (default, the paper's), ``bf16`` or ``fp16`` (module docstring); it is one of the
    ``settings()``, so it keys the trace cache. ``.model`` is torchvision's model; ``detect``/``detect_batch`` run a
    fast copy of it built on the first call (changes made to ``.model`` after that call are not seen).
    ``fused=False``: no BatchNorm folding / channels_last (torchvision's arithmetic exactly; for tests).
    """

    name = "maskrcnn"
    default_threshold = PAPER_THRESHOLD

    def __init__(self, threshold: float = PAPER_THRESHOLD, weights: str | Path | None = None, device: str | None = None,
                 pretrained: bool = True, classes=KEEP_CLASSES, precision: str = "fp32",
                 fused: bool = True):
        self.threshold = float(threshold)
        self.weights = None if weights is None else Path(weights)
        self.pretrained = pretrained
        self.classes = tuple(sorted(int(c) for c in classes))
        self.device = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
        check_precision(precision, self.device)
        self.precision = precision
        self.fused = bool(fused)
        self._model = None
        self._runtime = None

    def settings(self) -> dict:
        if self.weights is not None:  # by content: another file under the same name is another cache key
            from massviz.io.filehash import file_digest

            if getattr(self, "_weights_digest", None) is None:  # hashed once per detector (the file is ~170 MB)
                self._weights_digest = file_digest(self.weights) if self.weights.is_file() else "missing"
            src = f"{self.weights.resolve()}:{self._weights_digest}"
        else:
            src = "torchvision:COCO_V1" if self.pretrained else "random-init"
        out = {"weights": src, "classes": list(self.classes), "mask_threshold": MASK_THRESHOLD,
               "precision": self.precision}
        if self.device.type != "cpu":  # another device's kernels round differently: another cache entry
            out["device"] = self.device.type
        return out

    @property
    def model(self) -> torch.nn.Module:
        if self._model is None:
            self._model = build_model(self.threshold, self.weights, self.pretrained, self.classes).to(self.device)
        return self._model

    @property
    def default_batch(self) -> int:
        """Frames per forward when ``--batch`` is not given (``massviz.core.device.default_batch``: 1 on a CPU and
        in the faithful fp32 mode on CUDA, 8 in bf16/fp16 on CUDA)."""
        return default_batch(self.device, self.precision)

    @property
    def runtime(self) -> torch.nn.Module:
        """The fast copy of ``model`` that runs (``runtime_model``), built on first use."""
        if self._runtime is None:
            self._runtime = runtime_model(self.model, self.precision, self.device, fused=self.fused)
        return self._runtime

    def detect(self, frame: Frame) -> Detections:
        return self.detect_batch([frame])[0]

    def detect_batch(self, frames: list[Frame]) -> list[Detections]:
        """Detections of each frame, frames of one size in one forward (equal to ``detect`` frame by frame)."""
        out: list[Detections] = []
        i = 0
        while i < len(frames):  # runs of equal size: a batch pads to its largest image, so never mix sizes
            j = i + 1
            while j < len(frames) and frames[j].rgb.shape == frames[i].rgb.shape:
                j += 1
            out.extend(self._forward(frames[i:j]))
            i = j
        return out

    def _forward(self, frames: list[Frame]) -> list[Detections]:
        model = self.runtime
        with torch.inference_mode(), faithful_fp32(self.device, self.precision == "fp32"):
            images = [to_unit_float(torch.from_numpy(f.rgb).to(self.device).permute(2, 0, 1))  # = ToTensor()
                      for f in frames]
            outputs = forward_detections(model, images, paste=True)
            return [outputs_to_detections(o, f.index, self.threshold, self.classes) for o, f in zip(outputs, frames)]

    def detect_device(self, frames: list[Frame], rgb: torch.Tensor) -> tuple[list[Detections], MaskWindows]:
        """``detect_batch`` for frames already on the device (``rgb``: (N, H, W, 3) uint8 there), masks left there:
        each frame's ``Detections`` (boxes, scores, classes; masks not filled) and one ``MaskWindows`` of all their
        masks, in order. One copy to the host (the boxes, scores and classes of every frame)."""
        model = self.runtime
        with torch.inference_mode(), faithful_fp32(self.device, self.precision == "fp32"):
            images = [to_unit_float(rgb[i].permute(2, 0, 1)) for i in range(len(frames))]  # = ToTensor()
            outputs = forward_detections(model, images, paste=False)
        with torch.inference_mode():
            counts = [len(o["scores"]) for o in outputs]
            boxes = torch.cat([o["boxes"].float() for o in outputs]) if outputs else torch.zeros((0, 4))
            host = torch.cat([boxes, torch.cat([o["scores"].float()[:, None] for o in outputs]),
                              torch.cat([o["labels"].float()[:, None] for o in outputs])], dim=1).cpu().numpy()
            probs = torch.cat([o["masks"] for o in outputs]) if outputs else torch.zeros((0, 1, 28, 28))
            scores, labels = host[:, 4].astype(np.float32), host[:, 5].astype(np.int64)
            keep = (scores > self.threshold) & np.isin(labels, list(self.classes))
            xyxy = host[:, :4].astype(np.float32).astype(np.int32)  # int(v): truncation, as outputs_to_detections
            dets, start = [], 0
            for f, n in zip(frames, counts):
                sl = slice(start, start + n)
                k = keep[sl]
                dets.append(Detections(frame=np.full(int(k.sum()), f.index), xyxy=xyxy[sl][k], score=scores[sl][k],
                                       class_id=labels[sl][k]))
                start += n
            kept = torch.from_numpy(np.flatnonzero(keep)).to(probs.device)
            h, w = (int(v) for v in rgb.shape[1:3])
            return dets, MaskWindows(probs[kept], boxes[kept], h, w)
