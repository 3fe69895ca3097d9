"""Flags: which chosen patches are probably *not* the container, and why — the analysis stage run after selection.

``analyse(trace)`` returns a :class:`Flags` (one :class:`PatchFlag` per chosen patch, nearest first), stored in
``trace.flags`` by the stages that make or change a selection (``massviz.core.trace``: the pipeline's finish,
``Trace.reselect``, ``analyse_trace``), never by constructing or replacing a trace; the trace file saves it, and every
consumer (``massviz log`` / ``estimate``, the Rerun logger, ``massviz render``, the notebooks) reads ``trace.flags``. It needs the detections' track ids (``massviz.core.tracks``).

**Cues** (need no ground truth; ``PatchFlag.cues``). The paper assumes the container is the nearest object; in a
hand-over the recording *ends* with the container held out to the camera. So the **container's track** is the track
of the nearest usable detection (score > threshold, with depth, not excluded) in the last :data:`END_FRACTION` of the
processed frames (at least :data:`END_MIN_FRAMES`). For each chosen patch:

* ``track``: it is on another track than the container's;
* ``size``: its metric size (box width x d / fx, height x d / fy, in mm) differs from the container track's median
  by more than :data:`SIZE_RATIO` x in width or height (a pitcher is not a cup, however near);
* ``depth_jump``: its track's depth changes faster than :data:`JUMP_M_S` m/s into or out of it (something lifted
  towards the camera, or a mask leaking onto what is behind);
* ``time``: its track came near and went away again (d grows by more than max(:data:`RECEDE_MM`,
  :data:`RECEDE_FRACTION` x d) after the patch's frame: a handed-over container does not go back), or its track stood
  still (box centre within :data:`STATIC_PX` px, d within :data:`STATIC_MM` mm) in at least
  :data:`STATIC_FRACTION` of the processed frames (nothing standing still is being handed over);
* ``class``: its class differs from the container track's most common class (never with the class-agnostic depth
  detector);
* ``border``: its box touches the image border (within :data:`BORDER_PX` px): the object is cut by it, so neither its
  patch nor its box ratios a, b describe the whole object (the table's front corner, a gripper entering the view);
* ``implausible``: its metric size (as for ``size``; needs intrinsics) is larger than :data:`MAX_CONTAINER_MM` in
  width or height: not a hand-held container.
* ``shape``: not container-like by its box: more than :data:`MAX_WIDTH_RATIO` x as wide as tall (a box lying on its
  side, e.g. a 215 x 78 mm cereal box in front of the cup), more than :data:`MAX_HEIGHT_RATIO` x as tall as wide, or
  (with intrinsics) smaller than :data:`MIN_CONTAINER_MM` in both width and height. The containers of CCM are all
  seen at most 1.0x as wide as tall, at most 3.6x as tall as wide, at least 69 mm. The paper's nearest-object
  assumption then chose something else; the flags say so instead of staying silent.

Without ground truth a patch is **flagged** when it is border-cut, implausibly sized or not container-like in
shape (whatever its track), or when
it is off the container's track *and* at least one other cue agrees; severity ``high`` with two or more cues besides
the track, ``medium`` with one; ``low`` (not flagged) off the track alone (a container track broken by an occlusion
must not be flagged for that only).

The flags never offer an estimate from patches they doubt themselves: ``estimate_without`` (the mean of the patches
not flagged) is -1 unless every one of those is undoubted (severity ``none``), and ``warning()`` then says so
instead of offering a number.

**Ground truth** (recordings whose ``meta.json`` has ``instance_masks`` and ``instances``, e.g. the samples): a patch
is flagged exactly when its mask overlaps the container's instance mask with IoU < :data:`GT_MIN_IOU` (severity
``high``), naming what it lies on (``pitcher``, ``hand``, ``container`` for only a part of it). The cues are still
computed and listed, so they can be checked against the ground truth. The masks are read by io
(``massviz.io.ground_truth.with_ground_truth``) into per-detection overlaps (``Detections.gt_iou``, ``gt_instance``,
``gt_fraction``; :func:`mask_overlap`): this module reads no file.

``Flags.estimate_without`` is the mean prediction of the chosen patches that are not flagged (-1: none left);
``Flags.warning()`` the one-line summary the commands print.
"""
from __future__ import annotations

