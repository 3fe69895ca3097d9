"""Notebook widgets and the plain state objects behind them (testable without a browser).

* ``Tuner``: traces + the current threshold, K, stride and per-recording exclusions; ``update`` re-estimates every
  recording from the cached detections (``massviz.evaluation.tuning.retune``, i.e. ``Trace.reselect`` on the frames kept by the
  stride) and re-scores them (``massviz.evaluation.tuning.score_traces``). No detector or model runs.
* ``TuningPanel``: sliders for threshold, K and stride, a recording picker, the chosen patches, their predictions,
  the estimate and the CORSMAL score with its per-class table (notebook 02). Slider callbacks only set widget values
  (HTML, PNG bytes), so an update stays fast; ``last_update_s`` is the time of the last one.
* ``FailurePanel``: recordings ranked by error, the chosen patches of one with why each was chosen and whether it is
  flagged (``trace.flags`` via ``massviz.evaluation.failures.chosen_table``), a keep / exclude / exclude-track toggle
  per patch ("exclude track" excludes every detection of that patch's object track, ``detections.track``, in one
  action), the re-estimate, and an export of the exclusions to the JSON file ``massviz estimate --exclude`` reads
  (notebook 03). The ranking comes from the estimates every update computes (``Tuner.ranking``): over selection
  indexes only the recording on screen has its full trace read.

Patch tiles are outlined in the palette's chosen colour, flagged ones in its flagged colour (``massviz.views.palette``)
and numbered ★rank (0 = nearest) as in Rerun. ``TuningPanel.set`` also moves the sliders to the values it sets.

Traces come from ``massviz.process_recordings`` (the pipeline builder, cached); the widgets only read them.

ipywidgets is imported only when a panel is built.
"""
from __future__ import annotations

import dataclasses
import html
import time
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np
import pandas as pd

from massviz.core.selection import estimate_mass
from massviz.core.trace import Trace, analyse_trace
from massviz.evaluation.failures import Exclusion, chosen_table, exclusion_of, rank_by_error, save_exclusions, track_of
from massviz.evaluation.sweep import SweepTable
from massviz.evaluation.tuning import original_selection, retune, retuned_selection, score_estimates
from massviz.views.palette import CHOSEN_HEX, FLAGGED_HEX

MODES = ("keep", "exclude", "exclude track")


