"""The failure browser across recordings (notebook 04): a grid of the chosen patches of every recording of a dataset
with filters, tags and exclusions, and a click that opens a patch's recording at its frame in an inline Rerun viewer.

``BrowserState`` is the plain state (testable without a browser): the (recordings, patches) tables of
``massviz.evaluation.browser``, the current filters, tags and exclusions. ``FailureBrowser`` puts ipywidgets on it:
filter widgets (flagged, cue, class, track, error above x), a grid of tiles (thumbnail, recording, ★rank, d,
prediction, flag and cues; an "open" button, an "exclude" toggle and a tag box each), a label "showing n of m", the
export button (the ``massviz.exclusions/1`` file ``massviz estimate --exclude`` and ``massviz extract --exclude`` read)
and the viewer. The grid shows at most ``max_tiles`` tiles (the worst recordings first) so that a filter stays fast
on a 1,140-recording dataset.

ipywidgets and rerun's notebook viewer are imported only when a browser is built.
"""
from __future__ import annotations

import html
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from massviz.evaluation.browser import cues_of, filter_patches, patch_exclusions, tagged_rows
from massviz.evaluation.failures import save_exclusions
from massviz.views.palette import CHOSEN_HEX, FLAGGED_HEX

ANY = "any"


@dataclass
class BrowserState:
    """Tables + filters + tags (``(recording, rank)`` → text) + excluded patches (a set of ``(recording, rank)``)."""

    recordings: pd.DataFrame
    patches: pd.DataFrame
    flagged: bool | None = None
    cue: str | None = None
    cls: str | None = None
    track: int | None = None
    min_error: float | None = None
    tags: dict = field(default_factory=dict)
    excluded: set = field(default_factory=set)

    def shown(self) -> pd.DataFrame:
        return filter_patches(self.patches, self.recordings, flagged=self.flagged, cue=self.cue, cls=self.cls,
                              track=self.track, min_error=self.min_error)

    def exclusions(self):
        return patch_exclusions(tagged_rows(self.patches, self.excluded), self.tags)

    def export(self, path: str | Path) -> Path:
        return save_exclusions(path, self.exclusions())


def tile_caption(row, recordings: pd.DataFrame) -> str:
    summary = recordings.loc[row.recording] if row.recording in recordings.index else None
    err = "" if summary is None or pd.isna(summary.get("rel_error")) else f" · ε {summary['rel_error']:.2f}"
    flag = (f"<br><span style='color:{FLAGGED_HEX}'>⚑ {html.escape(str(row.cues) or 'flagged')}</span>"
            if row.flagged else "")
    return (f"<small><b>{html.escape(str(row.recording))}</b>{err}<br>★{int(row.rank)} · f{int(row.frame)} · "
            f"track {int(row.track)}<br>d={row.d_mm:.0f} mm · {row.pred_g:.1f} g</small>{flag}")


