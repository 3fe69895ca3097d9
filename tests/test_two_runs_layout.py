"""Two runs of one recording in one Rerun recording are told apart: each run its own colour and legend name in the
predictions plot, each patch tile captioned and titled with its run."""
from __future__ import annotations

import rerun.blueprint as rrb

from massviz.views.palette import FLAGGED_COLOUR, rgb255
from massviz.views.rerun_runs import B_ROOT, RUN_COLOURS, two_runs_blueprint, write_two_runs
from rrd_reader import rrd_rows


def packed(rgb) -> int:
    """Rerun's 0xRRGGBBAA colour of an opaque RGB."""
    r, g, b = rgb
    return (r << 24) | (g << 16) | (b << 8) | 0xFF


def last_static(path, entity) -> dict:
    """The components of ``entity``'s static rows, the later winning (what the viewer shows)."""
    merged: dict = {}
    for row in rrd_rows(path, entity):
        if row["time"] is None:
            merged.update(row)
    return merged


def test_each_run_has_its_colour_and_name_in_the_plot_and_on_every_tile(sample_traces, samples_dir, tmp_path):
    from massviz.io.recording import open_recording

    cup = next(t for t in sample_traces if t.recording.id == "cup_handover")
    pitcher = [int(p.detection) for p in cup.flags.flagged]
    other = cup.reselect(exclude=pitcher)
    labels = ("detector=depth", "no pitcher")
    path = write_two_runs(cup, other, open_recording(samples_dir / "cup_handover"), tmp_path,
                          {"id": "cup_handover"}, labels)
    for side, root, trace in (("A", "", cup), ("B", B_ROOT, other)):
        series = last_static(path, f"{root}/predictions/running_estimate")
        assert series["SeriesLines:names"] == [f"{side}: {labels['AB'.index(side)]}"]
        assert series["SeriesLines:colors"] == [packed(RUN_COLOURS[side])]
        flagged = {int(p.detection) for p in trace.flags.flagged}
        for rank, i in enumerate(trace.selection):
            outline = last_static(path, f"{root}/patches/{rank}/outline")
            assert outline["Boxes2D:labels"][0].startswith(f"{side} ★{rank}")
            colour = rgb255(FLAGGED_COLOUR) if int(i) in flagged else RUN_COLOURS[side]
            assert outline["Boxes2D:colors"] == [packed(colour)]
    assert RUN_COLOURS["A"] != RUN_COLOURS["B"]


def views(container):
    for child in getattr(container, "contents", []):
        if isinstance(child, (rrb.Container, rrb.Horizontal, rrb.Vertical, rrb.Grid, rrb.Tabs)):
            yield from views(child)
        else:
            yield child


def test_the_plot_holds_one_series_a_run_and_a_legend_and_tiles_name_their_run():
    bp = two_runs_blueprint(5, 3, ("k=5", "k=3"), flagged_a={0, 1}, flagged_b=())
    shown = list(views(bp.root_container))
    (plot,) = [v for v in shown if isinstance(v, rrb.TimeSeriesView)]
    assert list(plot.contents) == ["/predictions/running_estimate", f"{B_ROOT}/predictions/running_estimate",
                                   "/predictions/ground_truth"]
    tiles = [v.name for v in shown if isinstance(v, rrb.Spatial2DView) and "/patches/" in str(v.origin)]
    assert tiles == ["A ★0 ⚑ flagged", "A ★1 ⚑ flagged", "A ★2", "A ★3", "A ★4", "B ★0", "B ★1", "B ★2"]
    assert plot.properties["PlotLegend"].visible.as_arrow_array().to_pylist() == [True]
