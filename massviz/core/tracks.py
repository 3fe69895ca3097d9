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


class Tracker:
    """Online tracker (module docstring): ``update(frame_index, detections)`` returns the track id of each.

    ``fps``: the recording's frame rate (for :data:`MAX_GAP_S`). Feed frames in increasing order; ``detections``
    need ``xyxy`` and ``d`` (the features stage's mean depth).

    The open tracks are parallel arrays, gated against all of a frame's detections at once (a GPU run keeps ~100
    detections a frame and, with :data:`MAX_GAP_S` of 1 s, up to thousands of open tracks).
    """

    def __init__(self, fps: float | None = None):
        fps = float(fps) if fps and fps > 0 else DEFAULT_FPS
        self.max_gap = max(1, int(round(MAX_GAP_S * fps)))
        self.ids = np.zeros(0, np.int64)
        self.frame = np.zeros(0, np.int64)
        self.box = np.zeros((0, 4))
        self.velocity = np.zeros((0, 4))
        self.d = np.zeros(0)
        self.size = np.zeros((0, 2))  # median metric size over the last SIZE_HISTORY detections with depth; NaN: none
        # each track's last SIZE_HISTORY metric sizes (a ring, NaN where unfilled) and how many it has had
        self.history = np.zeros((0, SIZE_HISTORY, 2))
        self.seen = np.zeros(0, np.int64)
        self.next_id = 1

    def _gate(self, frame: int, boxes: np.ndarray, depths: np.ndarray) -> np.ndarray:
        """IoU of each (open track, detection) candidate (T x N), NaN where a gate rejects it."""
        gap = (frame - self.frame).astype(np.float64)
        overlap = np.maximum(box_iou(self.box, boxes), box_iou(self.box + self.velocity * gap[:, None], boxes))
        ok = overlap >= IOU_MIN
        both = np.isfinite(depths)[None, :] & np.isfinite(self.d)[:, None]
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            ok &= ~(both & (np.abs(depths[None, :] - self.d[:, None]) > DEPTH_GATE * np.maximum(depths[None, :],
                                                                                                 self.d[:, None])))
            sized = ~np.isnan(self.size[:, 0])
            w = (boxes[:, 2] - boxes[:, 0]) * depths
            h = (boxes[:, 3] - boxes[:, 1]) * depths
            positive = (self.size.min(axis=1) > 0)[:, None] & (np.minimum(w, h) > 0)[None, :]
            rw, rh = w[None, :] / self.size[:, :1], h[None, :] / self.size[:, 1:]
            worst = np.maximum(np.maximum(rw, 1 / rw), np.maximum(rh, 1 / rh))
            ok &= ~(sized[:, None] & both & (~positive | (worst > SIZE_GATE)))
        return np.where(ok, overlap, np.nan)

    def _record_sizes(self, rows: np.ndarray, boxes: np.ndarray, depths: np.ndarray) -> None:
        """Tracks ``rows`` (distinct) get the metric sizes of ``boxes`` at ``depths`` (those with depth) into their
        histories, and ``size`` their medians."""
        has = np.isfinite(depths)
        r = rows[has]
        sizes = np.stack([(boxes[has, 2] - boxes[has, 0]) * depths[has],
                          (boxes[has, 3] - boxes[has, 1]) * depths[has]], axis=1)
        self.history[r, self.seen[r] % SIZE_HISTORY] = sizes
        self.seen[r] += 1
        self.size[rows] = _median_of_filled(self.history[rows], np.minimum(self.seen[rows], SIZE_HISTORY))

    def _match(self, frame: int, boxes: np.ndarray, depths: np.ndarray, older: np.ndarray):
        """Greedy matching of the open tracks ``older`` to the detections: (track rows, detection columns)."""
        overlap = self._gate(frame, boxes, depths)[older]
        r, j = np.nonzero(~np.isnan(overlap))
        t = older[r]
        # greedy, highest IoU first; ties: the shorter gap, the older track, the earlier detection
        order = np.lexsort((j, self.ids[t], frame - self.frame[t], -overlap[r, j]))
        return greedy_pairs(t[order], j[order])

    def update(self, frame: int, dets: Detections) -> np.ndarray:
        """Track ids (int64, >= 1) of ``dets``, all made on frame ``frame``."""
        frame = int(frame)
        alive = frame - self.frame <= self.max_gap
        if not alive.all():
            self.ids, self.frame, self.box = self.ids[alive], self.frame[alive], self.box[alive]
            self.velocity, self.d, self.size = self.velocity[alive], self.d[alive], self.size[alive]
            self.history, self.seen = self.history[alive], self.seen[alive]
        boxes = np.asarray(dets.xyxy, dtype=np.float64).reshape(-1, 4)
        depths = np.asarray(dets.d, dtype=np.float64).reshape(-1)
        ids = np.zeros(len(boxes), dtype=np.int64)
        older = np.flatnonzero(self.frame < frame)
        if len(boxes) and len(older):
            rows, cols = self._match(frame, boxes, depths, older)
            ids[cols] = self.ids[rows]
            self.velocity[rows] = (boxes[cols] - self.box[rows]) / np.maximum(frame - self.frame[rows], 1)[:, None]
            self.frame[rows], self.box[rows], self.d[rows] = frame, boxes[cols], depths[cols]
            self._record_sizes(rows, boxes[cols], depths[cols])
        new = np.flatnonzero(ids == 0)
        if len(new):
            ids[new] = np.arange(self.next_id, self.next_id + len(new))
            self.next_id += len(new)
            first = len(self.ids)
            self.ids = np.concatenate([self.ids, ids[new]])
            self.frame = np.concatenate([self.frame, np.full(len(new), frame, np.int64)])
            self.box = np.concatenate([self.box, boxes[new]])
            self.velocity = np.concatenate([self.velocity, np.zeros((len(new), 4))])
            self.d = np.concatenate([self.d, depths[new]])
            self.size = np.concatenate([self.size, np.full((len(new), 2), np.nan)])
            self.history = np.concatenate([self.history, np.full((len(new), SIZE_HISTORY, 2), np.nan)])
            self.seen = np.concatenate([self.seen, np.zeros(len(new), np.int64)])
            self._record_sizes(np.arange(first, first + len(new)), boxes[new], depths[new])
        return ids