# ------------------------------------------------------------------------------------------------------- state
class Tuner:
    """Re-estimation state over many traces (see the module docstring).

    ``traces`` are the cached traces (any K; their detections are what counts) or their selection indexes
    (``massviz.io.cache.TraceIndex``, a few kB each: ``massviz.evaluation.tuning.index_recordings``); then only the
    recordings shown load their full trace (patches, masks; :meth:`full`, the last few kept). Every estimate of a
    slider move is one vectorised re-selection over all recordings (``massviz.evaluation.sweep.SweepTable``); the
    flags are analysed only for the recordings read from ``current``. ``ann``/``class_of``: annotation frame for
    ``score_traces`` (None: the recordings' meta.json).
    """

    #: full traces kept in memory when the tuner holds indexes (the shown recording and a few before it)
    KEEP_FULL = 4

    def __init__(self, traces: Sequence[Trace], *, k: int = 5, threshold: float | None = None, stride: int = 1,
                 ann: pd.DataFrame | None = None, class_of=None):
        self.traces = list(traces)
        self.ann, self.class_of = ann, class_of
        self.min_threshold = max((t.detect_threshold for t in self.traces), default=0.0)
        self.k, self.stride = int(k), int(stride)
        self.threshold = self.min_threshold if threshold is None else float(threshold)
        self.modes: list[dict[int, str]] = [{} for _ in self.traces]  # detection index -> "exclude" / "exclude track"
        self._table = SweepTable(self.traces, excluded=[()] * len(self.traces))  # the user's exclusions apart
        self._full: dict[int, Trace] = {}
        self.current: list[Trace] = []
        self.report = None
        self.update()

    # -- exclusions -------------------------------------------------------------------------------------------------
    def excluded(self, i: int) -> np.ndarray:
        """Detection indices of trace ``i`` excluded by the user's choices ("exclude track": every detection of
        that detection's object track, ``detections.track``)."""
        out: set[int] = set()
        for det, mode in self.modes[i].items():
            out.update(track_of(self.traces[i], det).tolist() if mode == "exclude track" else [det])
        return np.array(sorted(out), dtype=np.int64)

    def set_mode(self, i: int, detection: int, mode: str) -> None:
        """Keep / exclude / exclude-track detection ``detection`` of trace ``i``, then re-estimate trace ``i``."""
        if mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
        if mode == "keep":
            self.modes[i].pop(int(detection), None)
        else:
            self.modes[i][int(detection)] = mode
        self.current[i] = self._retune(i)
        self._estimates[i], self._chosen[i] = float(self.current[i].estimate), len(self.current[i].selection)
        self.report = self._score()

    def exclusions(self) -> list[Exclusion]:
        """Every excluded detection as a file entry (recording id, frame, box)."""
        return [exclusion_of(t, int(d), note=self._note(i, int(d)))
                for i, t in enumerate(self.traces) for d in self.excluded(i)]

    def _note(self, i: int, det: int) -> str:
        return "excluded" if det in self.modes[i] else "excluded with its track"

    def export(self, path: str | Path) -> Path:
        """Write the exclusions JSON (``massviz.evaluation.failures`` format) for ``massviz estimate --exclude``."""
        return save_exclusions(path, self.exclusions())

    # -- re-estimation ----------------------------------------------------------------------------------------------
    def update(self, *, k: int | None = None, threshold: float | None = None, stride: int | None = None) -> None:
        """Set any of K, threshold, stride and re-estimate every recording and the score."""
        if k is not None:
            self.k = int(k)
        if threshold is not None:
            self.threshold = float(threshold)
        if stride is not None:
            self.stride = int(stride)
        self.current = _LazyTraces(self._retune, len(self.traces))  # made when read: the shown ones
        estimates = self._table.estimates(self.threshold, self.k, self.stride).tolist()
        chosen = self._table.chosen(self.threshold, self.k, self.stride).tolist()
        for i, modes in enumerate(self.modes):  # recordings with exclusions: one by one
            if modes:
                estimates[i], chosen[i] = self._light_retune(i)
        self._estimates, self._chosen = estimates, chosen
        self.report = self._score()

    def _light_retune(self, i: int) -> tuple[float, int]:
        """(estimate, number of chosen patches) of recording ``i`` with its exclusions, from its detections' columns
        (an index is enough: no full trace read, no flags analysis)."""
        sel = retuned_selection(self.traces[i], k=self.k, threshold=self.threshold, stride=self.stride,
                                exclude=self.excluded(i))
        return estimate_mass(self.traces[i].detections.pred, sel), len(sel)

    def ranking(self) -> pd.DataFrame:
        """Recordings ranked by error, worst first (``massviz.evaluation.failures.rank_by_error`` of ``current``),
        from the estimates every update computes: no full trace read."""
        return rank_by_error(self.traces, self._estimates, self._chosen)

    def full(self, i: int) -> Trace:
        """The full trace of recording ``i`` (read from the cache when the tuner holds its index)."""
        t = self.traces[i]
        if isinstance(t, Trace):
            return t
        if i not in self._full:
            _keep_last(self._full, i, t.full_trace, self.KEEP_FULL)
        return self._full[i]

    def _retune(self, i: int) -> Trace:
        return retune(self.full(i), k=self.k, threshold=self.threshold, stride=self.stride,
                      exclude=self.excluded(i))

    def _score(self):
        try:
            return score_estimates(self.traces, self._estimates, self.ann, self.class_of)
        except Exception:  # noqa: BLE001 - recordings without ground truth: no score, the rest still works
            return None

    def selection(self, i: int) -> np.ndarray:
        """Chosen patches of recording ``i`` as indices into ``traces[i].detections``, nearest first."""
        return original_selection(self.full(i), self.current[i], self.stride)

    def estimates(self) -> dict[str, float]:
        return {t.recording.id: e for t, e in zip(self.traces, self._estimates)}

    def patch_table(self, i: int) -> pd.DataFrame:
        """The chosen patches of recording ``i``: rank, detection, frame, class, score, a, b, d_mm, pred_g."""
        full = self.full(i)
        memo = self.__dict__.setdefault("_tables", {})  # {i: (full trace, its table)}: one table per trace read
        if i not in memo or memo[i][0] is not full:
            _keep_last(memo, i, lambda: (full, full.table()), self.KEEP_FULL)  # no more traces than ``full`` keeps
        t = memo[i][1]
        sel = self.selection(i)
        out = t.iloc[sel][["frame", "class", "score", "a", "b", "d_mm", "pred_g"]].copy()
        out.insert(0, "detection", sel)
        out.insert(0, "rank", np.arange(len(sel)))
        return out.reset_index(drop=True)


