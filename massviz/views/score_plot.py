"""The paper's Fig. 4 analogue: grouped bars of per-class and total score (top) and mean ε (bottom) per split.

Drawn with matplotlib's object API on an Agg canvas (no pyplot state, no display needed).
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from massviz.errors import MassvizError
from massviz.evaluation.metrics import CLASS_ORDER, ScoreReport
from massviz.evaluation.sweep import best_pair
from massviz.io.atomic import atomic_path

if TYPE_CHECKING:
    import pandas as pd

#: The paper's colours (RGB 0–255): cup black, glass orange, box grey, total yellow.
COLOURS = {"cup": (0, 0, 0), "glass": (238, 113, 27), "box": (127, 127, 127), "total": (229, 194, 36)}
#: Upper limit of the mean-ε axis, as in the paper (taller bars are clipped and labelled with their value).
EPS_YMAX = 10.0


def _colour(name: str, fallback_index: int) -> tuple[float, float, float] | str:
    if name in COLOURS:
        return tuple(c / 255 for c in COLOURS[name])
    return f"C{fallback_index % 10}"


def plot_score_analysis(reports: Sequence[ScoreReport], labels: Sequence[str]) -> Figure:
    """One group of bars per report (split), one bar per class (cup, glass, box, then others) plus ``total``.

    Top: score in %; bottom: mean ε over the estimated recordings, the axis capped at :data:`EPS_YMAX` like the
    paper's figure, a clipped bar showing its true value above it. A class a split has no recording of gets no bar.
    """
    if len(reports) != len(labels):
        raise ValueError(f"{len(reports)} reports but {len(labels)} labels")
    classes = [c for c in CLASS_ORDER if any(c in r.per_class.index for r in reports)]
    classes += sorted({c for r in reports for c in r.per_class.index} - set(classes))
    series = classes + ["total"]
    width = 0.8 / len(series)

    fig = Figure(figsize=(max(4.0, 1.6 * len(reports) + 1.5), 5.0), layout="constrained")
    FigureCanvasAgg(fig)
    ax_score, ax_eps = fig.subplots(2, 1, sharex=True)
    for k, name in enumerate(series):
        xs, scores, eps = [], [], []
        for i, report in enumerate(reports):
            if name == "total":
                s, e = report.score_pct, report.mean_eps
            elif name in report.per_class.index:
                s, e = report.per_class.loc[name, ["score_pct", "mean_eps"]]
            else:
                continue
            xs.append(i + (k - (len(series) - 1) / 2) * width)
            scores.append(s)
            eps.append(e)
        style = dict(width=width, color=_colour(name, k), edgecolor=(0, 0, 0, 0.5), linewidth=0.5)
        ax_score.bar(xs, scores, label=name, **style)
        ax_eps.bar(xs, [min(e, EPS_YMAX) if not math.isnan(e) else 0.0 for e in eps], **style)
        for x, e in zip(xs, eps):
            if e > EPS_YMAX:
                ax_eps.annotate(f"{e:.3f}", (x, EPS_YMAX), xytext=(0, 2), textcoords="offset points",
                                ha="center", va="bottom", fontsize=7)
    ax_score.set(ylim=(0, 100), ylabel="Score s (%)")
    ax_eps.set(ylim=(0, EPS_YMAX * 1.1), ylabel="Mean ε")
    ax_eps.set_xticks(range(len(reports)), labels)
    for ax in (ax_score, ax_eps):
        ax.grid(axis="y", alpha=0.4)
        ax.set_axisbelow(True)
    fig.legend(*ax_score.get_legend_handles_labels(), loc="outside upper center", ncols=len(series), frameon=False)
    return fig


def save_figure(fig: Figure, path: str | Path, dpi: int = 150) -> Path:
    """Save ``fig`` to ``path`` atomically (temp file, then rename); the format follows the suffix."""
    path = Path(path)
    kind = path.suffix.lstrip(".").lower()
    supported = fig.canvas.get_supported_filetypes()
    if kind not in supported:
        raise MassvizError(f"cannot write a figure of type {kind!r}; use one of .{', .'.join(sorted(supported))}", path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format=kind)
    return path


def plot_heatmap(table: pd.DataFrame, path: str | Path, title: str = "CORSMAL score (%)") -> Path:
    """Heatmap of score over threshold (rows) × K (columns), best pair outlined; written atomically."""
    from matplotlib.patches import Rectangle

    grid = table.pivot(index="threshold", columns="k", values="score")
    fig = Figure(figsize=(1.0 + 0.55 * grid.shape[1], 1.0 + 0.35 * grid.shape[0]))
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    im = ax.imshow(grid.to_numpy(), aspect="auto", cmap="viridis", origin="lower")
    ax.set_xticks(range(grid.shape[1]), [str(k) for k in grid.columns])
    ax.set_yticks(range(grid.shape[0]), [f"{t:.2f}" for t in grid.index])
    ax.set_xlabel("K (nearest patches averaged)")
    ax.set_ylabel("detection threshold")
    best = best_pair(table)
    bi, bj = list(grid.index).index(best["threshold"]), list(grid.columns).index(best["k"])
    ax.add_patch(Rectangle((bj - 0.5, bi - 0.5), 1, 1, fill=False, edgecolor="red", linewidth=2))
    ax.set_title(f"{title}; best {best['score']:.2f}% at t={best['threshold']:.2f}, K={int(best['k'])}", fontsize=9)
    fig.colorbar(im, ax=ax, label="score (%)")
    fig.tight_layout()
    return save_figure(fig, path, dpi=120)
