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

The file is untrusted: ``frame`` must be an integer >= 0, box values finite numbers in [0, 2^31), ``score`` in
[0, 1]; a ``mask`` must be a relative path that stays inside the JSON file's folder (no ``..``, no absolute path, no
symlink out) and its PNG header is checked before it is decoded. A box is checked against the frame before its mask
is allocated. Anything else is one ``DataError`` naming the file and the detection.
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from massviz.core.detector import PAPER_THRESHOLD
from massviz.core.types import COCO_KEEP, OBJECT_CLASS_ID, Detections, Frame, PackedMask
from massviz.errors import DataError
from massviz.io.trace_file import load_trace
from massviz.io.untrusted import MAX_INDEX, confined, decode_image, image_header_size, load_json, number

#: largest replay JSON read.
MAX_REPLAY_JSON_BYTES = 256 << 20


def _class_id(value, path: Path, row: int) -> int:
    if isinstance(value, int) and not isinstance(value, bool):
        if not -1 <= value <= 10_000:
            raise DataError(f"detection {row}: class id {value} is not a COCO category id", path)
        return value
    if value == "object":
        return OBJECT_CLASS_ID
    if isinstance(value, str) and value in COCO_KEEP:
        return COCO_KEEP[value]
    raise DataError(f"detection {row}: unknown class {value!r} (use cup, book, wine glass, bottle, object or a "
                    "COCO id)"[:300], path)


def _load_json(path: Path) -> tuple[Detections, list[Path], dict[int, tuple[int, int]]]:
    """The detections of a replay JSON file (full-box masks left as None: made after the box is checked against
    the frame), the mask files it names and, for each detection whose mask is a full frame, that frame's size
    (width, height: checked against the recording's frames when they are known)."""
    try:
        data = load_json(path, "replay detections file", DataError, MAX_REPLAY_JSON_BYTES)
        rows = data["detections"] if isinstance(data, dict) else None
        if not isinstance(rows, list):
            raise TypeError("expected an object whose 'detections' is a list")
    except (OSError, ValueError, KeyError, TypeError, RecursionError) as err:
        raise DataError(f"not a replay detections file ({type(err).__name__}: {err})"[:300], path) from None
    frames, boxes, scores, classes, masks, files, frame_sized = [], [], [], [], [], [], {}
    for row, det in enumerate(rows):
        where = f"detection {row}:"
        if not isinstance(det, dict) or "frame" not in det or "box" not in det:
            raise DataError(f"{where} needs 'frame' and 'box' [x1, y1, x2, y2]", path)
        box = det["box"]
        if not isinstance(box, list) or len(box) != 4:
            raise DataError(f"{where} 'box' must be 4 numbers [x1, y1, x2, y2], got {box!r}"[:300], path)
        x1, y1, x2, y2 = (int(number(v, f"{where} box {n}", path, lo=0, hi=MAX_INDEX))
                          for n, v in zip(("x1", "y1", "x2", "y2"), box))
        frame = number(det["frame"], f"{where} 'frame'", path, lo=0, hi=MAX_INDEX, integral=True)
        score = number(det.get("score", 1.0), f"{where} 'score'", path, lo=0, hi=1)
        if x2 <= x1 or y2 <= y1:
            raise DataError(f"{where} empty box {box}", path)
        mask = None
        if det.get("mask") is not None:
            mpath = confined(path.parent, det["mask"], path, f"{where} mask")
            h, w = y2 - y1, x2 - x1
            declared = image_header_size(mpath)
            if declared is not None and declared != (w, h) and (declared[0] < x2 or declared[1] < y2):
                raise DataError(f"{where} mask {det['mask']} declares {declared[0]}x{declared[1]} pixels, neither the "
                                f"box's {w}x{h} nor a full frame holding the box; not decoded", path)
            img = decode_image(mpath, "mask image", flags=cv2.IMREAD_GRAYSCALE, formats=("PNG",), error=DataError)
            if img is None:
                raise DataError(f"{where} cannot read mask {det['mask']}", path)
            if img.shape != (h, w):
                frame_sized[row] = (img.shape[1], img.shape[0])
            crop = img if img.shape == (h, w) else img[y1:y2, x1:x2]
            if crop.shape != (h, w):
                raise DataError(f"{where} mask {det['mask']} is {img.shape[1]}x{img.shape[0]}, neither the "
                                f"box's {w}x{h} nor a full frame holding the box", path)
            mask = crop > 0
            files.append(mpath)
        frames.append(frame), boxes.append([x1, y1, x2, y2]), scores.append(score)
        classes.append(_class_id(det.get("class", "object"), path, row)), masks.append(mask)
    return Detections(frame=frames, xyxy=boxes, score=scores, class_id=classes, masks=masks), files, frame_sized


def _load(path: Path) -> tuple[Detections, list[Path], float, dict[int, tuple[int, int]]]:
    """The detections, the mask files they name, the default score cut (a trace's own selection cut: what the run
    it replays chose with; a JSON file's: the paper's) and the sizes of full-frame masks (see ``_load_json``)."""
    if not path.is_file():
        raise DataError("replay file not found", path)
    if path.suffix == ".npz":
        trace = load_trace(path)
        return trace.detections, [], float(trace.threshold), {}
    dets, files, frame_sized = _load_json(path)
    return dets, files, PAPER_THRESHOLD, frame_sized


class ReplayDetector:
    """Returns, for each frame, the saved detections of that frame with score > threshold (default: a saved trace's
    own selection cut, a JSON file's the paper's 0.4)."""

    name = "replay"

    def __init__(self, source: str | Path, threshold: float | None = None):
        self.source = Path(source)
        dets, self._files, self.default_threshold, self._frame_sized = _load(self.source)
        self.threshold = self.default_threshold if threshold is None else float(threshold)
        self._by_frame = dets.indices_by_frame()
        self._dets = dets

    def settings(self) -> dict:
        """The source by its content (and that of the mask PNGs it names): an edited file is a new cache key."""
        from massviz.io.filehash import file_digest

        return {"source": str(self.source.resolve()), "digest": file_digest(self.source),
                "masks": [file_digest(p) for p in self._files]}

    def detect(self, frame: Frame) -> Detections:
        idx = self._by_frame.get(frame.index, np.zeros(0, dtype=np.int64))
        for i in idx.tolist():
            if (size := self._frame_sized.get(i)) is not None and size != (frame.width, frame.height):
                raise DataError(f"detection {i}: its mask is a {size[0]}x{size[1]} image, neither its box nor a "
                                f"{frame.width}x{frame.height} frame (is this replay file for this recording?)",
                                self.source)
        dets = self._dets[idx]
        dets = dets[dets.score > self.threshold]
        x1, y1, x2, y2 = dets.xyxy.T
        outside = (x1 < 0) | (y1 < 0) | (x2 > frame.width) | (y2 > frame.height)
        if outside.any():
            raise DataError(f"frame {frame.index}: box {dets.xyxy[outside][0].tolist()} lies outside the "
                            f"{frame.width}x{frame.height} frame (is this replay file for this recording?)",
                            self.source)
        # the whole box is the mask of a detection without one; made only now that the box is known to fit
        masks = [m if m is not None else PackedMask(np.ones((int(b[3] - b[1]), int(b[2] - b[0])), bool))
                 for m, b in zip(dets.masks, dets.xyxy)]
        # features and predictions are recomputed by the pipeline on this recording's frames
        return Detections(frame=dets.frame, xyxy=dets.xyxy, score=dets.score, class_id=dets.class_id, masks=masks)
