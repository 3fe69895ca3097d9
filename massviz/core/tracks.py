"""Object tracks: detections of consecutive processed frames linked into one id per object.

A small online tracker in the style of the IoU tracker of Bochinski, Eiselein and Sikora (AVSS 2017), with the depth
every detection already has. For each processed frame, every (open track, detection) pair is a candidate when

* **overlap**: box IoU >= :data:`IOU_MIN` with the track's last box *or* with that box moved on at the track's last
  velocity (constant-velocity prediction: a lifted pitcher grows frame after frame);
* **depth continuity**: |d - d_last| <= :data:`DEPTH_GATE` x the larger of the two (a hand moves an object a few
  centimetres per frame, not across the room);
* **same metric size**: box width x d and height x d (proportional to the size in mm; no intrinsics needed for the
  ratio) within :data:`SIZE_GATE` x of the track's median over its last :data:`SIZE_HISTORY` detections: an object
  coming nearer grows in the image as its depth shrinks, another object at another depth does not;
* **recent**: the track was last seen at most :data:`MAX_GAP_S` seconds earlier (detector flicker, a hand passing).

Candidates are matched greedily, highest IoU first (on the few detections per frame this is what the Hungarian
matching gives), each track and detection at most once; an unmatched detection opens a new track. Ids are 1, 2, ...
in order of appearance; every detection gets one (detections without depth are matched by overlap alone).
Class is not a gate: Mask R-CNN flips a cup to a wine glass between frames, and the flags use a track's class mix.

Why not ``supervision``'s ByteTrack (the well-kept choice): supervision <= 0.26 requires ``opencv-python`` (the GUI
build; it and the project's ``opencv-python-headless`` both install ``cv2``); supervision 0.31 dropped ByteTrack for
the ``trackers`` package, which requires ``opencv-python`` again; both pull scipy (and 0.31 PyAV, ~250 MB together).
ByteTrack also knows nothing of depth, and leaves some detections without an id. On the bundled samples this
tracker and ByteTrack 0.26 agree on the objects (the pitcher in ``cup_handover``, lifted in frames 7-11, is one track).
"""
from __future__ import annotations

import math

import numpy as np

from massviz.core.types import Detections

#: minimum box IoU (with the last box or its constant-velocity prediction) to continue a track.
IOU_MIN = 0.3
#: largest relative change of the mean depth d between two linked detections.
DEPTH_GATE = 0.35
#: largest ratio of metric box size (width x d, height x d) between a detection and its track.
SIZE_GATE = 1.75
#: a track's metric size is the median over its last this many detections.
SIZE_HISTORY = 5
#: a track not seen for longer than this (seconds) is closed.
MAX_GAP_S = 1.0
#: frame rate assumed when the recording does not say.
DEFAULT_FPS = 30.0


def box_iou(a, b) -> np.ndarray:
    """IoU matrix (len(a) x len(b)) of x1, y1, x2, y2 boxes, in float64; 0 where the union is empty.

    The one box IoU of massviz (tracker, ``massviz compare``, exclusion matching); numpy so that warm commands do not
    import torch. Equal to ``torchvision.ops.box_iou`` in float64 with NaN (empty union) as 0 (tests/test_copies.py).
    """
    a = np.asarray(a, dtype=np.float64).reshape(-1, 4)
    b = np.asarray(b, dtype=np.float64).reshape(-1, 4)
    area_a = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1])
    area_b = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    w = np.minimum(a[:, None, 2], b[None, :, 2]) - np.maximum(a[:, None, 0], b[None, :, 0])
    h = np.minimum(a[:, None, 3], b[None, :, 3]) - np.maximum(a[:, None, 1], b[None, :, 1])
    inter = np.maximum(w, 0.0) * np.maximum(h, 0.0)
    union = area_a[:, None] + area_b[None, :] - inter
    return np.where(union > 0, inter / np.where(union > 0, union, 1.0), 0.0)


def metric_size(xyxy, d: float) -> tuple[float, float]:
    """(box width x d, box height x d): the object's size in mm times the focal length (NaN without depth)."""
    return float((xyxy[2] - xyxy[0]) * d), float((xyxy[3] - xyxy[1]) * d)


