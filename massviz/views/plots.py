"""Static matplotlib figures of one trace's stages, for notebooks and reports.

Every function returns a ``matplotlib.figure.Figure`` built with the object API (no pyplot state; Jupyter's inline
backend displays it, ``fig.savefig`` writes it). They only read the trace and, for pixels, the recording's frames.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from massviz.core.trace import Trace
from massviz.core.types import Frame, Intrinsics, class_name
from massviz.evaluation.metrics import ScoreReport
from massviz.views.labels import short_reason
from massviz.views.palette import (
    CHOSEN_COLOUR,
    CHOSEN_HEX,
    FLAGGED_COLOUR,
    FLAGGED_HEX,
    OTHER_HEX,
    WITHOUT_FLAGGED_COLOUR,
    hex_colour,
)

#: colour of chosen patches (rank shown) and of the other detections.
CHOSEN, OTHER, FLAGGED = CHOSEN_HEX, OTHER_HEX, FLAGGED_HEX  # massviz.views.palette: the same in every view


def frame_detections(trace: Trace, frame_index: int) -> np.ndarray:
    """Indices of the trace's detections made on ``frame_index``."""
    return np.flatnonzero(trace.detections.frame == int(frame_index))


def best_frame(trace: Trace) -> int:
    """The frame of the nearest chosen patch (else the first processed frame)."""
    if len(trace.selection):
        return int(trace.detections.frame[trace.selection[0]])
    return int(trace.frames[0]) if len(trace.frames) else 0


def frame_figure(trace: Trace, frame: Frame, flagged: Sequence[int] | None = None, width: float = 7.0) -> Figure:
    """RGB frame with every detection of that frame: mask tinted, box, "class score · d mm" and the rank of chosen
    patches (★rank, in the palette's chosen colour); flagged detections (default: the trace's flags) in its flagged
    colour with ⚑."""
    dets = trace.detections
    if flagged is None:
        flagged = [p.detection for p in trace.flags.flagged]
    rank_of = {int(i): r for r, i in enumerate(trace.selection)}
    fig = Figure(figsize=(width, width * frame.height / frame.width + 0.4))
    ax = fig.add_subplot()
    overlay = frame.rgb.astype(np.float32) / 255.0
    for i in frame_detections(trace, frame.index):
        colour = FLAGGED if int(i) in set(flagged) else (CHOSEN if int(i) in rank_of else OTHER)
        rgb = np.array([int(colour[k:k + 2], 16) for k in (1, 3, 5)]) / 255.0
        m = dets.full_mask(int(i), frame.height, frame.width)
        overlay[m] = 0.55 * overlay[m] + 0.45 * rgb
    ax.imshow(overlay)
    for i in frame_detections(trace, frame.index):
        x1, y1, x2, y2 = (int(v) for v in dets.xyxy[i])
        chosen = int(i) in rank_of
        colour = FLAGGED if int(i) in set(flagged) else (CHOSEN if chosen else OTHER)
        ax.add_patch(Rectangle((x1, y1), x2 - x1, y2 - y1, fill=False, edgecolor=colour, linewidth=2))
        label = f"{class_name(dets.class_id[i])} {dets.score[i]:.2f} · {dets.d[i]:.0f} mm"
        if chosen:
            label += f" ★{rank_of[int(i)]}" + (" ⚑" if int(i) in set(flagged) else "")
        ax.text(x1, max(y1 - 3, 8), label, color="black", fontsize=8,
                bbox={"facecolor": colour, "alpha": 0.85, "pad": 1, "edgecolor": "none"})
    ax.set_title(f"{trace.recording.id} · frame {frame.index}: masks and boxes "
                 f"(magenta: chosen, ★rank; red ⚑: flagged; blue: other detections)", fontsize=9)
    ax.set_axis_off()
    fig.tight_layout()
    return fig


def depth_figure(frame: Frame, width: float = 7.0) -> Figure:
    """The depth map in mm (turbo colour map; pixels without depth are white)."""
    fig = Figure(figsize=(width, width * frame.height / frame.width + 0.4))
    ax = fig.add_subplot()
    depth = np.ma.masked_equal(frame.depth.astype(np.float32), 0)
    im = ax.imshow(depth, cmap="turbo")
    fig.colorbar(im, ax=ax, label="depth (mm)", fraction=0.03)
    ax.set_title(f"frame {frame.index}: depth (white: no depth)", fontsize=9)
    ax.set_axis_off()
    fig.tight_layout()
    return fig


