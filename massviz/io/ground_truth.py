"""Ground-truth instance masks of a recording (``meta.json``'s ``instance_masks`` pattern, e.g. the samples'
``gt/{frame:06d}.png``): read here, turned into per-detection overlaps the flags read (``massviz.core.flags``).

:func:`with_ground_truth` is called where a trace is made from a recording (``massviz.app``) and where one is read
from a file (``massviz.io.trace_file.load_trace``); it reads each frame's mask once (frames with detections only).
"""
from __future__ import annotations

import dataclasses
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np

from massviz.core.flags import ground_truth_source, mask_overlap
from massviz.core.types import Detections
from massviz.errors import DataError
from massviz.io.untrusted import decode_image, frame_path


@lru_cache(maxsize=256)
def read_instance_image(path: str, size: tuple[int, int] | None = None) -> np.ndarray | None:
    """The instance-id image of one ground-truth PNG (first channel), None when missing or unreadable. Its header
    is checked before it is decoded (a small file may declare gigabytes of pixels): more than massviz decodes, or
    another size than ``size`` (the frames' width, height), is a ``DataError`` naming the file."""
    if not Path(path).is_file():
        return None
    img = decode_image(path, "ground-truth image", flags=cv2.IMREAD_UNCHANGED, formats=("PNG",), error=DataError,
                       expected=size)
    return None if img is None else (img if img.ndim == 2 else img[..., 0])


def ground_truth_masks(trace, frame: int) -> tuple[np.ndarray, dict[int, str]] | None:
    """(instance-id image of ``frame``, {id: name}) from the recording's ``meta.json`` ground truth (``trace``: a
    ``Trace`` or its ``RecordingInfo``), or None when unknown (no ``instance_masks`` / ``instances``, a pattern other
    than ``...{frame}...`` or one leading outside the recording folder (``massviz.io.untrusted.frame_path``), a
    missing, oversized or unreadable PNG, or one of another size than the frames)."""
    info = getattr(trace, "recording", trace)
    gt = info.ground_truth
    root = info.path
    if gt is None or not gt.instance_masks or not gt.instances or not root:
        return None
    try:  # the pattern comes from a data file: only {frame}, and inside the recording folder
        path = frame_path(gt.instance_masks, root, int(frame), root, "instance_masks")
    except DataError:
        return None
    img = read_instance_image(str(path), (info.width, info.height) if info.height else None)
    if img is None or (info.height and img.shape[:2] != (info.height, info.width)):
        return None
    return img, dict(gt.instances)


def with_ground_truth(trace):
    """``trace`` with every detection's ground-truth overlap (``Detections.gt_iou``, ``gt_instance``,
    ``gt_fraction``: ``massviz.core.flags.mask_overlap``) read from its recording's instance masks, its flags cleared
    (the caller's analysis stage makes them with the overlaps: ``massviz.core.trace.analyse_trace`` or
    ``Trace.reselect``); ``trace`` itself when it has no ground truth or already carries these overlaps."""
    source = ground_truth_source(trace.recording)
    if not source or trace.ground_truth_source == source:
        return trace
    dets = trace.detections
    iou = np.full(len(dets), np.nan)
    instance = np.full(len(dets), -1, np.int32)
    fraction = np.full(len(dets), np.nan)
    for frame, idx in dets.indices_by_frame().items():
        gt = ground_truth_masks(trace, frame)
        if gt is None:
            continue
        img, names = gt
        for i in idx:
            iou[i], instance[i], fraction[i] = mask_overlap(dets.full_mask(int(i), *img.shape[:2]), img, names)
    new = Detections(**{n: getattr(dets, n) for n in Detections._ARRAYS if not n.startswith("gt_")}, gt_iou=iou,
                     gt_instance=instance, gt_fraction=fraction, masks=dets.masks, patches=dets.patches)
    return dataclasses.replace(trace, detections=new, ground_truth_source=source, flags=None)


__all__ = ["read_instance_image", "ground_truth_masks", "with_ground_truth"]