class FailureBrowser:
    """The widgets (module docstring) over a ``BrowserState``. ``images``: the dataset folder holding the
    ``thumb`` files (``patches.csv``), or a callable ``(row) -> PNG/JPEG bytes``. ``open_patch(row, viewer)``
    shows the recording of a patch row at its frame (default: ``RecordingViewer`` over the dataset folder)."""

    def __init__(self, state: BrowserState, images, *, folder: str | Path | None = None, catalog=None,
                 export_path: str | Path = "exclusions.json", max_tiles: int = 60, viewer: bool = True):
        import ipywidgets as W

        self.state, self.images, self.max_tiles = state, images, int(max_tiles)
        self.export_path = Path(export_path)
        self._bytes: dict[str, bytes] = {}
        classes = sorted(c for c in state.recordings["container_class"].dropna().unique() if c)
        self.w_flagged = W.Dropdown(options=[ANY, "flagged", "not flagged"], value=ANY, description="flag")
        self.w_cue = W.Dropdown(options=[ANY, *cues_of(state.patches)], value=ANY, description="cue")
        self.w_class = W.Dropdown(options=[ANY, *classes], value=ANY, description="class")
        self.w_track = W.Text(value="", placeholder="any", description="track")
        self.w_error = W.FloatText(value=0.0, step=0.1, description="error >")
        self.count = W.HTML()
        self.grid = W.GridBox(layout=W.Layout(grid_template_columns="repeat(auto-fill, 150px)", grid_gap="4px"))
        self.export_button = W.Button(description="export exclusions", icon="save")
        self.export_note = W.HTML()
        self.viewer = RecordingViewer(folder, catalog) if viewer else None
        for w in (self.w_flagged, self.w_cue, self.w_class, self.w_track, self.w_error):
            w.observe(self._on_filter, names="value")
        self.export_button.on_click(lambda _: self.export())
        self.last_update_s = 0.0
        parts = [W.HBox([self.w_flagged, self.w_cue, self.w_class]), W.HBox([self.w_track, self.w_error]),
                 self.count, self.grid, W.HBox([self.export_button, self.export_note])]
        if self.viewer is not None:
            parts.append(self.viewer.widget)
        self.widget = W.VBox(parts)
        self.refresh()

    # -- filters -----------------------------------------------------------------------------------------------
    def set(self, **filters) -> float:
        """Set filters (``flagged``, ``cue``, ``cls``, ``track``, ``min_error``; None = any), show them on the
        widgets, redraw the grid; returns the seconds taken."""
        t0 = time.perf_counter()
        for k, v in filters.items():
            setattr(self.state, k, v)
        self._syncing = True
        try:
            s = self.state
            self.w_flagged.value = ANY if s.flagged is None else ("flagged" if s.flagged else "not flagged")
            self.w_cue.value = s.cue if s.cue in self.w_cue.options else ANY
            self.w_class.value = s.cls if s.cls in self.w_class.options else ANY
            self.w_track.value = "" if s.track is None else str(s.track)
            self.w_error.value = 0.0 if s.min_error is None else float(s.min_error)
        finally:
            self._syncing = False
        self.refresh()
        self.last_update_s = time.perf_counter() - t0
        return self.last_update_s

    def _on_filter(self, change) -> None:
        if getattr(self, "_syncing", False):
            return
        track = self.w_track.value.strip()
        self.set(flagged=None if self.w_flagged.value == ANY else self.w_flagged.value == "flagged",
                 cue=None if self.w_cue.value == ANY else self.w_cue.value,
                 cls=None if self.w_class.value == ANY else self.w_class.value,
                 track=int(track) if track.lstrip("-").isdigit() else None,
                 min_error=self.w_error.value if self.w_error.value > 0 else None)

    # -- grid --------------------------------------------------------------------------------------------------
    def _image(self, row) -> bytes:
        key = f"{row.recording}/{int(row.rank)}"
        if key not in self._bytes:
            if callable(self.images):
                self._bytes[key] = self.images(row)
            else:
                path = Path(self.images) / str(row.thumb)
                self._bytes[key] = path.read_bytes() if path.is_file() else b""
        return self._bytes[key]

    def tile(self, row):
        import ipywidgets as W

        key = (str(row.recording), int(row.rank))
        image = W.Image(value=self._image(row), format="jpeg", layout=W.Layout(max_width="140px"))
        open_button = W.Button(description="open", tooltip=f"open {row.recording} at frame {int(row.frame)}",
                               layout=W.Layout(width="60px"))
        exclude = W.ToggleButton(value=key in self.state.excluded, description="exclude",
                                 layout=W.Layout(width="76px"))
        tag = W.Text(value=self.state.tags.get(key, ""), placeholder="tag", layout=W.Layout(width="140px"))
        open_button.on_click(lambda _, r=row: self.open(r))
        exclude.observe(lambda c, k=key: self._exclude(k, c["new"]), names="value")
        tag.observe(lambda c, k=key: self.state.tags.__setitem__(k, c["new"]), names="value")
        border = f"3px solid {FLAGGED_HEX}" if row.flagged else f"2px solid {CHOSEN_HEX}"
        box = W.VBox([image, W.HTML(tile_caption(row, self.state.recordings)), W.HBox([open_button, exclude]), tag],
                     layout=W.Layout(border=border, padding="2px"))
        box.add_class("massviz-tile")
        if row.flagged:
            box.add_class("massviz-flagged")
        return box

    def refresh(self) -> None:
        shown = self.state.shown()
        rows = list(shown.head(self.max_tiles).itertuples())
        self.grid.children = [self.tile(r) for r in rows]
        n_rec = shown["recording"].nunique()
        self.count.value = (f"<span class='massviz-count'>showing {len(rows)} of {len(shown)} patches "
                            f"({n_rec} recordings; {len(self.state.patches)} patches in all)</span>")

    def _exclude(self, key, on: bool) -> None:
        (self.state.excluded.add if on else self.state.excluded.discard)(key)

    def export(self, path: str | Path | None = None) -> Path:
        out = self.state.export(path or self.export_path)
        self.export_note.value = (f"wrote {len(self.state.exclusions())} exclusion(s) to <code>{html.escape(str(out))}"
                                  "</code> (massviz estimate / extract --exclude)")
        return out

    def open(self, row) -> None:
        if self.viewer is not None:
            self.viewer.show(str(row.recording), int(row.frame))


class RecordingViewer:
    """An inline Rerun viewer (rerun-notebook) that shows one recording of a dataset at a frame: from the catalog
    server (``catalog``: its segment URL, at the frame) or, without one, the recording's .rrd file from ``folder``
    logged into a new stream, then the time set to the frame."""

    def __init__(self, folder: str | Path | None, catalog=None, width: int = 1000, height: int = 560):
        import ipywidgets as W

        self.folder, self.catalog = (None if folder is None else Path(folder)), catalog
        self.width, self.height = width, height
        self.widget = W.VBox()  # the viewer's own widgets go in here (not through an Output capture)
        self.current: tuple[str, int] | None = None
        self._viewer = None

    def show(self, recording: str, frame: int) -> None:
        import rerun as rr

        from massviz.views.rerun.output import APPLICATION_ID, use_local_notebook_assets
        from massviz.views.rerun_dataset import rrd_name

        use_local_notebook_assets()  # before rerun_notebook is imported
        from rerun.notebook import Viewer

        self.current = (recording, frame)
        if self.catalog is not None:
            viewer = Viewer(width=self.width, height=self.height)
            viewer.open_url(self.catalog.dataset.segment_url(recording, "frame", frame))
        else:
            stream = rr.RecordingStream(APPLICATION_ID, recording_id=f"browser-{recording}-{np.random.randint(1e9)}")
            viewer = Viewer(width=self.width, height=self.height, recording=stream)
            stream.log_file_from_path(self.folder / rrd_name(recording))
            stream.flush()
        viewer.set_time_ctrl(timeline="frame", sequence=int(frame))
        # the viewer's widget (what rerun.notebook.Viewer.display() shows) in the browser's own box: it renders from
        # a button's callback too, where a cell's display() would go nowhere
        self.widget.children = [viewer._viewer]
        self._viewer = viewer


__all__ = ["BrowserState", "FailureBrowser", "RecordingViewer", "tile_caption"]
