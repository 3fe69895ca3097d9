"""What changes between two traces: another precision, detector, threshold or weights on one recording, or two
recordings. ``compare_traces(a, b)`` matches the detections frame by frame (IoU, one to one) and reports:

* the settings that differ (detector and its settings, threshold, K, stride, model weights);
* frames processed by only one side;
* matched detections with their IoU and B − A differences of score, d and prediction; class changes;
* unmatched detections of each side (a box the other side has no box for at ``iou``);
* the chosen patches rank by rank (same detection, or which one each side chose) and the estimate difference.

Matching is greedy on IoU (highest first, each detection used once, IoU >= ``iou``, default 0.5), deterministic, in
each frame both traces processed. Boxes are the traces' integer boxes (x2/y2 exclusive).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from massviz.core.trace import Trace
from massviz.core.tracks import box_iou
from massviz.core.types import class_name

#: IoU at or above which two boxes of one frame are the same detection.
DEFAULT_IOU = 0.5


def match_boxes(a: np.ndarray, b: np.ndarray, iou: float = DEFAULT_IOU) -> list[tuple[int, int, float]]:
    """Greedy one-to-one matching: repeatedly the pair with the highest IoU (ties: lowest indices) >= ``iou``."""
    m = box_iou(a, b)
    pairs = []
    if m.size == 0:
        return pairs
    order = np.lexsort((np.tile(np.arange(m.shape[1]), m.shape[0]), np.repeat(np.arange(m.shape[0]), m.shape[1]),
                        -m.reshape(-1)))
    used_a, used_b = set(), set()
    for flat in order:
        i, j = divmod(int(flat), m.shape[1])
        if m[i, j] < iou or m[i, j] <= 0:
            break
        if i in used_a or j in used_b:
            continue
        used_a.add(i)
        used_b.add(j)
        pairs.append((i, j, float(m[i, j])))
    return pairs


@dataclass
class ChosenRank:
    """Rank ``rank`` of the selection: A's detection ``a`` and B's ``b`` (-1: that side chose fewer)."""

    rank: int
    a: int
    b: int
    same: bool  # B's choice is the detection matched to A's


@dataclass
class Comparison:
    """The differences between trace ``a`` and trace ``b`` (all deltas are B − A). See the module docstring."""

    a: Trace
    b: Trace
    labels: tuple[str, str]
    iou: float
    settings: list[tuple[str, object, object]]
    frames_only_a: list[int]
    frames_only_b: list[int]
    match_a: np.ndarray
    match_b: np.ndarray
    match_iou: np.ndarray
    unmatched_a: np.ndarray
    unmatched_b: np.ndarray
    chosen: list[ChosenRank] = field(default_factory=list)

    # -- per matched pair ------------------------------------------------------------------------------------------
    @property
    def d_score(self) -> np.ndarray:
        return self.b.detections.score[self.match_b].astype(np.float64) - self.a.detections.score[self.match_a]

    @property
    def d_d(self) -> np.ndarray:
        return self.b.detections.d[self.match_b] - self.a.detections.d[self.match_a]

    @property
    def d_pred(self) -> np.ndarray:
        return self.b.detections.pred[self.match_b].astype(np.float64) - self.a.detections.pred[self.match_a]

    @property
    def class_changes(self) -> np.ndarray:
        """Indices into the matches whose class differs."""
        return np.flatnonzero(self.a.detections.class_id[self.match_a] != self.b.detections.class_id[self.match_b])

    @property
    def estimate_delta(self) -> float | None:
        """B − A in grams; None when either side is not estimated (-1)."""
        if self.a.estimate < 0 or self.b.estimate < 0:
            return None
        return float(self.b.estimate - self.a.estimate)

    @property
    def chosen_changes(self) -> list[ChosenRank]:
        return [c for c in self.chosen if not c.same]

    def matched_of_a(self, i: int) -> int:
        """B's detection matched to A's detection ``i`` (-1: unmatched)."""
        hit = np.flatnonzero(self.match_a == i)
        return int(self.match_b[hit[0]]) if len(hit) else -1

    # -- summaries -------------------------------------------------------------------------------------------------
    def summary(self) -> dict:
        """The figures as a JSON-able dict."""
        def max_abs(x):
            x = np.asarray(x, dtype=np.float64)
            x = x[np.isfinite(x)]
            return float(np.abs(x).max()) if len(x) else 0.0

        def mean_abs(x):
            x = np.asarray(x, dtype=np.float64)
            x = x[np.isfinite(x)]
            return float(np.abs(x).mean()) if len(x) else 0.0

        return {
            "labels": list(self.labels), "iou": self.iou,
            "settings": [[n, _jsonable(va), _jsonable(vb)] for n, va, vb in self.settings],
            "detections": [len(self.a.detections), len(self.b.detections)],
            "frames_only_a": self.frames_only_a, "frames_only_b": self.frames_only_b,
            "matched": int(len(self.match_a)),
            "unmatched_a": int(len(self.unmatched_a)), "unmatched_b": int(len(self.unmatched_b)),
            "mean_iou": float(self.match_iou.mean()) if len(self.match_iou) else None,
            "min_iou": float(self.match_iou.min()) if len(self.match_iou) else None,
            "class_changes": int(len(self.class_changes)),
            "max_abs_d_score": max_abs(self.d_score), "mean_abs_d_score": mean_abs(self.d_score),
            "max_abs_d_d_mm": max_abs(self.d_d), "mean_abs_d_d_mm": mean_abs(self.d_d),
            "max_abs_d_pred_g": max_abs(self.d_pred), "mean_abs_d_pred_g": mean_abs(self.d_pred),
            "chosen_changed": [c.rank for c in self.chosen_changes],
            "estimate": [self.a.estimate, self.b.estimate], "estimate_delta_g": self.estimate_delta,
        }

    def table(self, max_rows: int = 10) -> str:
        """A plain-text report (what ``massviz compare`` prints)."""
        s = self.summary()
        la, lb = self.labels
        lines = [f"A: {la}: {_describe(self.a)}", f"B: {lb}: {_describe(self.b)}"]
        if self.settings:
            lines.append("settings that differ: " + "; ".join(f"{n} {_short(va)} -> {_short(vb)}"
                                                              for n, va, vb in self.settings))
        else:
            lines.append("settings that differ: none")
        if self.frames_only_a or self.frames_only_b:
            lines.append(f"frames processed only in A: {_frames(self.frames_only_a)}; only in B: "
                         f"{_frames(self.frames_only_b)} (not compared)")
        iou_txt = "" if s["mean_iou"] is None else f", IoU mean {s['mean_iou']:.3f} min {s['min_iou']:.3f}"
        lines.append(f"detections: {s['matched']} matched (IoU >= {self.iou:g}{iou_txt}), {s['unmatched_a']} only in "
                     f"A, {s['unmatched_b']} only in B, {s['class_changes']} class changes")
        lines += ["", f"{'matched, B - A':<16}{'max |delta|':>12}{'mean |delta|':>14}",
                  f"{'score':<16}{s['max_abs_d_score']:>12.4f}{s['mean_abs_d_score']:>14.4f}",
                  f"{'d (mm)':<16}{s['max_abs_d_d_mm']:>12.2f}{s['mean_abs_d_d_mm']:>14.2f}",
                  f"{'prediction (g)':<16}{s['max_abs_d_pred_g']:>12.2f}{s['mean_abs_d_pred_g']:>14.2f}", ""]
        lines.append("chosen patches (rank: A | B):")
        for c in self.chosen:
            mark = "same" if c.same else "CHANGED"
            lines.append(f"  {c.rank}: {_det(self.a, c.a)} | {_det(self.b, c.b)}  {mark}")
        if not self.chosen:
            lines.append("  none on either side")
        ea, eb = self.a.estimate, self.b.estimate
        delta = "" if self.estimate_delta is None else f", delta {self.estimate_delta:+.2f} g"
        lines.append(f"estimate: A {_grams(ea)}, B {_grams(eb)}{delta}")
        for side, trace, idx in (("A", self.a, self.unmatched_a), ("B", self.b, self.unmatched_b)):
            if len(idx):
                lines.append(f"only in {side} ({len(idx)}" + (f", first {max_rows}" if len(idx) > max_rows else "")
                             + "):")
                lines += [f"  {_det(trace, int(i))}" for i in idx[:max_rows]]
        return "\n".join(lines) + "\n"

    def markdown(self) -> str:
        """The report as a markdown document (logged as ``/compare`` in both Rerun recordings)."""
        return "# massviz compare\n\n```\n" + self.table() + "```\n"


def compare_traces(a: Trace, b: Trace, *, iou: float = DEFAULT_IOU, labels: tuple[str, str] = ("A", "B")) -> Comparison:
    """Compare trace ``a`` with trace ``b`` (module docstring)."""
    if not 0.0 < iou <= 1.0:
        raise ValueError("iou must be in (0, 1]")
    fa, fb = set(int(f) for f in a.frames), set(int(f) for f in b.frames)
    da, db = a.detections, b.detections
    match_a, match_b, match_iou = [], [], []
    for frame in sorted(fa & fb):
        ia, ib = np.flatnonzero(da.frame == frame), np.flatnonzero(db.frame == frame)
        for i, j, v in match_boxes(da.xyxy[ia], db.xyxy[ib], iou):
            match_a.append(int(ia[i]))
            match_b.append(int(ib[j]))
            match_iou.append(v)
    match_a = np.asarray(match_a, dtype=np.int64)
    match_b = np.asarray(match_b, dtype=np.int64)
    both = np.isin(da.frame, sorted(fa & fb)), np.isin(db.frame, sorted(fa & fb))
    unmatched_a = np.setdiff1d(np.flatnonzero(both[0]), match_a)
    unmatched_b = np.setdiff1d(np.flatnonzero(both[1]), match_b)
    out = Comparison(a=a, b=b, labels=tuple(labels), iou=float(iou), settings=setting_differences(a, b),
                     frames_only_a=sorted(fa - fb), frames_only_b=sorted(fb - fa), match_a=match_a, match_b=match_b,
                     match_iou=np.asarray(match_iou, dtype=np.float64), unmatched_a=unmatched_a,
                     unmatched_b=unmatched_b)
    partner = dict(zip(match_a.tolist(), match_b.tolist()))
    for r in range(max(len(a.selection), len(b.selection))):
        ia = int(a.selection[r]) if r < len(a.selection) else -1
        ib = int(b.selection[r]) if r < len(b.selection) else -1
        out.chosen.append(ChosenRank(r, ia, ib, ia >= 0 and ib >= 0 and partner.get(ia, -2) == ib))
    return out


def setting_differences(a: Trace, b: Trace) -> list[tuple[str, object, object]]:
    """(name, A's value, B's value) of every setting that differs: recording, detector settings, threshold, K, stride,
    model weights."""
    out = []
    if a.recording.id != b.recording.id or a.recording.path != b.recording.path:
        out.append(("recording", a.recording.id, b.recording.id))
    for key in sorted(set(a.detector) | set(b.detector)):
        va, vb = a.detector.get(key), b.detector.get(key)
        if va != vb:
            out.append(("detector" if key == "name" else key, va, vb))
    for name in ("threshold", "k", "stride", "weights_id"):
        va, vb = getattr(a, name), getattr(b, name)
        if va != vb:
            out.append(("model weights" if name == "weights_id" else name, va, vb))
    return out


# ------------------------------------------------------------------------------------------------------- helpers
def _describe(t: Trace) -> str:
    precision = t.detector.get("precision")
    det = t.detector.get("name", "?") + (f" {precision}" if precision else "")
    return (f"{t.recording.id}, {det}, threshold {t.threshold:g}, K {t.k}; {len(t.detections)} detections on "
            f"{len(t.frames)} frames, estimate {_grams(t.estimate)}")


def _det(t: Trace, i: int) -> str:
    if i < 0:
        return "-"
    d = t.detections
    return (f"frame {int(d.frame[i])} {class_name(d.class_id[i])} {d.score[i]:.3f} box {d.xyxy[i].tolist()} "
            f"d={d.d[i]:.1f}mm pred={d.pred[i]:.1f}g")


def _grams(v: float) -> str:
    return "not estimated" if v < 0 else f"{v:.2f} g"


def _frames(frames: list[int]) -> str:
    return "none" if not frames else ", ".join(map(str, frames[:10])) + (" ..." if len(frames) > 10 else "")


def _short(v) -> str:
    text = str(v)
    return text if len(text) <= 60 else text[:57] + "..."


def _jsonable(v):
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    return v


__all__ = ["DEFAULT_IOU", "Comparison", "ChosenRank", "box_iou", "match_boxes", "compare_traces",
           "setting_differences"]
