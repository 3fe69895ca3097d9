"""Two runs of one recording in one Rerun recording (``massviz compare DATASET --a ... --b ... --rrd-dir OUT``):
a dataset folder whose catalog table shows both runs' figures, each recording both runs on one timeline.

``OUT/<id>.rrd`` is one Rerun recording (recording id = segment id = the recording's id) holding run A's light
recording at the usual paths (``/camera``, ``/patches/<rank>``, ``/predictions``, ``/log``, ``/summary`` …: what
``massviz.views.rerun_dataset.log_light`` logs) and run B's under ``/b`` (``/b/camera``, ``/b/patches/<rank>``,
``/b/predictions`` …), both on the ``frame`` timeline, plus ``/compare`` (markdown: the two runs' row of the
comparison table and the per-recording ``compare`` report). Its layout puts A and B side by side: the best frame
with each run's boxes, each run's chosen patches, one plot of both runs' predictions.

**Recording properties** (``massviz``; in a catalog's segment table ``property:massviz:<name>``): ``id``,
``container_class``, ``gt_mass_g``, ``in_runs``; for each figure of ``massviz.evaluation.runs.FIGURES``
(``estimate_g``, ``rel_error``, ``score``, ``n_flagged``) and setting (``detector``, ``k``, ``threshold``,
``stride``, ``weights_id``) ``<name>_a`` and ``<name>_b``, and ``delta_<figure>`` (B − A); ``n_patches_changed``,
``n_flags_appeared``, ``n_flags_gone``, ``cues_appeared``, ``cues_gone``, ``label_a``, ``label_b``, ``change_rank``
(the table's order: 1 is the largest change of the relative error) and ``best_frame`` (the frame the recording opens
at: run A's, else B's). Unknown values (no ground truth, not estimated) are left out. ``comparison.csv`` beside the
recordings is the whole table.

``massviz serve OUT`` recognises such a folder by its recordings' ``label_b`` property and registers
``two_runs_blueprint`` for its recordings and ``table_blueprint`` (``TABLE_COLUMNS``, ranked by ``change_rank``) for
its segment table.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from massviz.io.atomic import atomic_path
from massviz.views.rerun.output import APPLICATION_ID
from massviz.views.rerun_dataset import _patch_images, rrd_name, send_properties, source_markdown

#: where run B's entities are (run A's are at the light recording's own paths).
B_ROOT = "/b"
#: each run's colour (0..255) in the two-run layout: its predictions plot line and its patch tiles' captions;
#: light enough to read on the viewer's dark background, and apart from the chosen, flagged and ground-truth colours.
RUN_COLOURS = {"A": (86, 180, 255), "B": (255, 196, 0)}
COMPARISON_NAME = "comparison.csv"
#: the comparison table's columns sent as recording properties (besides the ``_a``/``_b``/``delta_`` ones).
SHARED_PROPERTIES = ("id", "container_class", "gt_mass_g", "in_runs", "change_rank", "n_patches_changed",
                     "n_flags_appeared", "n_flags_gone", "cues_appeared", "cues_gone")
#: the columns of the catalog's segment table that the two-run table layout shows after the "recording" button (in
#: this order), ranked by ``change_rank``.
TABLE_COLUMNS = ("change_rank", "container_class", "rel_error_a", "rel_error_b", "delta_rel_error", "estimate_g_a",
                 "estimate_g_b", "delta_estimate_g", "gt_mass_g", "n_patches_changed", "n_flags_appeared",
                 "n_flags_gone", "cues_appeared", "cues_gone", "score_a", "score_b", "detector_a", "detector_b",
                 "k_a", "k_b", "threshold_a", "threshold_b", "label_a", "label_b")


class Prefixed:
    """A recording stream whose ``log`` and ``send_columns`` put every entity under ``root`` (so that a run's loggers, which log at
    fixed paths, log a second run beside the first); everything else is the stream's."""

    def __init__(self, stream: rr.RecordingStream, root: str):
        self._stream, self._root = stream, root.rstrip("/")

    def _path(self, path) -> str:
        return self._root + "/" + str(path).lstrip("/")

    def log(self, path: str, *args, **kwargs):
        return self._stream.log(self._path(path), *args, **kwargs)

    def send_columns(self, path: str, *args, **kwargs):
        return self._stream.send_columns(self._path(path), *args, **kwargs)

    def __getattr__(self, name):
        return getattr(self._stream, name)


