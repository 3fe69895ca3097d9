"""Notebook 05's widgets: the two-run table with filters, and the patch map (an interactive plotly scatter of every
chosen patch) linked to a patch grid, a similar-patch search and the inline Rerun viewer.

* ``RunsTable`` — a ``massviz.evaluation.runs.compare_runs`` table with the filters "got worse by > x", "flag
  appeared", "patches changed" and the class; it shows the rows that pass (``.massviz-runs-count`` says how many).
* ``PatchMapView`` — the map (``massviz.evaluation.patch_map.PatchMap``): colour by relative error, flag, class, run
  or the ground truth's instance; a box or lasso selection fills the grid with those patches (``.massviz-map-tile``);
  a click on a point opens that patch's recording at its frame in the viewer (``RecordingViewer`` over a folder of
  recordings, e.g. the two-run recordings of ``massviz compare DATASET --a … --b … --rrd-dir``); "similar" on a
  tile, or the search box, fills the grid with the nearest patches and selects them on the map.

plotly (``FigureWidget``, anywidget) and ipywidgets are imported when a widget is built.
"""
from __future__ import annotations

import html
import time

import numpy as np
import pandas as pd

from massviz.views.palette import CHOSEN_HEX, FLAGGED_HEX

#: the colourings of the map: label → column of ``PatchMap.patches``.
COLOURINGS = {"relative error": "rel_error", "flag": "flagged", "class": "class", "run": "run",
              "container class": "container_class", "ground truth": "ground_truth"}
#: categorical colours (plotly's D3 palette).
CATEGORY_COLOURS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f",
                    "#bcbd22", "#17becf")
#: columns of the two-run table shown (``patches``: +added −dropped ↕re-ranked; ``flags``: +appeared −gone).
TABLE_COLUMNS = {"id": "recording", "container_class": "class", "estimate_g_a": "A (g)",
                 "estimate_g_b": "B (g)", "delta_estimate_g": "Δ (g)", "rel_error_a": "ε A",
                 "rel_error_b": "ε B", "delta_rel_error": "Δ ε", "score_a": "score A", "score_b": "score B",
                 "patches": "patches", "flags": "flags"}
FORMATS = {"estimate_g_a": "{:.2f}", "estimate_g_b": "{:.2f}", "delta_estimate_g": "{:+.2f}", "rel_error_a": "{:.3f}",
           "rel_error_b": "{:.3f}", "delta_rel_error": "{:+.3f}", "score_a": "{:.3f}", "score_b": "{:.3f}"}
TABLE_STYLE = ("<style>.massviz-runs-table{border-collapse:collapse;font-size:12px;line-height:1.3}"
               ".massviz-runs-table td,.massviz-runs-table th{padding:2px 6px;border-bottom:1px solid #ddd;"
               "text-align:right;white-space:nowrap}.massviz-runs-table td:nth-child(-n+2){text-align:left}</style>")


def _counts(table: pd.DataFrame) -> pd.DataFrame:
    n = lambda col: table[col].fillna("").map(lambda s: len(str(s).split()))  # noqa: E731
    return table.assign(patches=[f"+{a} −{d} ↕{r}" for a, d, r in zip(n("patches_added"), n("patches_dropped"),
                                                                       n("patches_reranked"))],
                        flags=[f"+{a} −{g}" for a, g in zip(table["n_flags_appeared"], table["n_flags_gone"])])