def _keep_last(items: dict, key, make, n: int) -> None:
    """``items[key] = make()``, first dropping the oldest entries (before ``make`` runs: the memory they hold goes
    first) so that at most ``n`` are kept."""
    items.pop(key, None)
    while len(items) >= n:
        items.pop(next(iter(items)))
    items[key] = make()


class _LazyTraces(Sequence):
    """``Tuner.current``: the re-tuned trace of each recording, made on first read (``make(i)``) and kept. A slider
    change makes only the shown recording's (its flags analysis is what costs); every estimate is computed at once
    without it (``retuned_estimate``)."""

    def __init__(self, make, n: int):
        self._make, self._items = make, [None] * n

    def __len__(self) -> int:
        return len(self._items)

    def __getitem__(self, i):
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(len(self)))]
        if self._items[i] is None:
            self._items[i] = self._make(range(len(self))[i])
        return self._items[i]

    def __setitem__(self, i, trace) -> None:
        self._items[i] = trace


# ------------------------------------------------------------------------------------------------------- views
class PatchImages:
    """PNG bytes of detection patches, cached, taken from the trace (it keeps the RGB patches of its ``KEEP_PATCHES``
    nearest detections, more than any K a slider offers); a patch the trace did not keep is a grey tile: the panel
    never reads the recording (a video decode or a RealSense replay up to that frame, per patch)."""

    def __init__(self):
        self._png: dict[tuple[int, int], bytes] = {}

    def patch(self, trace: Trace, i: int) -> np.ndarray | None:
        return trace.detections.patches[i]

    def png(self, trace: Trace, i: int, height: int = 96) -> bytes:
        key = (id(trace), int(i))
        if key not in self._png:
            p = self.patch(trace, int(i))
            if p is None or p.size == 0:
                p = np.full((height, height, 3), 200, np.uint8)
            scale = height / p.shape[0]
            p = cv2.resize(p, (max(1, int(round(p.shape[1] * scale))), height), interpolation=cv2.INTER_AREA)
            self._png[key] = cv2.imencode(".png", cv2.cvtColor(p, cv2.COLOR_RGB2BGR))[1].tobytes()
        return self._png[key]


def _table_html(df: pd.DataFrame, floatfmt: str = "{:.2f}") -> str:
    return df.to_html(index=False, float_format=floatfmt.format, border=0, na_rep="-", escape=True)


def score_html(report) -> str:
    """Overall CORSMAL score and the per-class table as HTML ('no ground truth' without a report)."""
    if report is None:
        return "<i>no ground truth for these recordings: no score</i>"
    eps = "-" if np.isnan(report.mean_eps) else f"{report.mean_eps:.3f}"
    head = (f"<b>CORSMAL score {report.score_pct:.2f} %</b> over {report.n_recordings} recordings "
            f"({report.n_estimated} estimated), mean ε {eps}")
    table = report.per_class.reset_index().rename(columns={"score_pct": "score %", "mean_eps": "mean ε"})
    return head + _table_html(table)


def estimate_html(trace: Trace) -> str:
    gt = trace.ground_truth_mass
    est = "not estimated" if trace.estimate < 0 else f"{trace.estimate:.1f} g"
    text = f"<b>{html.escape(trace.recording.id)}</b>: estimate <b>{est}</b>"
    if gt is not None:
        text += f" · ground truth {gt:.1f} g"
        if trace.estimate >= 0:
            text += f" · ε = {abs(trace.estimate - gt) / gt:.3f}"
    return text + f" · K={trace.k}, threshold {trace.threshold:.2f}, stride {trace.stride}"


def _tile_border(flagged: bool, chosen: bool = True) -> str:
    """CSS border of a patch tile: the palette's flagged or chosen colour (the same as in Rerun, Open3D, figures)."""
    return f"3px solid {FLAGGED_HEX}" if flagged else (f"2px solid {CHOSEN_HEX}" if chosen else "2px dashed #999")


