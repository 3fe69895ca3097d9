"""``--detector replay``: detections from a file instead of a model.

``--replay PATH`` is either

* a trace saved by an earlier run (any ``.npz`` of the trace cache), or
* a JSON file (documented format)::

      {"detections": [
          {"frame": 12, "box": [x1, y1, x2, y2], "score": 0.93, "class": "cup",
           "mask": "masks/000012_0.png"},
          ...
      ]}

  ``box`` is in pixels (x2/y2 exclusive; floats are truncated as the paper's code does); ``class`` is one of cup,
  book, wine glass, bottle, object, or a COCO category id; ``mask`` (optional) is a PNG, relative to the JSON file,
  either full-frame or box-sized, non-zero inside the object; without it the whole box is the mask.
"""
from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np

from massviz.errors import DataError
from massviz.core.trace import Trace
from massviz.core.types import COCO_KEEP, OBJECT_CLASS_ID, Detections, Frame


def _class_id(value, path: Path, row: int) -> int:
    if isinstance(value, int):
        return value
    if value == "object":
        return OBJECT_CLASS_ID
    if value in COCO_KEEP:
        return COCO_KEEP[value]
    raise DataError(f"detection {row}: unknown class {value!r} (use cup, book, wine glass, bottle, object or a "
                    "COCO id)", path)


def _load_json(path: Path) -> Detections:
    try:
        data = json.loads(path.read_text())
        rows = data["detections"]
        if not isinstance(rows, list):
            raise TypeError("'detections' must be a list")
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise DataError(f"not a replay detections file ({type(err).__name__}: {err})", path) from None
    frames, boxes, scores, classes, masks = [], [], [], [], []
    for row, det in enumerate(rows):
        try:
            x1, y1, x2, y2 = (int(v) for v in det["box"])
            frame, score = int(det["frame"]), float(det.get("score", 1.0))
        except (KeyError, TypeError, ValueError) as err:
            raise DataError(f"detection {row}: needs 'frame' and 'box' [x1, y1, x2, y2] ({err})", path) from None
        if x2 <= x1 or y2 <= y1:
            raise DataError(f"detection {row}: empty box {det['box']}", path)
        mask = np.ones((y2 - y1, x2 - x1), dtype=bool)
        if det.get("mask"):
            mpath = path.parent / det["mask"]
            img = cv2.imread(str(mpath), cv2.IMREAD_GRAYSCALE)
            if img is None:
                raise DataError(f"detection {row}: cannot read mask {det['mask']}", path)
            crop = img if img.shape == mask.shape else img[y1:y2, x1:x2]
            if crop.shape != mask.shape:
                raise DataError(f"detection {row}: mask {det['mask']} is {img.shape[1]}x{img.shape[0]}, neither the "
                                f"box's {x2 - x1}x{y2 - y1} nor a full frame holding the box", path)
            mask = crop > 0
        frames.append(frame), boxes.append([x1, y1, x2, y2]), scores.append(score)
        classes.append(_class_id(det.get("class", "object"), path, row)), masks.append(mask)
    return Detections(frame=frames, xyxy=boxes, score=scores, class_id=classes, masks=masks)


def load_detections(path: str | Path) -> Detections:
    """All detections of a replay source (trace .npz or JSON)."""
    path = Path(path)
    if not path.is_file():
        raise DataError("replay file not found", path)
    if path.suffix == ".npz":
        return Trace.load(path).detections
    return _load_json(path)


class ReplayDetector:
    """Returns, for each frame, the saved detections of that frame with score > threshold."""

    name = "replay"

    def __init__(self, source: str | Path, threshold: float = 0.4):
        self.source = Path(source)
        self.threshold = float(threshold)
        dets = load_detections(self.source)
        self._by_frame = defaultdict(list)
        for i, f in enumerate(dets.frame):
            self._by_frame[int(f)].append(i)
        self._dets = dets

    def settings(self) -> dict:
        st = self.source.stat()
        return {"source": str(self.source.resolve()), "size": st.st_size, "mtime_ns": st.st_mtime_ns}

    def detect(self, frame: Frame) -> Detections:
        idx = self._by_frame.get(frame.index, [])
        dets = self._dets[idx]
        dets = dets[dets.score > self.threshold]
        x1, y1, x2, y2 = dets.xyxy.T
        outside = (x1 < 0) | (y1 < 0) | (x2 > frame.width) | (y2 > frame.height)
        if outside.any():
            raise DataError(f"frame {frame.index}: box {dets.xyxy[outside][0].tolist()} lies outside the "
                            f"{frame.width}x{frame.height} frame (is this replay file for this recording?)",
                            self.source)
        # features and predictions are recomputed by the pipeline on this recording's frames
        return Detections(frame=dets.frame, xyxy=dets.xyxy, score=dets.score, class_id=dets.class_id,
                          masks=dets.masks)