class RunsTable:
    """The comparison table with filters (module docstring); ``set(worse_by=, flag_appeared=, ...)`` filters from
    code, as the widgets do."""

    def __init__(self, table: pd.DataFrame, scores: pd.DataFrame | None = None, max_rows: int = 200):
        import ipywidgets as W

        self.table, self.max_rows = table, int(max_rows)
        classes = sorted(c for c in table["container_class"].dropna().unique() if c)
        self.w_worse = W.FloatText(value=0.0, step=0.05, description="worse by >",
                                   style={"description_width": "initial"})
        self.w_use_worse = W.Checkbox(value=False, description="only worse", indent=False)
        self.w_flag = W.Checkbox(value=False, description="flag appeared", indent=False)
        self.w_changed = W.Checkbox(value=False, description="patches changed", indent=False)
        self.w_class = W.Dropdown(options=["any", *classes], value="any", description="class")
        self.count = W.HTML()
        self.out = W.HTML()
        self.scores = W.HTML(TABLE_STYLE + "<b>score per class</b> (%; best: each recording's better run)" +
                             scores.to_html(classes="massviz-runs-table", border=0, float_format="{:.2f}".format)
                             if scores is not None else "")
        for w in (self.w_worse, self.w_use_worse, self.w_flag, self.w_changed, self.w_class):
            w.observe(lambda _: self.refresh(), names="value")
        self.widget = W.VBox([W.HBox([self.w_use_worse, self.w_worse, self.w_flag, self.w_changed, self.w_class]),
                              self.count, self.out, self.scores])
        self.widget.add_class("massviz-runs")
        self.refresh()

    def set(self, worse_by: float | None = None, flag_appeared: bool = False, patches_changed: bool = False,
            cls: str | None = None) -> pd.DataFrame:
        self.w_use_worse.value, self.w_worse.value = worse_by is not None, float(worse_by or 0.0)
        self.w_flag.value, self.w_changed.value = bool(flag_appeared), bool(patches_changed)
        self.w_class.value = cls or "any"
        return self.refresh()

    def shown(self) -> pd.DataFrame:
        from massviz.evaluation.runs import filter_comparison

        return filter_comparison(self.table, worse_by=self.w_worse.value if self.w_use_worse.value else None,
                                 flag_appeared=True if self.w_flag.value else None,
                                 patches_changed=True if self.w_changed.value else None,
                                 cls=None if self.w_class.value == "any" else self.w_class.value)

    def refresh(self) -> pd.DataFrame:
        shown = self.shown()
        view = _counts(shown.head(self.max_rows))
        cols = [c for c in TABLE_COLUMNS if c in view.columns]
        fmt = {TABLE_COLUMNS[c]: (lambda v, f=f: "–" if pd.isna(v) else f.format(v)) for c, f in FORMATS.items()}
        self.out.value = TABLE_STYLE + view[cols].rename(columns=TABLE_COLUMNS).to_html(
            index=False, formatters=fmt, na_rep="–", classes="massviz-runs-table", border=0)
        self.count.value = (f"<span class='massviz-runs-count'>{len(shown)} of {len(self.table)} recordings"
                            "</span>")
        return shown


def colours_of(values: pd.Series) -> tuple[list, dict]:
    """(a colour per value, legend: label → colour). Numbers: a continuous scale (returned as numbers; the map
    uses a colour scale); booleans and text: ``CATEGORY_COLOURS`` (flagged: the flagged colour)."""
    if values.dtype == bool:
        return [FLAGGED_HEX if v else CHOSEN_HEX for v in values], {"flagged": FLAGGED_HEX, "not flagged": CHOSEN_HEX}
    if pd.api.types.is_numeric_dtype(values):
        return list(values.astype(float).fillna(-1.0)), {}
    cats = sorted({str(v) for v in values.fillna("")})
    legend = {c or "(none)": CATEGORY_COLOURS[i % len(CATEGORY_COLOURS)] for i, c in enumerate(cats)}
    return [legend[str(v) or "(none)"] for v in values.fillna("")], legend