import hashlib
import math
from collections import Counter
from dataclasses import dataclass

import numpy as np

from massviz.core.tracks import metric_size, track_members
from massviz.core.types import OBJECT_CLASS_ID, class_name

CUE_KINDS = ("track", "size", "depth_jump", "time", "class", "border", "implausible", "shape")
#: cues that doubt a patch on their own, whatever its track.
ABSOLUTE_CUES = ("border", "implausible", "shape")
#: no container CCM hands over is seen this much wider than tall (its widest, seen from the front: 1.0x; a box lying
#: on its side, a tray, a lid, a table edge are): the shape cue's bound on width / height
MAX_WIDTH_RATIO = 1.6
#: ... nor this much taller than wide (its slenderest, the wine glass: 3.6x; a bottle's neck, a spoon, a pen are)
MAX_HEIGHT_RATIO = 5.0
#: nor smaller than this in both width and height (mm; its smallest is 69 x 72 mm)
MIN_CONTAINER_MM = 40.0
#: a box within this many pixels of the image border is cut by it.
BORDER_PX = 1
#: no hand-held container is wider or taller than this (mm); CCM's largest are about 250 mm.
MAX_CONTAINER_MM = 450.0
SEVERITIES = ("none", "low", "medium", "high")
#: a chosen patch whose mask has IoU below this with the ground-truth container mask is not the container.
GT_MIN_IOU = 0.5
#: the container's track is the nearest one in the last END_FRACTION of the processed frames (at least END_MIN_FRAMES).
END_FRACTION, END_MIN_FRAMES = 0.1, 3
#: metric size ratio (either way, width or height) beyond which the size cue fires.
SIZE_RATIO = 1.5
#: depth speed (m/s) of a track into or out of a patch beyond which the depth-jump cue fires.
JUMP_M_S = 2.5
#: the track went back by more than max(RECEDE_MM, RECEDE_FRACTION x d) after the patch: time cue.
RECEDE_MM, RECEDE_FRACTION = 150.0, 0.2
#: a track standing still (centre within STATIC_PX px, d within STATIC_MM mm) in >= STATIC_FRACTION of the frames.
STATIC_PX, STATIC_MM, STATIC_FRACTION = 4.0, 30.0, 0.5


@dataclass(frozen=True)
class Cue:
    """One reason to doubt a patch: ``kind`` (one of ``CUE_KINDS``) and a readable ``message``."""

    kind: str
    message: str