def _rounded(name: str, value):
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        if not math.isfinite(float(value)):
            return None
        return round(float(value), 2 if "_g" in name else 4) + 0.0  # (+ 0.0: no "-0" in a table)
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return None
    return str(value)


def run_properties(row: dict, labels: tuple[str, str]) -> dict:
    """The recording properties (module docstring) of one row of ``massviz.evaluation.runs.compare_runs``,
    rounded as a table shows them; unknown values left out."""
    from massviz.evaluation.runs import FIGURES, SETTING_COLUMNS

    names = list(SHARED_PROPERTIES) + [f"{f}_{s}" for f in (*FIGURES, *SETTING_COLUMNS) for s in "ab"] + \
        [f"delta_{f}" for f in FIGURES]
    out = {}
    for name in names:
        value = _rounded(name, row.get(name))
        if value is not None:
            out[name] = value
    out["label_a"], out["label_b"] = labels
    return out


def style_run(stream, trace, side: str, label: str) -> None:
    """Name and colour run ``side`` ("A" or "B") in a two-run recording (``stream``: the run's own stream or its
    ``Prefixed`` one): its running estimate is the plot's one series of the run, named "``side``: ``label``" in the
    run's colour (static, after the light recording's own style); every patch tile's caption starts with the run's
    name, in the run's colour unless the patch is flagged."""
    from massviz.views.palette import FLAGGED_COLOUR, rgb255

    colour = RUN_COLOURS[side]
    stream.log("/predictions/running_estimate", rr.SeriesLines.from_fields(names=f"{side}: {label}", colors=colour,
                                                                           widths=3), static=True)
    for rank, i in enumerate(trace.selection):
        flag = trace.flags.of(int(i))
        flagged = flag is not None and flag.flagged
        stream.log(f"/patches/{rank}/outline", rr.Boxes2D.from_fields(
            labels=[f"{side} ★{rank}" + (" ⚑" if flagged else "")],
            colors=[rgb255(FLAGGED_COLOUR) if flagged else colour]), static=True)


def flagged_ranks(trace) -> set[int]:
    """The ranks of ``trace``'s chosen patches that are flagged."""
    ranks = set()
    for rank, i in enumerate(trace.selection):
        flag = trace.flags.of(int(i))
        if flag is not None and flag.flagged:
            ranks.add(rank)
    return ranks


def two_runs_blueprint(k_a: int, k_b: int, labels: tuple[str, str] = ("", ""), flagged_a=(), flagged_b=()) -> \
        rrb.Blueprint:
    """A and B side by side: the best frame with each run's boxes of every frame, each run's chosen patches (tiles
    named by run and rank, "⚑ flagged" on the flagged ranks), one plot of both runs' running estimates (one series
    a run, in its colour, and the ground truth) with its legend, the texts (comparison first)."""
    flagged = {"A": {int(r) for r in flagged_a}, "B": {int(r) for r in flagged_b}}
    label_of = dict(zip("AB", labels))

    def grid(root: str, k: int, side: str):
        if not k:
            return rrb.TextDocumentView(name=f"{side}: summary", origin=f"{root}/summary")
        tiles = [rrb.Spatial2DView(name=f"{side} ★{r}" + (" ⚑ flagged" if r in flagged[side] else ""),
                                   origin=f"{root}/patches/{r}") for r in range(k)]
        title = f"{side}: chosen patches" + (f" ({label_of[side]})" if label_of[side] else "")
        return rrb.Grid(*tiles, name=title)

    cam = lambda root, side: rrb.Spatial2DView(  # noqa: E731
        name=f"{side}: best frame · detections", origin=f"{root}/camera",
        contents=[f"{root}/camera/rgb", f"{root}/camera/detections"],
        # the boxes without their labels: side by side at a laptop's size the labels (in the boxes' colours) cover
        # the frame and are hard to read; hovering a box shows them, the tiles hold each patch's numbers
        overrides={f"{root}/camera/detections": rr.Boxes2D.from_fields(show_labels=False)})
    plot = rrb.TimeSeriesView(name="Running estimate (g): A and B", origin="/",
                              contents=["/predictions/running_estimate", f"{B_ROOT}/predictions/running_estimate",
                                        "/predictions/ground_truth"],
                              plot_legend=rrb.PlotLegend(corner=rrb.Corner2D.LeftTop, visible=True))
    text = rrb.Tabs(rrb.TextDocumentView(name="A vs B", origin="/compare"),
                    rrb.TextDocumentView(name="A: summary", origin="/summary"),
                    rrb.TextDocumentView(name="B: summary", origin=f"{B_ROOT}/summary"),
                    rrb.TextLogView(name="A: decisions", origin="/log"),
                    rrb.TextLogView(name="B: decisions", origin=f"{B_ROOT}/log"))
    return rrb.Blueprint(
        rrb.Horizontal(rrb.Vertical(rrb.Horizontal(cam("", "A"), cam(B_ROOT, "B")), text, row_shares=[3, 2]),
                       rrb.Vertical(grid("", k_a, "A"), grid(B_ROOT, k_b, "B"), plot, row_shares=[1, 1, 1]),
                       column_shares=[3, 2]),
        # at a laptop's window size both runs need the width: the side panels start collapsed, the time panel as
        # its one-line bar (each opens with a click)
        rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(timeline="frame", state="collapsed"))