class _Track:
    __slots__ = ("id", "frame", "box", "velocity", "d", "sizes")

    def __init__(self, tid: int, frame: int, box: np.ndarray, d: float):
        self.id, self.frame, self.box, self.d = tid, frame, box, d
        self.velocity = np.zeros(4)
        self.sizes = [metric_size(box, d)] if math.isfinite(d) else []

    def size(self) -> tuple[float, float] | None:
        if not self.sizes:
            return None
        w, h = np.median(np.asarray(self.sizes), axis=0)
        return float(w), float(h)

    def update(self, frame: int, box: np.ndarray, d: float) -> None:
        self.velocity = (box - self.box) / max(frame - self.frame, 1)
        self.frame, self.box, self.d = frame, box, d
        if math.isfinite(d):
            self.sizes = (self.sizes + [metric_size(box, d)])[-SIZE_HISTORY:]


class Tracker:
    """Online tracker (module docstring): ``update(frame_index, detections)`` returns the track id of each.

    ``fps``: the recording's frame rate (for :data:`MAX_GAP_S`). Feed frames in increasing order; ``detections``
    need ``xyxy`` and ``d`` (the features stage's mean depth).
    """

    def __init__(self, fps: float | None = None):
        fps = float(fps) if fps and fps > 0 else DEFAULT_FPS
        self.max_gap = max(1, int(round(MAX_GAP_S * fps)))
        self.tracks: dict[int, _Track] = {}
        self.next_id = 1

    def _gate(self, tr: _Track, frame: int, boxes: np.ndarray, depths: np.ndarray) -> np.ndarray:
        """IoU of each (track, detection) candidate, NaN where a gate rejects it (all detections at once)."""
        gap = frame - tr.frame
        overlap = np.maximum(box_iou(tr.box, boxes)[0], box_iou(tr.box + tr.velocity * gap, boxes)[0])
        ok = overlap >= IOU_MIN
        both = np.isfinite(depths) & math.isfinite(tr.d)
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            ok &= ~(both & (np.abs(depths - tr.d) > DEPTH_GATE * np.maximum(depths, tr.d)))
            size = tr.size()
            if size is not None:
                w = (boxes[:, 2] - boxes[:, 0]) * depths
                h = (boxes[:, 3] - boxes[:, 1]) * depths
                positive = (min(size) > 0) & (np.minimum(w, h) > 0)
                rw, rh = w / size[0], h / size[1]
                worst = np.maximum(np.maximum(rw, 1 / rw), np.maximum(rh, 1 / rh))
                ok &= ~(both & (~positive | (worst > SIZE_GATE)))
        return np.where(ok, overlap, np.nan)

    def update(self, frame: int, dets: Detections) -> np.ndarray:
        """Track ids (int64, >= 1) of ``dets``, all made on frame ``frame``."""
        frame = int(frame)
        for tid in [t for t, tr in self.tracks.items() if frame - tr.frame > self.max_gap]:
            del self.tracks[tid]
        boxes = np.asarray(dets.xyxy, dtype=np.float64).reshape(-1, 4)
        depths = np.asarray(dets.d, dtype=np.float64).reshape(-1)
        candidates = []
        for tid, tr in self.tracks.items():
            if tr.frame >= frame or not len(boxes):
                continue
            overlap = self._gate(tr, frame, boxes, depths)
            for j in np.flatnonzero(~np.isnan(overlap)):
                candidates.append((-float(overlap[j]), frame - tr.frame, tid, int(j)))
        ids = np.zeros(len(boxes), dtype=np.int64)
        used = set()
        for _, _, tid, j in sorted(candidates):
            if ids[j] or tid in used:
                continue
            used.add(tid)
            ids[j] = tid
            self.tracks[tid].update(frame, boxes[j], float(depths[j]))
        for j in np.flatnonzero(ids == 0):
            ids[j] = self.next_id
            self.tracks[self.next_id] = _Track(self.next_id, frame, boxes[j], float(depths[j]))
            self.next_id += 1
        return ids


def assign_tracks(dets: Detections, fps: float | None = None) -> np.ndarray:
    """Track ids of all ``dets`` of a recording (any order; frames taken in increasing order)."""
    ids = np.zeros(len(dets), dtype=np.int64)
    tracker = Tracker(fps)
    for frame in np.unique(dets.frame):
        idx = np.flatnonzero(dets.frame == frame)
        ids[idx] = tracker.update(int(frame), dets[idx])
    return ids


def track_members(dets: Detections, track: int) -> np.ndarray:
    """Indices of the detections of ``track``, in frame order."""
    idx = np.flatnonzero(np.asarray(dets.track) == int(track))
    return np.array(sorted(idx.tolist(), key=lambda i: (int(dets.frame[i]), i)), dtype=np.int64)


__all__ = ["Tracker", "assign_tracks", "track_members", "box_iou", "metric_size", "IOU_MIN", "DEPTH_GATE",
           "SIZE_GATE", "MAX_GAP_S"]