@dataclass(frozen=True)
class PatchFlag:
    """The verdict on one chosen patch.

    ``detection`` (index into the trace's detections), ``rank`` (0 = nearest), ``frame``, ``track``; ``cues`` (no
    ground truth needed); ``ground_truth``: None without ground truth, else the instance its mask lies on most
    (``container`` when it is the container or a part of it) with ``gt_iou`` its IoU with the container's mask;
    ``flagged`` and ``severity`` (one of ``SEVERITIES``).
    """

    detection: int
    rank: int
    frame: int
    track: int
    flagged: bool
    severity: str
    cues: tuple = ()
    ground_truth: str | None = None
    gt_iou: float | None = None

    @property
    def cue_kinds(self) -> tuple[str, ...]:
        return tuple(c.kind for c in self.cues)

    @property
    def by_ground_truth(self) -> bool:
        return self.ground_truth is not None

    @property
    def reason(self) -> str:
        """Why it is (or is not) flagged, in one line."""
        cues = "; ".join(c.message for c in self.cues)
        if self.ground_truth is not None:
            if not self.flagged:
                return "ground truth: the container" + (f" (cues: {cues})" if cues else "")
            part = " (only a part of the container)" if self.ground_truth == "container" else ""
            gt = (f"ground truth: IoU {self.gt_iou:.2f} < {GT_MIN_IOU} with the container, mostly on the "
                  f"{self.ground_truth}{part}")
            return gt + (f"; cues: {cues}" if cues else "; no cue fired")
        return cues

    def to_dict(self) -> dict:
        return {"detection": self.detection, "rank": self.rank, "frame": self.frame, "track": self.track,
                "flagged": self.flagged, "severity": self.severity,
                "cues": [[c.kind, c.message] for c in self.cues], "ground_truth": self.ground_truth,
                "gt_iou": self.gt_iou}

    @classmethod
    def from_dict(cls, d: dict) -> "PatchFlag":
        return cls(detection=int(d["detection"]), rank=int(d["rank"]), frame=int(d["frame"]), track=int(d["track"]),
                   flagged=bool(d["flagged"]), severity=str(d["severity"]),
                   cues=tuple(Cue(str(k), str(m)) for k, m in d.get("cues", [])),
                   ground_truth=None if d.get("ground_truth") is None else str(d["ground_truth"]),
                   gt_iou=None if d.get("gt_iou") is None else float(d["gt_iou"]))


@dataclass(frozen=True)
class Flags:
    """The analysis of one selection: ``patches`` (one per chosen patch, nearest first), ``container_track`` (the
    track taken as the container's by the cues, -1 none), ``estimate_without`` (mean prediction of the patches not
    flagged, g; -1 none left) and ``estimate`` (of all chosen patches, for the summary line)."""

    patches: tuple = ()
    container_track: int = -1
    estimate_without: float = -1.0
    estimate: float = -1.0
    #: what the analysis was made of (``selection_key``): ``analyse_trace`` recomputes flags whose key is not the
    #: trace's own.
    key: str = ""

    @property
    def flagged(self) -> list[PatchFlag]:
        return [p for p in self.patches if p.flagged]

    @property
    def detections(self) -> np.ndarray:
        """Detection indices of the flagged patches."""
        return np.array([p.detection for p in self.flagged], dtype=np.int64)

    def of(self, detection: int) -> PatchFlag | None:
        """The verdict on chosen detection ``detection`` (None when it is not chosen)."""
        return next((p for p in self.patches if p.detection == int(detection)), None)

    def describes(self, trace) -> bool:
        """Whether these flags are of ``trace``'s selection: same key (``selection_key``) and one verdict per chosen
        patch, rank by rank, with its frame and track (flags read from an untrusted file are checked with it)."""
        dets, sel = trace.detections, [int(i) for i in np.asarray(trace.selection, dtype=np.int64)]
        if self.key != selection_key(trace) or [p.detection for p in self.patches] != sel:
            return False
        return all(p.rank == r and p.frame == int(dets.frame[p.detection]) and p.track == int(dets.track[p.detection])
                   and p.severity in SEVERITIES and all(c.kind in CUE_KINDS for c in p.cues)
                   for r, p in enumerate(self.patches))

    def warning(self) -> str | None:
        """One line, e.g. "3 of 5 chosen patches look like another object (frames 8–10, track 4): without them
        8.3 g", or None when nothing is flagged."""
        bad = self.flagged
        if not bad:
            return None
        n, k = len(bad), len(self.patches)
        by_track: dict[int, list[int]] = {}
        for p in sorted(bad, key=lambda p: p.frame):
            by_track.setdefault(p.track, []).append(p.frame)
        where = "; ".join(f"{_frames_text(fr)}, track {t}" for t, fr in by_track.items())
        verb = "looks" if n == 1 else "look"
        noun = "patch" if k == 1 else "patches"
        rest = [p for p in self.patches if not p.flagged]
        if self.estimate_without >= 0:
            without = f"without {'it' if n == 1 else 'them'} {self.estimate_without:.1f} g"
        elif not rest:
            absolute = sorted({c.kind for p in bad for c in p.cues if c.kind in ABSOLUTE_CUES})
            without = ("no plausible container: only " + " / ".join(
                {"border": "border-cut", "implausible": "implausibly sized", "shape": "not container-like"}[k]
                for k in absolute) + " objects"
                       if absolute and all(set(p.cue_kinds) & set(ABSOLUTE_CUES) for p in bad)
                       else "no patch left without them")
        else:
            without = (f"the other {len(rest)} {'is' if len(rest) == 1 else 'are'} doubted too (off the container's "
                       "track): no estimate without them")
        gt = sorted({p.ground_truth for p in bad if p.ground_truth is not None})
        basis = ("ground truth: " + " and ".join(f"the {g}" for g in gt) if gt else
                 "cues: " + ", ".join(sorted({c.kind.replace('_', ' ') for p in bad for c in p.cues})))
        return f"{n} of {k} chosen {noun} {verb} like another object ({where}): {without} [{basis}]"

    def to_dict(self) -> dict:
        return {"patches": [p.to_dict() for p in self.patches], "container_track": self.container_track,
                "estimate_without": self.estimate_without, "estimate": self.estimate, "key": self.key}

    @classmethod
    def from_dict(cls, d: dict) -> "Flags":
        return cls(patches=tuple(PatchFlag.from_dict(p) for p in d.get("patches", [])),
                   container_track=int(d.get("container_track", -1)),
                   estimate_without=float(d.get("estimate_without", -1.0)), estimate=float(d.get("estimate", -1.0)),
                   key=str(d.get("key", "")))

    def table(self):
        """One row per chosen patch (pandas DataFrame): rank, detection, frame, track, flagged, severity, cues
        (kinds), ground_truth and reason."""
        import pandas as pd

        return pd.DataFrame([{"rank": p.rank, "detection": p.detection, "frame": p.frame, "track": p.track,
                              "flagged": p.flagged, "severity": p.severity, "cues": ", ".join(p.cue_kinds),
                              "ground_truth": p.ground_truth or "", "reason": p.reason} for p in self.patches],
                            columns=["rank", "detection", "frame", "track", "flagged", "severity", "cues",
                                     "ground_truth", "reason"])


