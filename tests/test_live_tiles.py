"""Issue 22 item 1: live patch tiles follow the K nearest. A live session from a paced .db3 of ``cup_handover``
(``massviz live --file X.db3 --detector depth --rrd live.rrd``, run in-process as the command runs it) is read back
from its .rrd: at every processed frame, tile ``/patches/<rank>`` shows the detection holding that rank in the
running selection then (the trace's ``running_selections``), and the last value of each tile is the final
selection; no rank of the final selection is without data."""
from __future__ import annotations

import numpy as np
import pytest

from massviz.io.recording import open_recording
from massviz.views.rerun.rrd_reader import rrd_rows
from test_live import depth_detector, played, played_db3, rs, session_args  # noqa: F401 - fixtures
from test_live import pipeline as live_pipeline


def tile_at(rows: list[dict], time: int) -> dict | None:
    """The latest row of a tile at ``time`` (None: no data, or cleared)."""
    state = None
    for row in rows:
        if row["time"] is None or row["time"] > time:
            continue
        state = None if "clear" in row and "d_mm" not in row else row
    return state


@pytest.mark.slow
def test_live_tiles_show_the_current_k_nearest(rs, played_db3, depth_detector, tmp_path):
    from massviz.commands.live import run_session
    from massviz.io.realsense import open_file_stream

    p = live_pipeline(depth_detector, tmp_path)
    args = session_args(file=str(played_db3), rrd=str(tmp_path / "live.rrd"), save=str(tmp_path / "rec"))
    assert run_session(args, p, open_file_stream(played_db3), "played") == 0
    saved = open_recording(tmp_path / "rec")
    trace = p.cache.load(saved, {"name": depth_detector.name, **depth_detector.settings()}, 1, 0.4)
    assert trace is not None
    running = trace.running_selections()
    numbers = range(len(running))  # the live .rrd's frame timeline: index of the processed frame
    assert saved.meta["live"]["processed"] == len(running) == len(trace.frames)
    k_final = len(trace.selection)
    assert k_final >= 2  # the recording has more than one patch to hold, so ranks can change
    tiles = {r: rrd_rows(tmp_path / "live.rrd", f"/patches/{r}") for r in range(trace.k)}
    changes = 0
    for number, selection in zip(numbers, running):
        for r in range(trace.k):
            state = tile_at(tiles[r], number)
            if r >= len(selection):
                assert state is None, (number, r)
                continue
            i = int(selection[r])
            assert state is not None, f"tile {r} has no data at frame {number}"
            assert state["d_mm"] == [pytest.approx(float(trace.detections.d[i]), abs=0.01)]
            assert state["score"] == [pytest.approx(float(trace.detections.score[i]), abs=1e-6)]
        changes += 1
    assert changes == len(numbers)
    # each rank of the final selection holds data, and its last value is the final occupant
    for r, i in enumerate(trace.selection):
        rows = [row for row in tiles[r] if "d_mm" in row]
        assert rows, f"/patches/{r} was never logged"
        assert rows[-1]["d_mm"] == [pytest.approx(float(trace.detections.d[int(i)]), abs=0.01)]
    # the ranks did change during the session (else this test would prove nothing about stale tiles)
    assert any(not np.array_equal(a[: len(b)], b[: len(a)]) for a, b in zip(running, running[1:]))
