"""The one context-managed Rerun output that ``massviz log``'s sinks open (``massviz.views.rerun.output.Output``:
``with Output(...) as out`` opens the stream, routes massviz's log records into its ``/log``, flushes and closes it,
leaves nothing at the .rrd path after an error and reports its stats). That ``log`` and ``live`` share one per-frame
mapping (``massviz.views.rerun.frame_logger.FrameLogger``) is checked by tests/test_architecture.py."""
from __future__ import annotations

import logging

import pytest
import rerun as rr

from massviz.errors import MassvizError
from massviz.views.rerun.output import Output, RerunLogHandler
from rrd_reader import rrd_entities


def handlers() -> list:
    return [h for h in logging.getLogger("massviz").handlers if isinstance(h, RerunLogHandler)]


def test_leaving_the_block_delivers_the_file_and_reports_it(tmp_path):
    out_path = tmp_path / "out.rrd"
    with Output(rrd=out_path) as out:
        out.stream.log("/note", rr.TextLog("hello"))
        logging.getLogger("massviz.test").warning("a massviz record")  # routed into /log while open
        assert not out_path.exists()  # written to a temporary name until the block ends
        assert len(handlers()) == 1
    assert handlers() == []
    assert out_path.is_file() and {"/note", "/log"} <= rrd_entities(out_path)
    assert out.stats() == {"recording_id": out.stream.get_recording_id(), "rrd": str(out_path)}
    assert out.seconds > 0 and out.seconds == out.seconds  # stopped when it was closed


def test_an_error_in_the_block_leaves_nothing_and_is_raised_on(tmp_path):
    out_path = tmp_path / "out.rrd"
    with pytest.raises(RuntimeError, match="the sink failed"):
        with Output(rrd=out_path) as out:
            out.stream.log("/note", rr.TextLog("hello"))
            raise RuntimeError("the sink failed")
    assert list(tmp_path.iterdir()) == []  # neither the .rrd nor its temporary file
    assert handlers() == []


class UnreachableStream:
    """A caller's stream whose viewer cannot be reached: Rerun's gRPC sink reports it when flushed."""

    def log(self, *args, **kwargs) -> None:
        pass

    def flush(self, timeout_sec: float | None = None) -> None:
        raise RuntimeError("connection refused")


def test_a_recording_that_cannot_be_delivered_is_one_line():
    with pytest.raises(MassvizError, match=r"could not deliver the recording to Rerun \(connection refused\)"):
        with Output(stream=UnreachableStream()):
            pass
    assert handlers() == []