def _frames_text(frames) -> str:
    """"frame 9", "frames 8–10", "frames 0, 6, 12"."""
    frames = sorted(set(int(f) for f in frames))
    if len(frames) == 1:
        return f"frame {frames[0]}"
    if frames == list(range(frames[0], frames[-1] + 1)):
        return f"frames {frames[0]}–{frames[-1]}"
    return "frames " + ", ".join(str(f) for f in frames)


# ------------------------------------------------------------------------------------------------- ground truth
def ground_truth_source(recording) -> str:
    """What the ground-truth overlaps of a recording's detections are computed from (its folder, the mask pattern
    and the instance names of its ``meta.json``); "" when it has no instance masks. A trace's overlaps
    (``Detections.gt_iou`` ...) count only while its ``ground_truth_source`` equals this."""
    gt = recording.ground_truth
    if gt is None or not gt.instance_masks or not gt.instances or not recording.path:
        return ""
    return f"{recording.path}|{gt.instance_masks}|{sorted(gt.instances.items())}"


def has_ground_truth(trace) -> bool:
    """Whether ``trace``'s detections carry ground-truth overlaps of its recording's current ground truth."""
    source = ground_truth_source(trace.recording)
    return bool(source) and trace.ground_truth_source == source


def mask_overlap(mask: np.ndarray, instances: np.ndarray, names: dict[int, str]) -> tuple[float, int, float]:
    """How the full-image boolean ``mask`` lies on the instance-id image ``instances`` ({id: name}; the container is
    named "container"): (IoU with the container's mask, the instance id covering most of the mask (0: background or
    an empty mask), the fraction of the mask it covers)."""
    cmask = np.isin(instances, [i for i, n in names.items() if n == "container"])
    union = int((mask | cmask).sum())
    iou = float((mask & cmask).sum() / union) if union else 0.0
    ids, counts = np.unique(instances[mask], return_counts=True)
    if len(ids) == 0:
        return iou, 0, 0.0
    best = int(np.argmax(counts))
    return iou, int(ids[best]), float(counts[best] / counts.sum())