def _flag_caption(flag) -> str:
    if not flag.flagged:
        return ""
    what = f"not the container: {flag.ground_truth}" if flag.ground_truth else ", ".join(flag.cue_kinds)
    return f"<br><small style='color:{FLAGGED_HEX}'>⚑ flagged ({html.escape(what)})</small>"


class TuningPanel:
    """Sliders (threshold, K, stride) + recording picker → chosen patches, predictions, estimate, score."""

    def __init__(self, tuner: Tuner, recording: int = 0, max_k: int = 32, max_stride: int = 12):
        import ipywidgets as W

        self.tuner, self.images, self.i = tuner, PatchImages(), int(recording)
        self.threshold = W.FloatSlider(value=tuner.threshold, min=tuner.min_threshold, max=0.99, step=0.01,
                                       description="threshold", continuous_update=False, readout_format=".2f")
        self.k = W.IntSlider(value=tuner.k, min=1, max=max_k, description="K", continuous_update=False)
        self.stride = W.IntSlider(value=tuner.stride, min=1, max=max_stride, description="stride",
                                  continuous_update=False)
        self.recording = W.Dropdown(options=[(t.recording.id, j) for j, t in enumerate(tuner.traces)],
                                    value=self.i, description="recording")
        self.estimate = W.HTML()
        self.patches = W.HBox(layout=W.Layout(flex_flow="row wrap"))
        self.predictions = W.HTML()
        self.score = W.HTML()
        self.timing = W.HTML()
        for w in (self.threshold, self.k, self.stride):
            w.observe(self._on_slider, names="value")
        self.recording.observe(self._on_recording, names="value")
        self.widget = W.VBox([W.HBox([self.threshold, self.k, self.stride]), self.recording, self.estimate,
                              self.patches, self.predictions, W.HTML("<b>Over all recordings</b>"), self.score,
                              self.timing])
        self.last_update_s = 0.0
        self.refresh()

    def set(self, *, threshold: float | None = None, k: int | None = None, stride: int | None = None) -> float:
        """What a slider change does (also for tests, and from code: the sliders then show the new values):
        re-estimate, refresh the views; returns the seconds taken."""
        t0 = time.perf_counter()
        self.tuner.update(k=k, threshold=threshold, stride=stride)
        self._sync_sliders()
        self.refresh()
        self.last_update_s = time.perf_counter() - t0
        self.timing.value = f"<small>updated in {1000 * self.last_update_s:.0f} ms</small>"
        return self.last_update_s

    def _sync_sliders(self) -> None:
        """Show the tuner's state on the sliders without their callbacks re-estimating again."""
        self._syncing = True
        try:
            self.threshold.value, self.k.value, self.stride.value = self.tuner.threshold, self.tuner.k, self.tuner.stride
        finally:
            self._syncing = False

    def _on_slider(self, change) -> None:
        if getattr(self, "_syncing", False):
            return
        self.set(threshold=self.threshold.value, k=self.k.value, stride=self.stride.value)

    def _on_recording(self, change) -> None:
        self.i = int(change["new"])
        self.refresh()

    def png(self, i: int, detection: int) -> bytes:
        """PNG of patch ``detection`` of recording ``i`` (its full trace read when the tuner holds its index)."""
        trace = self.tuner.full(i)
        # PatchImages keys PNGs by id(trace): hold the traces whose PNGs are kept (so no id is reused meanwhile),
        # the last few only, dropping the PNGs of a trace let go
        owners = self.__dict__.setdefault("_png_owners", {})
        owners[id(trace)] = owners.pop(id(trace), trace)
        while len(owners) > Tuner.KEEP_FULL + 1:
            gone = next(iter(owners))
            owners.pop(gone)
            self.images._png = {key: v for key, v in self.images._png.items() if key[0] != gone}
        return self.images.png(trace, int(detection))

    #: tiles made beyond the ones shown, hidden, so that K + 1 (up to this many more) only shows one: a new widget
    #: is a round trip to the page and a new view to lay out, most of a slider move's time in the browser
    SPARE_TILES = 4

    def tiles(self, i: int, indices: Sequence[int], captions: Sequence[str]):
        """Every tile made so far (image, caption), the first ``len(indices)`` showing the chosen patches and the
        rest hidden. Tiles are kept and only their values change from one update to the next (also when K grows
        within the spares: the tile is shown, not made); a value that did not change is not sent again."""
        import ipywidgets as W

        flagged = {p.rank for p in self.tuner.current[i].flags.flagged}
        pool = self.__dict__.setdefault("_tile_pool", [])
        if len(pool) < len(indices):
            while len(pool) < len(indices) + self.SPARE_TILES:
                image, caption = W.Image(format="png"), W.HTML()
                box = W.VBox([image, caption], layout=W.Layout(margin="2px 6px", display="none"))
                pool.append((box, image, caption))
        for r, (box, image, caption) in enumerate(pool):
            if r >= len(indices):
                if box.layout.display != "none":
                    box.layout.display = "none"
                continue
            png, border = self.png(i, indices[r]), _tile_border(r in flagged)
            if image.value != png:
                image.value = png
            if caption.value != captions[r]:
                caption.value = captions[r]
            if box.layout.border != border:
                box.layout.border = border
            if box.layout.display is not None:
                box.layout.display = None
        return [box for box, _, _ in pool]

    def shown_tiles(self) -> list:
        """The tiles the page shows (the chosen patches, in rank order); ``patches.children`` also holds the spares."""
        return [box for box in self.patches.children if box.layout.display != "none"]

    def refresh(self) -> None:
        i, tuner = self.i, self.tuner
        cur = tuner.current[i]
        self.estimate.value = estimate_html(cur)
        table = tuner.patch_table(i)
        flags = cur.flags.patches
        captions = [f"<small>★{r.rank} · f{r.frame} · track {flags[r.rank].track}<br>d={r.d_mm:.0f} mm<br>"
                    f"{r.pred_g:.1f} g</small>" + _flag_caption(flags[r.rank]) for r in table.itertuples()]
        self.patches.children = self.tiles(i, table["detection"].tolist(), captions)
        self.predictions.value = _table_html(table)
        self.score.value = self._score_html(tuner.report)

    def _score_html(self, report) -> str:
        """``score_html`` of ``report``, made again only when the report changed (not on a recording switch)."""
        if getattr(self, "_scored", (None, ""))[0] is not report or report is None:
            self._scored = (report, score_html(report))
        return self._scored[1]


