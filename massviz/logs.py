"""massviz's messages go through Python's ``logging``: the logger ``massviz`` and its children (one per module,
``logging.getLogger(__name__)``). A library call never prints; what is shown, and where, is the caller's choice:

* the command line (``massviz.cli.main``) runs inside :func:`to_stderr`: every record of level INFO and above is its
  one line on stderr, as the commands have always printed them (the messages carry their ``massviz: ...`` prefix);
* a notebook or a service configures ``logging`` as it likes (without any handler, Python prints warnings and
  errors to stderr and drops the rest);
* while a Rerun sink is active, its records also go to that recording's ``/log`` as ``TextLog`` entries
  (``massviz.views.rerun.output.RerunLogHandler``, as Rerun's own logging-handler example does).
"""
from __future__ import annotations

import logging
import sys
from contextlib import contextmanager

ROOT = "massviz"


class _Stderr(logging.Handler):
    """Each record as its message alone, on whatever ``sys.stderr`` is when it is emitted (the CLI's escaping
    stream, a test's capture)."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            print(self.format(record), file=sys.stderr)
        except Exception:  # noqa: BLE001 - logging must never raise into the caller
            self.handleError(record)


@contextmanager
def to_stderr():
    """While inside: massviz's records of level INFO and above are one line each on stderr (the command line's
    messages) and do not also propagate to the root logger; the logger is restored on the way out (a process that
    runs ``massviz.cli.main`` in-process keeps no handler)."""
    logger = logging.getLogger(ROOT)
    handler = _Stderr(logging.INFO)
    handler.setFormatter(logging.Formatter("%(message)s"))
    level, propagate = logger.level, logger.propagate
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    logger.propagate = False
    try:
        yield handler
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)
        logger.propagate = propagate


__all__ = ["ROOT", "to_stderr"]
