"""The viewer's layout, read back from the .rrd ``massviz log`` writes: the 2D views fit
the whole image, the predictions legend is not drawn over the plot, tiles are titled "★rank" (and "⚑ flagged"), the
3D view starts oblique (yaw 25°, pitch 15°) with the camera's frustum in view, and scrubbing back shows in each tile
the patch holding that rank at that frame (never "No data available" once the rank is held). The browser test
(tests/test_browser.py) checks what a person sees of the same layout."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from fakes import DistanceModel
from massviz.core.pipeline import run
from massviz.detect import make_detector
from massviz.io.recording import open_recording
from massviz.views.rerun import log_trace_with_clouds
from rrd_reader import rrd_rows

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def logged(tmp_path_factory):
    rec = open_recording(ROOT / "data_samples" / "cup_handover")
    trace = run(rec, make_detector("depth"), DistanceModel(), k=4, stride=2)
    out = tmp_path_factory.mktemp("layout") / "cup.rrd"
    log_trace_with_clouds(trace, rec, rrd=out)
    return rec, trace, out


def blueprint_rows(path: Path) -> dict[str, dict]:
    """Entity path -> {component: value} of the .rrd's blueprint."""
    from rerun.chunk import RrdReader

    reader = RrdReader(path)
    (blueprint,) = reader.blueprints()
    out: dict[str, dict] = {}
    for chunk in reader.store(store=blueprint).stream():
        batch = chunk.to_record_batch()
        for c, name in enumerate(batch.schema.names):
            if ":" in name:
                value = batch.column(c)[batch.num_rows - 1].as_py()
                if value is not None:
                    out.setdefault(chunk.entity_path, {})[name] = value[0] if isinstance(value, list) else value
    return out


def test_layout_fits_the_image_hides_the_legend_and_names_the_tiles(logged):
    rec, trace, out = logged
    rows = blueprint_rows(out)
    names = {p: r["ViewBlueprint:display_name"] for p, r in rows.items() if "ViewBlueprint:display_name" in r}
    flagged = {p.rank for p in trace.flags.flagged}
    assert flagged  # cup_handover's pitcher patches: the ⚑ titles are exercised
    tiles = sorted(n for n in names.values() if n.startswith("★"))
    assert tiles == sorted(f"★{r}" + (" ⚑ flagged" if r in flagged else "") for r in range(len(trace.selection)))
    by_name = {n: p for p, n in names.items()}
    for view in ("RGB · detections · masks", "Depth"):
        bounds = rows[by_name[view] + "/VisualBounds2D"]["VisualBounds2D:range"]
        assert bounds == {"x_range": [0.0, float(rec.width)], "y_range": [0.0, float(rec.height)]}
    (plot,) = [p for n, p in by_name.items() if n.startswith("Predictions")]
    assert rows[plot + "/PlotLegend"]["PlotLegend:visible"] is False


def test_3d_view_starts_oblique_with_the_frustum_in_view(logged):
    rec, trace, out = logged
    rows = blueprint_rows(out)
    (view,) = [p for p, r in rows.items() if r.get("ViewBlueprint:display_name", "").startswith("3D")]
    eye = rows[view + "/EyeControls3D"]
    position, target = np.array(eye["EyeControls3D:position"]), np.array(eye["EyeControls3D:look_target"])
    assert target[2] > 0.1  # in front of the camera: the nearest chosen patch
    offset = (position - target) / np.linalg.norm(position - target)
    assert math.degrees(math.asin(-offset[1])) == pytest.approx(15.0, abs=0.5)  # pitch: from above (y is down)
    assert math.degrees(math.atan2(offset[0], -offset[2])) == pytest.approx(25.0, abs=0.5)  # yaw: from the right
    to_target = (target - position) / np.linalg.norm(target - position)
    to_camera = -position / np.linalg.norm(position)
    assert math.degrees(math.acos(float(to_target @ to_camera))) < 25.0  # the frustum at the origin is in view


def test_scrubbing_back_shows_the_patch_chosen_so_far(logged):
    rec, trace, out = logged
    frames = [int(f) for f in trace.frames]
    tiles = {r: rrd_rows(out, f"/patches/{r}") for r in range(trace.k)}
    for f, selection in zip(frames, trace.running_selections(), strict=False):
        for r in range(trace.k):
            state = None
            for row in tiles[r]:
                if row["time"] is not None and row["time"] <= f:
                    state = row if "d_mm" in row else None
            if r < len(selection):
                i = int(selection[r])
                assert state is not None, f"tile ★{r} shows no data at frame {f}"
                assert state["d_mm"] == [pytest.approx(float(trace.detections.d[i]), abs=0.01)]
            else:
                assert state is None