def table_blueprint(present=None):
    """The two-run segment table's layout: the "recording" button, then ``TABLE_COLUMNS`` (with ``present``, only
    those the segment table has), the largest change of the relative error first
    (``massviz.views.rerun_dataset.table_blueprint``)."""
    from massviz.views.rerun_dataset import table_blueprint as one_run_table

    return one_run_table(TABLE_COLUMNS, sort_by="change_rank", direction="ascending", present=present)


def write_two_runs(trace_a, trace_b, recording, out_dir: str | Path, row: dict, labels: tuple[str, str],
                   markdown: str = "") -> Path:
    """Write ``out_dir/<id>.rrd``: both traces of ``recording`` in one recording (module docstring), with the
    properties of its comparison ``row``. Returns the file."""
    out_dir = Path(out_dir)
    path = out_dir / rrd_name(trace_a.recording.id)
    stream = rr.RecordingStream(APPLICATION_ID, recording_id=trace_a.recording.id)
    with atomic_path(path) as tmp:
        stream.save(tmp)
        try:
            stream.send_recording_name(f"massviz {trace_a.recording.id}: A {labels[0]} | B {labels[1]}")
            from massviz.evaluation.browser import best_frame

            props = run_properties(row, labels)
            props["best_frame"] = best_frame(trace_a if len(trace_a.selection) or not len(trace_b.selection)
                                             else trace_b)
            send_properties(stream, props)
            stream.send_blueprint(two_runs_blueprint(len(trace_a.selection), len(trace_b.selection), labels,
                                                     flagged_ranks(trace_a), flagged_ranks(trace_b)),
                                  make_active=True, make_default=True)
            from massviz.views.rerun_dataset import log_light

            source = source_markdown(trace_a, recording)
            for side, run, trace, label in (("A", stream, trace_a, labels[0]),
                                            ("B", Prefixed(stream, B_ROOT), trace_b, labels[1])):
                patches, rgb_best = _patch_images(trace, recording)
                log_light(run, trace, recording, patches, rgb_best, source)
                style_run(run, trace, side, label)
            stream.log("/compare", rr.TextDocument(markdown or f"# A {labels[0]} | B {labels[1]}",
                                                   media_type=rr.MediaType.MARKDOWN), static=True)
            stream.flush()
        finally:
            stream.disconnect()
    return path


def row_markdown(row: dict, labels: tuple[str, str], report: str = "") -> str:
    """The comparison of one recording as markdown: A, B and delta of each figure, the changed patches and flags,
    then the per-recording ``compare`` report."""
    from massviz.evaluation.runs import FIGURES

    lines = [f"# {row.get('id')}: A {labels[0]} | B {labels[1]}", "", "| | A | B | B − A |", "|---|---|---|---|"]
    for f in FIGURES:
        vals = [_rounded(f, row.get(n)) for n in (f"{f}_a", f"{f}_b", f"delta_{f}")]
        lines.append(f"| {f} | " + " | ".join("–" if v is None else str(v) for v in vals) + " |")
    for name in ("patches_added", "patches_dropped", "patches_reranked", "flags_appeared", "flags_gone",
                 "cues_appeared", "cues_gone"):
        lines.append(f"- {name.replace('_', ' ')}: {row.get(name) or 'none'}")
    if report:
        lines += ["", "```", report.rstrip(), "```"]
    return "\n".join(lines) + "\n"


__all__ = ["B_ROOT", "RUN_COLOURS", "COMPARISON_NAME", "TABLE_COLUMNS", "Prefixed", "run_properties", "style_run",
           "flagged_ranks", "two_runs_blueprint",
           "table_blueprint", "write_two_runs",
           "row_markdown"]