def point_cloud_figure(trace: Trace, frame: Frame, intrinsics: Intrinsics, step: int = 3,
                       max_depth_m: float = 1.8, width: float = 7.0) -> Figure:
    """The frame's depth back-projected to 3D (metres, camera frame; RGB colours), the masks of the frame's chosen
    patches in the palette's chosen colour (a flagged one, ``trace.flags``, in its flagged colour), points farther
    than ``max_depth_m`` (the room's wall) left out. A matplotlib 3D scatter, seen from above left."""
    from matplotlib.ticker import MaxNLocator

    from massviz.measure3d.geometry import depth_to_points

    points, colours = depth_to_points(frame.depth, intrinsics, frame.rgb, step)
    sub = frame.depth[::step, ::step] > 0
    flagged = {int(p.detection) for p in trace.flags.flagged}
    cols = colours.astype(np.float32) / 255.0
    for i in trace.selection:  # flagged last, so that a flagged patch overlapping a chosen one stays red
        if int(trace.detections.frame[i]) == frame.index and int(i) not in flagged:
            cols[trace.detections.full_mask(int(i), frame.height, frame.width)[::step, ::step][sub]] = CHOSEN_COLOUR
    for i in trace.selection:
        if int(trace.detections.frame[i]) == frame.index and int(i) in flagged:
            cols[trace.detections.full_mask(int(i), frame.height, frame.width)[::step, ::step][sub]] = FLAGGED_COLOUR
    near = points[:, 2] <= max_depth_m
    points, cols = points[near], cols[near]
    fig = Figure(figsize=(width, width * 0.75))
    ax = fig.add_subplot(projection="3d")
    # camera frame is x right, y down, z forward: plot x, z (depth), -y (up)
    ax.scatter(points[:, 0], points[:, 2], -points[:, 1], c=cols, s=1.0, depthshade=False)
    for axis in (ax.xaxis, ax.yaxis, ax.zaxis):  # few ticks: the tilted axes' labels must not run into each other
        axis.set_major_locator(MaxNLocator(4))
    ax.set_xlabel("x (m)", labelpad=6)
    ax.set_ylabel("distance (m)", labelpad=10)
    ax.set_zlabel("up (m)", labelpad=6)
    ax.view_init(elev=12, azim=-65)
    ax.set_title(f"frame {frame.index}: depth as a point cloud ({len(points)} points; chosen patch in magenta, "
                 f"flagged in red)", fontsize=9)
    fig.tight_layout()
    return fig


def patches_figure(trace: Trace, indices: Sequence[int] | None = None, flags: dict | None = None,
                   columns: int = 5, patch_source=None) -> Figure:
    """The chosen patches (or ``indices``), one tile each titled with ★rank, frame, track, a, b, d and the prediction,
    outlined in the palette's chosen colour; ``flags`` ({index: short reason}, default: the trace's own flags) are
    drawn in its flagged colour with ⚑. ``patch_source(i)`` returns the RGB patch of detection i when the trace did
    not keep it (default: a grey tile)."""
    dets = trace.detections
    if flags is None:
        flags = {p.detection: short_reason(p) for p in trace.flags.flagged}
    idx = [int(i) for i in (trace.selection if indices is None else indices)]
    rank_of = {int(i): r for r, i in enumerate(trace.selection)}
    n = max(len(idx), 1)
    cols = min(columns, n)
    rows = int(np.ceil(n / cols))
    fig = Figure(figsize=(2.3 * cols, 2.7 * rows))
    for j, i in enumerate(idx):
        ax = fig.add_subplot(rows, cols, j + 1)
        patch = dets.patches[i] if dets.patches[i] is not None else (patch_source(i) if patch_source else None)
        ax.imshow(patch if patch is not None else np.full((8, 8, 3), 200, np.uint8))
        rank = f"★{rank_of[i]}" if i in rank_of else "excluded"
        title = (f"{rank} · frame {int(dets.frame[i])} · track {int(dets.track[i])}\n"
                 f"a={dets.a[i]:.2f} b={dets.b[i]:.2f} d={dets.d[i]:.0f}mm\npred {dets.pred[i]:.1f} g")
        red = i in flags
        ax.set_title(title + (f"\n⚑ {flags[i]}" if red else ""), fontsize=8, color=FLAGGED if red else "black")
        ax.set_xticks([])
        ax.set_yticks([])
        for side in ax.spines.values():
            side.set_edgecolor(FLAGGED if red else (CHOSEN if i in rank_of else "#999999"))
            side.set_linewidth(3 if red else 2)
    if not idx:
        fig.text(0.5, 0.5, "no patch chosen", ha="center")
    fig.tight_layout()
    return fig


def flags_text(trace: Trace) -> str:
    """The flags of the trace's chosen patches in a few lines (notebooks): the summary line, then one line per
    chosen patch (★rank, frame, track, flagged or not and why)."""
    flags = trace.flags
    lines = [f"⚑ {flags.warning()}" if flags.flagged else
             f"no chosen patch is flagged: all {len(flags.patches)} look like the container"]
    for p in flags.patches:
        state = f"FLAGGED ({p.severity})" if p.flagged else "ok"
        lines.append(f"  ★{p.rank} frame {p.frame:>3} track {p.track:>2}: {state}" + (f": {p.reason}" if p.reason
                                                                                        else ""))
    return "\n".join(lines)


