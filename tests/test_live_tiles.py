"""Live patch tiles follow the K nearest. A live session from a paced .db3 of ``cup_handover``
(``massviz live --file X.db3 --detector depth --rrd live.rrd``, run in-process as the command runs it) is read back
from its .rrd: at every processed frame, tile ``/patches/<rank>`` shows the detection holding that rank in the
running selection then (the trace's ``running_selections``), and the last value of each tile is the final
selection; no rank of the final selection is without data. At the end the tiles of flagged patches carry their
flags and the command prints the flag warning, as ``massviz log`` does."""
from __future__ import annotations

import numpy as np
import pytest

from fakes import flagged_session, live_pipeline, session_args
from massviz.io.recording import open_recording
from rrd_reader import rrd_rows


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
    from massviz.io.formats.realsense_live import open_file_stream

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
    for number, selection in zip(numbers, running, strict=False):
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
    assert any(not np.array_equal(a[: len(b)], b[: len(a)]) for a, b in zip(running, running[1:], strict=False))



@pytest.mark.slow
def test_live_tiles_and_the_last_lines_carry_the_flags(rs, played_db3, tmp_path, capsys):
    """A chosen patch the flags doubt (here a box cut by the image's bottom edge: the ``border`` cue, whatever its
    track) is marked in the live session as ``massviz log`` marks it: its tile, at the last frame, is flagged (the
    outline's label says why), ``/log`` has the flag warnings and the command prints the warning line."""
    flagged_session(played_db3, tmp_path)
    err = capsys.readouterr().err
    warnings = [line for line in err.splitlines() if line.startswith("massviz live: warning: played: ")]
    assert len(warnings) == 1 and "1 of 5 chosen patches looks like another object" in warnings[0], err
    tile = [row for row in rrd_rows(tmp_path / "live.rrd", "/patches/0") if "d_mm" in row]
    assert tile[-1]["flagged"] == [True] and "border" in tile[-1]["flag"][0], tile[-1]
    assert tile[-1]["d_mm"][0] < 900  # the box on the table's edge, the nearest
    outline = [row for row in rrd_rows(tmp_path / "live.rrd", "/patches/0/outline") if "Boxes2D:labels" in row]
    assert outline[-1]["Boxes2D:labels"][0].startswith("★0 ⚑ flagged"), outline[-1]
    for r in range(1, 5):  # the others are the container's track: not flagged
        rows = [row for row in rrd_rows(tmp_path / "live.rrd", f"/patches/{r}") if "d_mm" in row]
        assert rows[-1]["flagged"] == [False]
    log = [row["TextLog:text"][0] for row in rrd_rows(tmp_path / "live.rrd", "/log") if "TextLog:text" in row]
    assert any(text.startswith("flagged patch ★0") for text in log), log[-5:]
