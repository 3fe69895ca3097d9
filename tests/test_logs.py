"""The library logs (Python's ``logging``, logger ``massviz``) instead of printing: the command line shows the records
as its one-line messages, a notebook or service chooses, and an open Rerun sink gets them in ``/log``."""
from __future__ import annotations

import logging

from massviz.logs import ROOT, to_stderr
from massviz.views.rerun.output import Output, RerunLogHandler
from massviz.views.rerun.rrd_reader import rrd_rows


def test_a_library_call_prints_nothing_itself(capsys, caplog):
    from massviz.io.formats.common import warn_once

    caplog.set_level(logging.INFO, logger=ROOT)
    logging.getLogger("massviz.detect").info("massviz: --detector auto: using depth: why")
    assert capsys.readouterr().err == ""  # an INFO record: shown only where the caller asks for it
    warn_once("a note only this test makes")
    assert [r.getMessage() for r in caplog.records] == ["massviz: --detector auto: using depth: why",
                                                        "massviz: warning: a note only this test makes"]
    assert [r.levelname for r in caplog.records] == ["INFO", "WARNING"]


def test_the_command_line_shows_every_record_as_its_line_and_restores_the_logger(capsys):
    logger = logging.getLogger(ROOT)
    before = (list(logger.handlers), logger.level, logger.propagate)
    with to_stderr():
        logging.getLogger("massviz.detect").info("massviz: --detector auto: using depth: why")
        logging.getLogger("massviz.io.cache").warning("massviz: warning: %s: not cached", "/x")
        logging.getLogger("massviz.io.cache").debug("not shown")
    assert capsys.readouterr().err == "massviz: --detector auto: using depth: why\nmassviz: warning: /x: not cached\n"
    assert (list(logger.handlers), logger.level, logger.propagate) == before


def test_an_open_rerun_sink_gets_the_records_in_its_log(tmp_path):
    rrd = tmp_path / "r.rrd"
    out = Output(rrd=rrd)
    assert any(isinstance(h, RerunLogHandler) for h in logging.getLogger(ROOT).handlers)
    out.stream.set_time("frame", sequence=3)
    logging.getLogger("massviz.io.cache").warning("massviz: warning: %s: not cached", "/x")
    logging.getLogger("other.library").warning("not massviz's")
    out.flush()
    out.close()
    assert not any(isinstance(h, RerunLogHandler) for h in logging.getLogger(ROOT).handlers)
    logging.getLogger("massviz.io.cache").warning("after close")
    rows = rrd_rows(rrd, "/log")
    assert [(r["time"], r["TextLog:text"], r["TextLog:level"]) for r in rows] == [
        (3, ["massviz: warning: /x: not cached"], ["WARN"])]