def greedy_pairs(rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pairs a greedy matching keeps from candidates (``rows[k]``, ``cols[k]``) in order of preference: each
    candidate whose row and column no earlier kept pair uses. In rounds, as arrays: a remaining candidate that is
    the first remaining one of its row and of its column is one greedy keeps (every earlier candidate of its row or
    column is gone, so none of them was kept); those are kept at once and the candidates they block removed."""
    rows, cols = np.asarray(rows, np.int64), np.asarray(cols, np.int64)
    kept = np.zeros(len(rows), bool)
    left = np.ones(len(rows), bool)
    while left.any():
        idx = np.flatnonzero(left)
        _, first_of_row = np.unique(rows[idx], return_index=True)
        _, first_of_col = np.unique(cols[idx], return_index=True)
        take = np.intersect1d(idx[first_of_row], idx[first_of_col], assume_unique=True)
        kept[take] = True
        left &= ~(np.isin(rows, rows[take]) | np.isin(cols, cols[take]))
    return rows[kept], cols[kept]


def _median_of_filled(values: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """``np.median(values[i, :counts[i]], axis=0)`` for each i, bit for bit (the mean of the two middle values is
    their sum / 2, as numpy computes it); NaN where ``counts`` is 0. ``values`` (N, H, 2), NaN where unfilled."""
    out = np.full((len(values), 2), np.nan)
    filled = counts > 0
    if not filled.any():
        return out
    s = np.sort(values[filled], axis=1)  # NaN (unfilled) last
    n = counts[filled]
    at = np.arange(len(s))
    hi, lo = s[at, n // 2], s[at, (n - 1) // 2]
    out[filled] = np.where((n % 2 == 1)[:, None], hi, (lo + hi) / 2)
    return out


def assign_tracks(dets: Detections, fps: float | None = None) -> np.ndarray:
    """Track ids of all ``dets`` of a recording (any order; frames taken in increasing order)."""
    ids = np.zeros(len(dets), dtype=np.int64)
    tracker = Tracker(fps)
    for frame, idx in dets.indices_by_frame().items():
        ids[idx] = tracker.update(frame, dets[idx])
    return ids


def track_members(dets: Detections, track: int) -> np.ndarray:
    """Indices of the detections of ``track``, in frame order."""
    idx = np.flatnonzero(np.asarray(dets.track) == int(track))
    return np.array(sorted(idx.tolist(), key=lambda i: (int(dets.frame[i]), i)), dtype=np.int64)


__all__ = ["Tracker", "assign_tracks", "greedy_pairs", "track_members", "box_iou", "metric_size", "IOU_MIN", "DEPTH_GATE",
           "SIZE_GATE", "MAX_GAP_S"]