def ground_truth_overlap(trace, index: int) -> dict | None:
    """For detection ``index``: ``iou_container`` (IoU of its mask with the container's), ``overlaps`` (name of the
    instance covering most of its mask, "background" for none) and ``fraction`` (of the mask it covers); None
    without ground truth for its frame (or overlaps not read: ``massviz.io.ground_truth.with_ground_truth``)."""
    dets = trace.detections
    if not has_ground_truth(trace) or not np.isfinite(dets.gt_iou[index]):
        return None
    instance, fraction = int(dets.gt_instance[index]), float(dets.gt_fraction[index])
    names = trace.ground_truth.instances
    name = "background" if fraction == 0 else names.get(instance, "background" if instance == 0 else
                                                        f"instance {instance}")
    return {"iou_container": float(dets.gt_iou[index]), "overlaps": name, "fraction": fraction}


# ------------------------------------------------------------------------------------------------------- cues
def _usable(trace) -> np.ndarray:
    dets = trace.detections
    ok = (dets.score > trace.threshold) & np.isfinite(dets.d)
    ok[np.asarray(trace.excluded, dtype=np.int64)] = False
    return ok


def container_track(trace) -> int:
    """The track taken as the container's: the nearest usable detection's in the last frames (module docstring)."""
    dets = trace.detections
    ok = _usable(trace)
    frames = np.unique(dets.frame[ok])
    if len(frames) == 0:
        return -1
    n_end = max(END_MIN_FRAMES, int(math.ceil(END_FRACTION * len(frames))))
    end = ok & np.isin(dets.frame, frames[-n_end:])
    idx = np.flatnonzero(end)
    return int(dets.track[idx[np.argmin(dets.d[idx])]])


def _mm(trace, i: int) -> tuple[float, float]:
    intr = trace.recording.intrinsics
    w, h = metric_size(trace.detections.xyxy[i], float(trace.detections.d[i]))
    return (w / intr.fx, h / intr.fy) if intr is not None else (w, h)