def estimate_figure(trace: Trace) -> Figure:
    """Each chosen patch's prediction (bars by rank, flagged ones in the flagged colour), their mean (the estimate),
    the estimate without the flagged patches and the ground truth when known."""
    pred = trace.detections.pred[trace.selection]
    flagged = {p.rank for p in trace.flags.flagged}
    fig = Figure(figsize=(6, 3))
    ax = fig.add_subplot()
    ax.bar(np.arange(len(pred)), pred, color=[FLAGGED if r in flagged else CHOSEN for r in range(len(pred))],
           label="patch prediction" + (" (red: flagged)" if flagged else ""))
    if trace.estimate >= 0:
        ax.axhline(trace.estimate, color="#1f77b4", linewidth=2, label=f"estimate {trace.estimate:.1f} g")
    if flagged and trace.flags.estimate_without >= 0:
        ax.axhline(trace.flags.estimate_without, color=hex_colour(WITHOUT_FLAGGED_COLOUR), linestyle=":", linewidth=2,
                   label=f"without flagged {trace.flags.estimate_without:.1f} g")
    gt = trace.ground_truth_mass
    if gt is not None:
        ax.axhline(gt, color="#2ca02c", linestyle="--", linewidth=2, label=f"ground truth {gt:.1f} g")
    ax.set_xticks(np.arange(len(pred)))
    ax.set_xlabel("chosen patch (★rank; 0 = nearest)")
    ax.set_ylabel("mass (g)")
    ax.set_title(f"{trace.recording.id}: K={trace.k}, threshold {trace.threshold:.2f}", fontsize=9)
    ax.legend(fontsize=8, loc="best")
    fig.tight_layout()
    return fig


def running_estimate_figure(trace: Trace, tolerance: float = 0.10) -> Figure:
    """The running estimate (``Trace.running_estimate``: the mean of the K nearest so far after each processed
    frame), the ±``tolerance`` band around the final estimate and the frame from which it stays inside the band
    (``Trace.settled_after``), and the ground truth when known."""
    frames, running = np.asarray(trace.frames), trace.running_estimate()
    fig = Figure(figsize=(6, 3))
    ax = fig.add_subplot()
    ok = running >= 0
    ax.step(frames[ok], running[ok], where="post", color="#1f77b4", linewidth=2, label="running estimate")
    title = f"{trace.recording.id}: not estimated"
    if trace.estimate >= 0:
        lo, hi = trace.estimate * (1 - tolerance), trace.estimate * (1 + tolerance)
        ax.axhspan(lo, hi, color="#1f77b4", alpha=0.12, label=f"final {trace.estimate:.1f} g ± {tolerance:.0%}")
        n = trace.settled_after(tolerance)
        ax.axvline(frames[n - 1], color="#ff7f0e", linestyle=":", label=f"settled at frame {frames[n - 1]}")
        title = f"{trace.recording.id}: within {tolerance:.0%} of the final estimate after {n} of {len(frames)} frames"
    gt = trace.ground_truth_mass
    if gt is not None:
        ax.axhline(gt, color="#2ca02c", linestyle="--", linewidth=2, label=f"ground truth {gt:.1f} g")
    ax.set_xlabel("frame")
    ax.set_ylabel("mass (g)")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8, loc="best")
    fig.tight_layout()
    return fig


def timings_figure(trace: Trace) -> Figure:
    """Wall time of each pipeline stage (seconds; ``total`` and ``cache`` apart)."""
    stages = [(k, v) for k, v in trace.timings.items() if k not in ("total",)]
    fig = Figure(figsize=(6, 0.4 + 0.35 * max(len(stages), 1)))
    ax = fig.add_subplot()
    ax.barh([k for k, _ in stages], [v for _, v in stages], color="#1f77b4")
    for y, (_, v) in enumerate(stages):
        ax.text(v, y, f" {v:.2f} s", va="center", fontsize=8)
    ax.invert_yaxis()
    total = trace.timings.get("total")
    ax.set_xlabel("seconds")
    ax.set_title(f"stage timings over {len(trace.frames)} frames"
                 + (f" (total {total:.1f} s)" if total is not None else ""), fontsize=9)
    fig.tight_layout()
    return fig


def score_figure(report: ScoreReport, label: str = "samples") -> Figure:
    """Per-class and total CORSMAL score and mean ε (the paper's Fig. 4 style, one group of bars)."""
    from massviz.views.score_plot import plot_score_analysis

    return plot_score_analysis([report], [label])


__all__ = ["flags_text", "frame_figure", "depth_figure", "point_cloud_figure", "patches_figure", "estimate_figure",
           "timings_figure", "score_figure", "best_frame", "frame_detections"]
