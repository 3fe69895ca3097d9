"""Failure analysis of the K-nearest selection: why each patch was chosen, which chosen patches are probably not the
manipulated container, and user exclusions that survive a re-run.

**Why chosen.** A patch is chosen because it is among the K detections with the smallest d (mean depth over its
mask) among those with score > threshold; ``chosen_table`` lists rank, d, score and frame of each.

**Flagging**: the trace's own flags (``trace.flags``, ``massviz.core.flags``: the analysis stage every trace runs
after selection, with the object tracks of ``massviz.core.tracks``); ``chosen_table`` shows them per patch
(columns ``track``, ``flagged``, ``severity``, ``cues``, ``flag_gt``, ``flag_reason``): ground-truth instance masks
where the recording has them (flagged exactly when the patch is not the container), else cues that need no ground
truth (track, size, depth jump, time, class). Both are listed whenever possible so the cues can be checked against the
ground truth.

**Tracks**: ``track_of`` (every detection of a detection's track) is what "exclude track" excludes.

**Exclusions** (``Exclusion``, ``save_exclusions``, ``load_exclusions``, ``match_exclusions``): detections the user
rules out, identified by recording id, frame and box, never by position in a trace, so the file stays valid when the
trace is recomputed (another stride, threshold or cache). JSON format (``massviz.exclusions/1``)::

    {
      "format": "massviz.exclusions/1",
      "exclusions": [
        {"recording": "cup_handover", "frame": 12, "box": [101, 80, 160, 171], "note": "pitcher"}
      ]
    }

``recording`` is the recording's id (``meta.json`` "id", else the folder name; CCM: the video's number, e.g.
``"000123"``); ``frame`` the frame index in the recording; ``box`` the detection's integer box ``x1, y1, x2, y2``
(x2/y2 exclusive) in pixels; ``note`` free text (optional). An entry matches the detection of that recording and
frame with exactly that box or, failing that, the one whose box overlaps it most with IoU >= 0.9 (a re-run of a
detector with slightly different settings); entries that match nothing are reported, never silently dropped.
``massviz estimate --exclude FILE`` honours the file.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np
import pandas as pd

from massviz.core.flags import GT_MIN_IOU, ground_truth_overlap
from massviz.core.trace import Trace
from massviz.core.tracks import box_iou
from massviz.core.types import class_name
from massviz.errors import DataError
from massviz.io.atomic import atomic_path
from massviz.io.ground_truth import ground_truth_masks
from massviz.io.untrusted import MAX_INDEX, text_id
from massviz.io.untrusted.text import _CONTROL

EXCLUSIONS_FORMAT = "massviz.exclusions/1"
#: IoU a box must reach to match an exclusion entry whose exact box is not found.
MATCH_MIN_IOU = 0.9


# ------------------------------------------------------------------------------------------------------ exclusions
@dataclass(frozen=True)
class Exclusion:
    """One excluded detection: recording id, frame index, integer box (x1, y1, x2, y2) and an optional note."""

    recording: str
    frame: int
    box: tuple[int, int, int, int]
    note: str = ""

    def to_dict(self) -> dict:
        out = {"recording": self.recording, "frame": self.frame, "box": list(self.box)}
        if self.note:
            out["note"] = self.note
        return out


def recording_id(trace: Trace) -> str:
    return trace.recording.id


def exclusion_of(trace: Trace, index: int, note: str = "") -> Exclusion:
    """The ``Exclusion`` entry naming detection ``index`` of ``trace``."""
    dets = trace.detections
    return Exclusion(recording_id(trace), int(dets.frame[index]), tuple(int(v) for v in dets.xyxy[index]), note)


def save_exclusions(path: str | Path, exclusions: Iterable[Exclusion]) -> Path:
    """Write the exclusions JSON (format in the module docstring) atomically; entries sorted, duplicates dropped."""
    path = Path(path)
    unique = sorted({(e.recording, e.frame, e.box): e for e in exclusions}.values(),
                    key=lambda e: (e.recording, e.frame, e.box))
    entries = ",\n".join("  " + json.dumps(e.to_dict()) for e in unique)
    text = f'{{\n "format": "{EXCLUSIONS_FORMAT}",\n "exclusions": [\n{entries}\n ]\n}}\n' if unique else \
        json.dumps({"format": EXCLUSIONS_FORMAT, "exclusions": []}) + "\n"
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return path


def load_exclusions(path: str | Path) -> list[Exclusion]:
    """Read an exclusions JSON file; ``DataError`` naming the file and entry when it is malformed."""
    path = Path(path)
    from massviz.io.untrusted import load_json

    doc = load_json(path, "exclusions file", DataError)
    if not isinstance(doc, dict) or doc.get("format") != EXCLUSIONS_FORMAT:
        raise DataError(f'not a massviz exclusions file (expected an object with "format": "{EXCLUSIONS_FORMAT}")',
                        path)
    entries = doc.get("exclusions")
    if not isinstance(entries, list):
        raise DataError('"exclusions" must be a list of {"recording", "frame", "box"} objects', path)
    out = []
    for n, e in enumerate(entries, 1):
        where = f"exclusion {n}"
        if not isinstance(e, dict):
            raise DataError(f"{where}: expected an object with recording, frame and box", path)
        recording_id, frame, box = e.get("recording"), e.get("frame"), e.get("box")
        if not isinstance(recording_id, str) or not recording_id:
            raise DataError(f'{where}: "recording" must be a non-empty string (the recording id)', path)
        text_id(recording_id, f'{where}: "recording"', path)
        if not isinstance(frame, int) or isinstance(frame, bool) or not 0 <= frame <= MAX_INDEX:
            raise DataError(f'{where}: "frame" must be an integer >= 0 and <= {MAX_INDEX}, got {frame!r}'[:300], path)
        if (not isinstance(box, list) or len(box) != 4
                or not all(isinstance(v, int) and not isinstance(v, bool) and 0 <= v <= MAX_INDEX for v in box)
                or not (box[2] > box[0] and box[3] > box[1])):
            raise DataError(f'{where}: "box" must be 4 integers [x1, y1, x2, y2] in [0, {MAX_INDEX}] with x2 > x1 '
                            f"and y2 > y1, got {box!r}"[:300], path)
        note = e.get("note", "")
        if not isinstance(note, str) or len(note) > 2000:
            raise DataError(f'{where}: "note" must be a string of at most 2000 characters', path)
        if _CONTROL.search(note.replace("\n", "").replace("\t", "")):
            raise DataError(f'{where}: "note" contains control characters', path)
        out.append(Exclusion(recording_id, frame, tuple(box), note))
    return out


def match_exclusions(trace: Trace, exclusions: Iterable[Exclusion],
                     min_iou: float = MATCH_MIN_IOU) -> tuple[np.ndarray, list[Exclusion]]:
    """(indices into ``trace.detections`` of the entries for this trace's recording, entries for this recording that
    match no detection). Entries for other recordings are ignored."""
    dets = trace.detections
    rid = recording_id(trace)
    found, unmatched = set(), []
    for e in exclusions:
        if e.recording != rid:
            continue
        same_frame = np.flatnonzero(dets.frame == e.frame)
        if len(same_frame) == 0:
            unmatched.append(e)
            continue
        exact = same_frame[(dets.xyxy[same_frame] == np.asarray(e.box)).all(axis=1)]
        if len(exact):
            found.add(int(exact[0]))
            continue
        iou = box_iou(e.box, dets.xyxy[same_frame])[0]
        best = int(np.argmax(iou))
        if iou[best] >= min_iou:
            found.add(int(same_frame[best]))
        else:
            unmatched.append(e)
    return np.array(sorted(found), dtype=np.int64), unmatched


def exclude_detections(trace: Trace, exclusions: Iterable[Exclusion]) -> tuple[Trace, list[Exclusion]]:
    """(``trace`` re-selected without the detections the entries name — ``trace`` itself when none matches —, the
    entries of this recording that match no detection). What ``estimate --exclude`` and ``extract --exclude`` do."""
    indices, unmatched = match_exclusions(trace, exclusions)
    return (trace if len(indices) == 0 else trace.reselect(exclude=indices)), unmatched


def track_of(trace: Trace, index: int) -> np.ndarray:
    """Every detection of ``trace`` on the same object track as detection ``index`` (``detections.track``; the
    lifted pitcher of ``cup_handover`` in frames 0-23 is one track), ascending. Includes ``index``."""
    tracks = np.asarray(trace.detections.track)
    return np.union1d(np.flatnonzero(tracks == tracks[int(index)]), [int(index)]).astype(np.int64)


def chosen_table(trace: Trace, extra: Sequence[int] = ()) -> pd.DataFrame:
    """One row per chosen patch (nearest first), then one per ``extra`` detection (e.g. excluded ones, rank -1):
    ``detection`` (index), ``rank`` (0 = nearest, as ★0 in every view), ``frame``, ``track``, ``class``, ``score``,
    ``d_mm``, ``a``, ``b``, ``pred_g``, ``why`` (why it was chosen), ``gt_iou`` / ``gt_overlaps`` (NaN / "" without
    ground truth), ``flag_gt`` (None without), ``cues`` (no ground truth needed), ``flagged``, ``severity`` and
    ``flag_reason``, from ``trace.flags``. Extra rows are not flagged (they are not chosen)."""
    dets = trace.detections
    sel = np.asarray(trace.selection, dtype=np.int64)
    rows_idx = list(sel) + [int(i) for i in extra if int(i) not in set(sel.tolist())]
    n_active = int((trace.active() & np.isfinite(dets.d)).sum())
    rows = []
    for r, i in enumerate(rows_idx):
        rank = r if r < len(sel) else -1
        why = (f"★{rank}: rank {rank} (0 = nearest) of the K={trace.k} chosen, d={dets.d[i]:.0f} mm, among the "
               f"{trace.k} smallest of {n_active} detections with score > {trace.threshold:.2f} (score "
               f"{dets.score[i]:.2f}, frame {int(dets.frame[i])})") if rank >= 0 else "not chosen (excluded)"
        flag = trace.flags.of(i) if rank >= 0 else None
        gt = ground_truth_overlap(trace, i) if flag is None else None
        gt_name = flag.ground_truth if flag is not None else (None if gt is None else gt["overlaps"])
        gt_iou = flag.gt_iou if flag is not None else (None if gt is None else gt["iou_container"])
        rows.append({
            "detection": int(i), "rank": rank, "frame": int(dets.frame[i]), "track": int(dets.track[i]),
            "class": class_name(dets.class_id[i]), "score": float(dets.score[i]), "d_mm": float(dets.d[i]),
            "a": float(dets.a[i]), "b": float(dets.b[i]), "pred_g": float(dets.pred[i]), "why": why,
            "gt_iou": np.nan if gt_iou is None else gt_iou, "gt_overlaps": gt_name or "",
            "flag_gt": None if gt_iou is None else bool(gt_iou < GT_MIN_IOU),
            "cues": "" if flag is None else "; ".join(c.message for c in flag.cues),
            "flagged": bool(flag is not None and flag.flagged), "severity": "none" if flag is None else flag.severity,
            "flag_reason": "" if flag is None or not flag.flagged else flag.reason,
        })
    return pd.DataFrame(rows)


def rank_by_error(traces: Sequence[Trace], estimates: Sequence[float] | None = None,
                  chosen: Sequence[int] | None = None) -> pd.DataFrame:
    """Recordings with known ground truth ranked by relative error ε = |estimate − true| / true, worst first (not
    estimated first of all): ``position`` (in ``traces``), ``recording``, ``class``, ``true_g``, ``estimate_g``,
    ``eps``, ``k``. ``estimates``/``chosen`` (the estimate and the number of chosen patches per trace) replace the
    traces' own; with both given, ``traces`` may be selection indexes (only their recording and ground truth are
    read)."""
    rows = []
    for pos, t in enumerate(traces):
        gt = t.ground_truth
        true = None if gt is None else gt.mass_g
        if true is None or true <= 0:
            continue
        est = float(t.estimate if estimates is None else estimates[pos])
        eps = abs(est - true) / true if est >= 0 else np.inf
        cls = (gt.cls if gt is not None else None) or ""
        rows.append({"position": pos, "recording": recording_id(t), "class": cls, "true_g": true,
                     "estimate_g": est if est >= 0 else np.nan, "eps": eps,
                     "k": len(t.selection) if chosen is None else int(chosen[pos])})
    table = pd.DataFrame(rows, columns=["position", "recording", "class", "true_g", "estimate_g", "eps", "k"])
    return table.sort_values("eps", ascending=False, kind="stable").reset_index(drop=True)


__all__ = ["EXCLUSIONS_FORMAT", "GT_MIN_IOU", "Exclusion", "exclusion_of", "save_exclusions",
           "load_exclusions", "match_exclusions", "exclude_detections", "box_iou", "track_of", "ground_truth_masks",
           "ground_truth_overlap", "chosen_table", "rank_by_error", "recording_id"]