class FailurePanel(TuningPanel):
    """Recordings ranked by error; per recording the chosen patches with why they were chosen, flags, and a
    keep / exclude / exclude-track toggle each; the re-estimate; export of the exclusions."""

    #: rows of the ranking table shown (the worst); the recording picker lists every recording in that order
    RANKING_ROWS = 25

    def __init__(self, tuner: Tuner, recording: int | None = None, export_path: str | Path = "exclusions.json"):
        import ipywidgets as W

        self.ranking_html = W.HTML()
        self.rows = W.VBox()
        self.path = W.Text(value=str(export_path), description="export to")
        self.export_button = W.Button(description="export exclusions", icon="download",
                                      layout=W.Layout(width="auto"))  # its whole label, not "export exclusi…"
        self.export_status = W.HTML()
        self.export_button.on_click(lambda _: self.export())
        self.toggles: dict[int, object] = {}
        ranking = tuner.ranking()
        first = int(ranking["position"].iloc[0]) if len(ranking) else 0
        super().__init__(tuner, recording=first if recording is None else recording)
        order = list(ranking["position"]) + [j for j in range(len(tuner.traces)) if j not in set(ranking["position"])]
        self.recording.options = [(f"{j + 1}. {tuner.traces[p].recording.id}", p)
                                  for j, p in enumerate(order)]
        self.recording.value = self.i
        self.widget = W.VBox([self.ranking_html, W.HBox([self.threshold, self.k, self.stride]), self.recording,
                              self.estimate, self.rows, W.HTML("<b>Over all recordings</b>"), self.score,
                              W.HBox([self.path, self.export_button]), self.export_status])
        self.refresh()

    def table(self, i: int | None = None) -> pd.DataFrame:
        """``chosen_table`` of recording ``i`` (default: the shown one) with detection indices of the cached trace
        and the user's mode per patch."""
        i = self.i if i is None else int(i)
        cur = self.tuner.current[i]
        table = chosen_table(cur)
        full = self.tuner.full(i)
        if len(table):
            table["detection"] = original_selection(full, cur, self.tuner.stride)
        excluded = list(self.tuner.modes[i])
        none = analyse_trace(dataclasses.replace(full, selection=np.zeros(0, dtype=np.int64), flags=None))
        extra = chosen_table(none, extra=excluded).assign(why="not chosen while excluded")
        out = pd.concat([table, extra], ignore_index=True) if len(extra) else table
        out["mode"] = [self.tuner.modes[i].get(int(d), "keep") for d in out["detection"]]
        return out

    def set_mode(self, detection: int, mode: str, i: int | None = None) -> None:
        """What a toggle does (also for tests): keep / exclude / exclude track, re-estimate, refresh."""
        self.tuner.set_mode(self.i if i is None else int(i), int(detection), mode)
        self.refresh()

    def export(self, path: str | Path | None = None) -> Path:
        """Write the exclusions file; returns its absolute path (the one the status line and
        ``massviz estimate --exclude`` need, wherever the kernel's working folder is)."""
        out = Path(self.tuner.export(path or self.path.value)).resolve()
        n = len(self.tuner.exclusions())
        self.export_status.value = (f"wrote {n} exclusions to <code>{html.escape(str(out))}</code> "
                                    f"(<code>massviz estimate --exclude {html.escape(str(out))}</code>)")
        return out

    def refresh(self) -> None:
        if not hasattr(self, "rows"):
            return
        import ipywidgets as W

        i, tuner = self.i, self.tuner
        ranking = tuner.ranking()
        more = len(ranking) - self.RANKING_ROWS
        self.ranking_html.value = ("<b>Recordings ranked by error (worst first)</b>"
                                   + _table_html(ranking.head(self.RANKING_ROWS), "{:.3f}")
                                   + (f"<small>… and {more} more (the recording picker lists them all, in this "
                                      "order when the panel was made)</small>" if more > 0 else ""))
        self.estimate.value = estimate_html(tuner.current[i])
        self.score.value = self._score_html(tuner.report)
        table = self.table(i)
        rows = []
        self.toggles = {}
        for r in table.itertuples():
            if r.rank < 0:  # excluded by the user: listed with its toggle so that "keep" undoes it
                n_track = len(track_of(tuner.traces[i], int(r.detection))) if r.mode == "exclude track" else 1
                what = f"with its whole track {r.track} ({n_track} detections)" if r.mode == "exclude track" else \
                    "this detection only"
                flag = (f"<span class='massviz-excluded' style='color:#666'>⊘ excluded by you ({what}); "
                        f"set keep to restore it</span>")
            elif r.flagged:
                flag = f"<span style='color:{FLAGGED_HEX}'>⚑ flagged ({r.severity}): {html.escape(r.flag_reason)}</span>"
            else:
                flag = "<span style='color:#080'>not flagged</span>"
            cues = f"<br><small>cues: {html.escape(r.cues)}</small>" if r.cues and not r.flagged else ""
            rank = f"★{r.rank}" if r.rank >= 0 else "excluded"
            text = (f"<b>{rank}</b> · frame {r.frame} · track {r.track} · d={r.d_mm:.0f} mm · score {r.score:.2f} · "
                    f"a={r.a:.2f} b={r.b:.2f} · pred {r.pred_g:.1f} g"
                    f"<br><small>{html.escape(r.why)}</small><br>{flag}{cues}")
            # buttons as wide as their labels ("exclude track" must not be cut to "exclude …")
            toggle = W.ToggleButtons(options=list(MODES), value=r.mode, style={"button_width": "auto"})
            toggle.observe(lambda ch, d=int(r.detection): self.set_mode(d, ch["new"]), names="value")
            self.toggles[int(r.detection)] = toggle
            img = W.Image(value=self.png(i, int(r.detection)), format="png",
                          layout=W.Layout(border=_tile_border(bool(r.flagged), r.rank >= 0)))
            rows.append(W.HBox([img, W.VBox([W.HTML(text), toggle])], layout=W.Layout(margin="4px 0")))
        self.rows.children = rows


__all__ = ["Tuner", "TuningPanel", "FailurePanel", "PatchImages",
           "score_html", "estimate_html", "MODES"]