def _cues(trace, i: int, ref: int, ref_size, ref_class, n_frames: int) -> list[Cue]:
    dets = trace.detections
    t = int(dets.track[i])
    cues = []
    if ref >= 0 and t != ref:
        cues.append(Cue("track", f"on track {t}, not the container's track {ref} (nearest at the end)"))
    if ref_size is not None and t != ref:
        w, h = _mm(trace, i)
        rw, rh = ref_size
        ratio = max(w / rw, rw / w, h / rh, rh / h) if min(w, h, rw, rh) > 0 else np.inf
        if ratio > SIZE_RATIO:
            unit = " mm" if trace.recording.intrinsics is not None else ""
            cues.append(Cue("size", f"{w:.0f}×{h:.0f}{unit} against the container track's {rw:.0f}×{rh:.0f}{unit} "
                                    f"({ratio:.1f}×)"))
    members = track_members(dets, t)
    members = members[np.isfinite(dets.d[members])]
    pos = np.flatnonzero(members == i)
    fps = trace.recording.fps if trace.recording.fps and trace.recording.fps > 0 else 30.0
    if len(pos):
        k = int(pos[0])
        speeds = []
        for a, b in ((k - 1, k), (k, k + 1)):
            if a >= 0 and b < len(members):
                dt = (int(dets.frame[members[b]]) - int(dets.frame[members[a]])) / fps
                if dt > 0:
                    speeds.append((abs(dets.d[members[b]] - dets.d[members[a]]) / 1000.0 / dt,
                                   int(dets.frame[members[a]]), int(dets.frame[members[b]]),
                                   dets.d[members[a]], dets.d[members[b]]))
        if speeds:
            v, fa, fb, da, db = max(speeds)
            if v > JUMP_M_S:
                cues.append(Cue("depth_jump", f"its track's depth jumps {da:.0f} → {db:.0f} mm from frame {fa} to "
                                              f"{fb} ({v:.1f} m/s)"))
    later = members[dets.frame[members] > dets.frame[i]]
    back = float(dets.d[later].max() - dets.d[i]) if len(later) else 0.0
    if back > max(RECEDE_MM, RECEDE_FRACTION * dets.d[i]):
        cues.append(Cue("time", f"its track came near and went away again ({dets.d[i]:.0f} → "
                                f"{dets.d[i] + back:.0f} mm after frame {int(dets.frame[i])})"))
    elif t != ref and len(members) and n_frames:
        span = len(np.unique(dets.frame[members])) / n_frames
        cx = (dets.xyxy[members, 0] + dets.xyxy[members, 2]) / 2.0
        cy = (dets.xyxy[members, 1] + dets.xyxy[members, 3]) / 2.0
        move, dd = max(np.ptp(cx), np.ptp(cy)), float(np.ptp(dets.d[members]))
        if span >= STATIC_FRACTION and move <= STATIC_PX and dd <= STATIC_MM:
            cues.append(Cue("time", f"its track stood still in {span:.0%} of the frames (moved {move:.0f} px, "
                                    f"{dd:.0f} mm): nothing standing still is handed over"))
    width, height = int(trace.recording.width or 0), int(trace.recording.height or 0)
    x1, y1, x2, y2 = (int(v) for v in dets.xyxy[i])
    if width > 0 and height > 0 and (x1 <= BORDER_PX or y1 <= BORDER_PX or x2 >= width - BORDER_PX
                                     or y2 >= height - BORDER_PX):
        sides = [name for name, cut in (("left", x1 <= BORDER_PX), ("top", y1 <= BORDER_PX),
                                        ("right", x2 >= width - BORDER_PX), ("bottom", y2 >= height - BORDER_PX)) if cut]
        cues.append(Cue("border", f"cut by the image's {' and '.join(sides)} border (box {[x1, y1, x2, y2]})"))
    if trace.recording.intrinsics is not None and np.isfinite(dets.d[i]):
        w, h = _mm(trace, i)
        if max(w, h) > MAX_CONTAINER_MM:
            cues.append(Cue("implausible", f"{w:.0f}×{h:.0f} mm: larger than any hand-held container "
                                           f"({MAX_CONTAINER_MM:.0f} mm)"))
    if np.isfinite(dets.d[i]):
        metric = trace.recording.intrinsics is not None
        w, h = _mm(trace, i) if metric else (float(x2 - x1), float(y2 - y1))
        unit = " mm" if metric else " px"
        if w > MAX_WIDTH_RATIO * h or h > MAX_HEIGHT_RATIO * w:
            cues.append(Cue("shape", f"{w:.0f}×{h:.0f}{unit}: {w / h:.1f}× as wide as tall, not container-like (no "
                                     f"container is seen more than {MAX_WIDTH_RATIO:g}× as wide or "
                                     f"{MAX_HEIGHT_RATIO:g}× as tall)"))
        elif metric and max(w, h) < MIN_CONTAINER_MM:
            cues.append(Cue("shape", f"{w:.0f}×{h:.0f} mm: smaller than any container ({MIN_CONTAINER_MM:.0f} mm)"))
    if ref_class is not None and t != ref and int(dets.class_id[i]) != ref_class:
        cues.append(Cue("class", f"a {class_name(dets.class_id[i])}; the container's track is mostly a "
                                 f"{class_name(ref_class)}"))
    return cues