class PatchMapView:
    """The map, its grid, the similar-patch search and the viewer (module docstring). ``images(row)`` returns a
    patch row's JPEG bytes; ``viewer``: a ``massviz.views.failure_browser.RecordingViewer`` (None: no viewer)."""

    def __init__(self, pmap, images, *, viewer=None, colour: str = "relative error", max_tiles: int = 48,
                 width: int = 720, height: int = 480):
        import ipywidgets as W
        import plotly.graph_objects as go

        self.map, self.images, self.viewer, self.max_tiles = pmap, images, viewer, int(max_tiles)
        p = pmap.patches
        self.w_colour = W.Dropdown(options=list(COLOURINGS), value=colour, description="colour")
        self.w_query = W.Combobox(options=list(p["patch_id"]), placeholder="patch id", description="similar to",
                                  ensure_option=True, layout=W.Layout(width="420px"))
        self.w_n = W.BoundedIntText(value=8, min=1, max=500, description="n", layout=W.Layout(width="120px"))
        self.w_search = W.Button(description="similar patches", icon="search")
        self.note = W.HTML()
        self.grid = W.GridBox(layout=W.Layout(grid_template_columns="repeat(auto-fill, 132px)", grid_gap="4px"))
        self.grid.add_class("massviz-map-grid")
        hover = [f"{html.escape(r.patch_id)}<br>{r.recording} · f{r.frame} · ★{r.rank} · {r['class']}"
                 f"<br>ε {r.rel_error:.2f} · {r.run}" + (" · ⚑" if r.flagged else "")
                 for _, r in p.iterrows()] if len(p) else []
        scatter = go.Scattergl if len(p) > 2000 else go.Scatter
        self.fig = go.FigureWidget(
            data=[scatter(x=p["x"], y=p["y"], mode="markers", customdata=np.arange(len(p)), hovertext=hover,
                          hoverinfo="text", marker={"size": 11, "line": {"width": 1, "color": "#333"}},
                          selected={"marker": {"size": 14}}, unselected={"marker": {"opacity": 0.35}})],
            layout=go.Layout(width=width, height=height, dragmode="select", margin={"l": 30, "r": 40, "t": 36, "b": 30},
                             modebar={"orientation": "v"},  # a column at the right edge, clear of the title
                             title={"text": f"every chosen patch ({len(p)}), {pmap.method} of the mass CNN's pooled "
                                            "features", "font": {"size": 13}},
                             xaxis={"showticklabels": False}, yaxis={"showticklabels": False}))
        self.fig.data[0].on_selection(self._on_selection)
        self.fig.data[0].on_click(self._on_click)
        self.w_colour.observe(lambda c: self.set_colour(c["new"]), names="value")
        self.w_search.on_click(lambda _: self.w_query.value and self.similar(self.w_query.value, self.w_n.value))
        self.legend = W.HTML()
        self.last_redraw_s = 0.0
        self.selected: list[int] = []
        parts = [W.HBox([self.w_colour, self.legend]), self.fig, W.HBox([self.w_query, self.w_n, self.w_search]),
                 self.note, self.grid]
        if viewer is not None:
            parts.append(viewer.widget)
        self.widget = W.VBox(parts)
        self.widget.add_class("massviz-patch-map")
        self.set_colour(colour)
        self.show_rows([], "select a region of the map (box or lasso), click a point, or search similar patches")

    # -- colour ------------------------------------------------------------------------------------------------
    def set_colour(self, label: str) -> float:
        """Colour the points by ``label`` (``COLOURINGS``); returns the seconds the kernel took."""
        t0 = time.perf_counter()
        column = COLOURINGS[label]
        colours, legend = colours_of(self.map.patches[column]) if len(self.map.patches) else ([], {})
        with self.fig.batch_update():
            marker = self.fig.data[0].marker
            if legend:
                marker.color, marker.showscale = colours, False
            else:
                marker.color, marker.colorscale, marker.showscale = colours, "Viridis", True
                marker.colorbar = {"title": {"text": "ε"}, "thickness": 12}
        self.legend.value = " ".join(f"<span style='color:{c}'>●</span> {html.escape(k)}" for k, c in legend.items())
        if self.w_colour.value != label:
            self.w_colour.value = label
        self.last_redraw_s = time.perf_counter() - t0
        return self.last_redraw_s

    # -- grid --------------------------------------------------------------------------------------------------
    def tile(self, i: int, extra: str = ""):
        import ipywidgets as W

        r = self.map.patches.iloc[i]
        image = W.Image(value=self.images(r), format="jpeg", layout=W.Layout(max_width="124px", max_height="124px"))
        flag = f"<br><span style='color:{FLAGGED_HEX}'>⚑ {html.escape(str(r.cues).replace(',', ', ') or 'flagged')}" \
            "</span>" if r.flagged else ""
        gt = f" · {html.escape(r.ground_truth)}" if r.ground_truth else ""
        caption = W.HTML(f"<div style='font-size:11px;line-height:1.3'><b>{html.escape(r.recording)}</b> "
                         f"ε {r.rel_error:.2f}<br>★{r['rank']} · f{r.frame} · {r['class']}{gt}<br>run "
                         f"{html.escape(str(r.run))}{extra}{flag}</div>")
        open_button = W.Button(description="open", layout=W.Layout(width="58px"),
                               tooltip=f"open {r.recording} at frame {r.frame}")
        similar = W.Button(description="similar", layout=W.Layout(width="66px"))
        open_button.on_click(lambda _, i=i: self.open(i))
        similar.on_click(lambda _, pid=r.patch_id: self.similar(pid, self.w_n.value))
        box = W.VBox([image, caption, W.HBox([open_button, similar])],
                     layout=W.Layout(border=f"3px solid {FLAGGED_HEX}" if r.flagged else f"2px solid {CHOSEN_HEX}",
                                     padding="2px"))
        box.add_class("massviz-map-tile")
        return box

    def show_rows(self, rows, note: str, extra=None) -> None:
        rows = list(rows)
        self.grid.children = [self.tile(i, (extra or {}).get(i, "")) for i in rows[:self.max_tiles]]
        self.note.value = f"<span class='massviz-map-note'>{html.escape(note)}</span>"

    def select(self, rows, note: str | None = None) -> None:
        """Show the patches of ``rows`` (positions in ``PatchMap.patches``) in the grid."""
        self.selected = [int(i) for i in rows]
        n_rec = self.map.patches.iloc[self.selected]["recording"].nunique() if self.selected else 0
        flagged = int(self.map.patches.iloc[self.selected]["flagged"].sum()) if self.selected else 0
        self.show_rows(self.selected, note or f"{len(self.selected)} patches selected ({n_rec} recordings, "
                                              f"{flagged} flagged)" +
                       (f"; the first {self.max_tiles} shown" if len(self.selected) > self.max_tiles else ""))

    def _on_selection(self, trace, points, selector) -> None:
        self.select(points.point_inds)

    def _on_click(self, trace, points, selector) -> None:
        if points.point_inds:
            self.open(int(points.point_inds[0]))

    def open(self, i: int) -> None:
        """Open patch ``i``'s recording at its frame in the viewer (and show that patch in the grid)."""
        r = self.map.patches.iloc[int(i)]
        self.show_rows([int(i)], f"opened {r.recording} at frame {r.frame} (★{r['rank']})")
        if self.viewer is not None:
            self.viewer.show(str(r.recording), int(r.frame))

    def similar(self, patch_id: str, n: int = 8) -> pd.DataFrame:
        """The ``n`` patches nearest to ``patch_id`` in the grid (itself first) and selected on the map."""
        near = self.map.nearest(patch_id, int(n))
        pos = {pid: k for k, pid in enumerate(self.map.patches["patch_id"])}
        rows = [pos[patch_id]] + [pos[p] for p in near["patch_id"]]
        extra = {pos[p]: f"<br>distance {d:.3f}" for p, d in zip(near["patch_id"], near["distance"])}
        extra[pos[patch_id]] = "<br><b>query</b>"
        self.fig.data[0].selectedpoints = rows
        self.selected = rows
        self.show_rows(rows, f"{len(near)} patches most similar to {patch_id}", extra)
        return near


def trace_images(runs):
    """``images(row)`` for ``PatchMapView``: the JPEG of a map row's patch, from the runs' traces (the trace's kept
    patch, else cut from its recording's frame)."""
    from massviz.evaluation.patch_map import _patch_images
    from massviz.views.rerun.entities import jpeg_bytes
    from massviz.views.rerun_dataset import thumbnail

    sources = {}
    for run in runs:
        recs = list(run.recordings_of) or [None] * len(run.traces)
        for trace, rec in zip(run.traces, recs):
            sources[(run.label, trace.recording.id)] = (trace, rec)
    done: dict[str, bytes] = {}

    def images(row) -> bytes:
        if row.patch_id not in done:
            trace, rec = sources[(row.source_run, row.recording)]
            patch = _patch_images(trace, rec, [int(row.detection)]).get(int(row.detection))
            done[row.patch_id] = b"" if patch is None else jpeg_bytes(thumbnail(patch, 120), 85)
        return done[row.patch_id]

    return images


__all__ = ["COLOURINGS", "RunsTable", "PatchMapView", "colours_of", "trace_images"]
