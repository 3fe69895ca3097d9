"""What a new user hit (issue 22): the figures' colours and labels (item 5) and the command line's messages (item 9).

The command-line tests run ``python -m massviz`` as a user would and check the exit code, the one error line and that
nothing was written.
"""
from __future__ import annotations

import itertools
import json
import os
import subprocess
import sys
from pathlib import Path

import nbformat
import numpy as np
import pytest
from sample_traces import WEIGHTS, sample_cache

ROOT = Path(__file__).resolve().parents[1]


# ------------------------------------------------------------------------------------------ item 5: the figures
@pytest.fixture(scope="module")
def cup(tmp_path_factory, shared_dir, samples_dir):
    from massviz.app import process_recordings
    from massviz.io.recording import open_recording

    cache = sample_cache(tmp_path_factory, shared_dir, samples_dir)
    rec = open_recording(samples_dir / "cup_handover")
    [trace] = process_recordings([rec], detector="depth", weights=str(shared_dir / WEIGHTS), cache=str(cache),
                                 threshold=0.4, quiet=True)
    return rec, trace


def _scatter_colours(fig) -> np.ndarray:
    [ax] = fig.axes
    [points] = ax.collections
    return np.asarray(points.get_facecolors())[:, :3]


def _count(colours: np.ndarray, colour) -> int:
    return int((np.abs(colours - np.asarray(colour)) < 1e-3).all(axis=1).sum())


def test_point_cloud_figure_colours_by_the_palette(cup):
    """A chosen patch's mask in the chosen colour, a flagged one in the flagged colour (not magenta as well)."""
    from massviz.views import plots
    from massviz.views.palette import CHOSEN_COLOUR, FLAGGED_COLOUR

    rec, trace = cup
    flagged = {p.detection for p in trace.flags.flagged}
    assert flagged, "the cup_handover sample should have flagged patches (the pitcher)"
    frames = {int(trace.detections.frame[i]): [] for i in trace.selection}
    for i in trace.selection:
        frames[int(trace.detections.frame[i])].append(int(i) in flagged)
    only_flagged = next(f for f, fl in frames.items() if all(fl))
    only_chosen = next(f for f, fl in frames.items() if not any(fl))
    for frame_index, flagged_there in ((only_flagged, True), (only_chosen, False)):
        fig = plots.point_cloud_figure(trace, rec.read_frame(frame_index), rec.intrinsics)
        colours = _scatter_colours(fig)
        red, magenta = _count(colours, FLAGGED_COLOUR), _count(colours, CHOSEN_COLOUR)
        if flagged_there:
            assert red > 50 and magenta == 0, (frame_index, red, magenta)
        else:
            assert magenta > 50 and red == 0, (frame_index, red, magenta)
        assert "flagged in red" in fig.axes[0].get_title()


def _overlap(a, b) -> bool:
    return a.x0 < b.x1 and b.x0 < a.x1 and a.y0 < b.y1 and b.y0 < a.y1


def test_point_cloud_figure_labels_do_not_overlap(cup):
    from massviz.views import plots

    rec, trace = cup
    fig = plots.point_cloud_figure(trace, rec.read_frame(plots.best_frame(trace)), rec.intrinsics)
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    renderer = canvas.get_renderer()
    [ax] = fig.axes
    for axis in (ax.xaxis, ax.yaxis, ax.zaxis):
        ticks = [t.get_window_extent(renderer) for t in axis.get_ticklabels() if t.get_visible() and t.get_text()]
        assert len(ticks) >= 2
        for a, b in itertools.combinations(ticks, 2):
            assert not _overlap(a, b), f"{axis.axis_name} tick labels overlap"
        label = axis.label.get_window_extent(renderer)
        assert not any(_overlap(label, t) for t in ticks), f"{axis.axis_name} label overlaps its tick labels"


def test_notebook_01_names_the_palette_colours():
    text = "\n".join(c.source for c in nbformat.read(ROOT / "notebooks" / "01_inspect_recording.ipynb", 4).cells
                     if c.cell_type == "markdown")
    assert "yellow" not in text
    cloud = text[text.index("## The depth as a point cloud"):]
    assert "magenta" in cloud.split("##")[1] and "red" in cloud.split("##")[1]