def selection_key(trace, ground_truth: bool = True) -> str:
    """A short digest of what the flags of ``trace`` depend on: detections (frames, tracks), threshold, selection,
    exclusions, the estimate and the ground truth's masks (when used) with the recording's folder."""
    dets = trace.detections
    h = hashlib.sha1()
    for part in (np.asarray(trace.selection, np.int64), np.asarray(trace.excluded, np.int64),
                 np.asarray(dets.track, np.int64), np.asarray(dets.frame, np.int64)):
        h.update(part.tobytes())
        h.update(b"|")
    gt = trace.ground_truth
    masks = (gt.instance_masks, sorted(gt.instances.items())) if ground_truth and has_ground_truth(trace) else None
    h.update(f"{float(trace.threshold):.6f}|{float(trace.estimate):.6f}|{masks}|{trace.recording.path}".encode())
    return h.hexdigest()[:16]


def analyse(trace, *, ground_truth: bool = True) -> Flags:
    """The flags of ``trace``'s selection (module docstring). ``ground_truth=False`` ignores ground-truth masks
    (cues only, as on a recording without them). Needs ``trace.detections.track`` (``massviz.core.tracks``)."""
    dets = trace.detections
    sel = [int(i) for i in np.asarray(trace.selection, dtype=np.int64)]
    key = selection_key(trace, ground_truth)
    if not sel:
        return Flags(estimate=float(trace.estimate), key=key)
    ref = container_track(trace)
    ok = _usable(trace)
    ref_idx = np.flatnonzero(ok & (dets.track == ref)) if ref >= 0 else np.zeros(0, np.int64)
    ref_size = tuple(np.median(np.array([_mm(trace, int(j)) for j in ref_idx]), axis=0)) if len(ref_idx) else None
    classes = Counter(int(c) for c in dets.class_id[ref_idx] if int(c) != OBJECT_CLASS_ID)
    ref_class = classes.most_common(1)[0][0] if classes else None
    n_frames = len(np.unique(trace.frames)) if len(trace.frames) else len(np.unique(dets.frame))
    patches = []
    for rank, i in enumerate(sel):
        cues = _cues(trace, i, ref, ref_size, ref_class, n_frames)
        gt = ground_truth_overlap(trace, i) if ground_truth else None
        if gt is not None:
            flagged = gt["iou_container"] < GT_MIN_IOU
            severity = "high" if flagged else "none"
        else:
            support = [c for c in cues if c.kind != "track"]
            off = any(c.kind == "track" for c in cues)
            flagged = (off and bool(support)) or any(c.kind in ABSOLUTE_CUES for c in cues)
            severity = ("high" if len(support) >= 2 else "medium") if flagged else ("low" if off else "none")
        patches.append(PatchFlag(detection=i, rank=rank, frame=int(dets.frame[i]), track=int(dets.track[i]),
                                 flagged=flagged, severity=severity, cues=tuple(cues),
                                 ground_truth=None if gt is None else gt["overlaps"],
                                 gt_iou=None if gt is None else round(gt["iou_container"], 4)))
    rest = [p for p in patches if not p.flagged]
    keep = [p.detection for p in rest if np.isfinite(dets.pred[p.detection])]
    # never offer an estimate from patches the flags doubt themselves (severity "low": off the container's track)
    without = float(np.mean(dets.pred[keep])) if keep and all(p.severity == "none" for p in rest) else -1.0
    return Flags(patches=tuple(patches), container_track=ref, estimate_without=without,
                 estimate=float(trace.estimate), key=key)


__all__ = ["Cue", "PatchFlag", "Flags", "analyse", "selection_key", "container_track", "ground_truth_source",
           "has_ground_truth", "mask_overlap", "ground_truth_overlap", "CUE_KINDS", "SEVERITIES", "GT_MIN_IOU",
           "ABSOLUTE_CUES", "BORDER_PX", "MAX_CONTAINER_MM", "MAX_WIDTH_RATIO", "MAX_HEIGHT_RATIO", "MIN_CONTAINER_MM"]
