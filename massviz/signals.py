"""Signals: SIGTERM and SIGHUP end a command the way Ctrl-C (SIGINT) does, never in the middle of an import, and a
commit (the renames that put a finished output in place, the removal of a temporary one) runs to its end before a
signal is acted on (:func:`deferred`). Used by the command line (``massviz.cli``), the live runner and the atomic
writers (``massviz.io.atomic``); imports nothing of massviz."""
from __future__ import annotations

import _thread
import contextlib
import os
import signal
import sys
import threading
import time
from collections.abc import Iterator


class Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP arrived: raised in the main thread like Ctrl-C's ``KeyboardInterrupt`` (a subclass, so
    every clean-up written for Ctrl-C runs), carrying the signal."""

    def __init__(self, signum: int):
        self.signum = signum
        super().__init__(signal.Signals(signum).name)


#: the signals that end a command like Ctrl-C does (SIGINT itself raises KeyboardInterrupt already).
CLEANUP_SIGNALS = (signal.SIGTERM, signal.SIGHUP)


def terminate(signum, frame):
    """The handler of :data:`CLEANUP_SIGNALS`: raise :class:`Terminated` (further such signals are ignored from
    here on, so they cannot interrupt the clean-up of the first)."""
    for sig in CLEANUP_SIGNALS:
        signal.signal(sig, signal.SIG_IGN)
    raise Terminated(signum)


#: the frames of Python's import machinery: a signal handled while one of them runs waits until it is done.
_IMPORT_FRAMES = ("<frozen importlib._bootstrap>", "<frozen importlib._bootstrap_external>")
_deferred: list[int] = []  # the signal waiting for the main thread's import to end (at most one)


def _importing(frame) -> bool:
    while frame is not None:
        if frame.f_code.co_filename in _IMPORT_FRAMES:
            return True
        frame = frame.f_back
    return False


def end_like_ctrl_c(signum, frame):
    """The handler of SIGINT and :data:`CLEANUP_SIGNALS` while a command runs: ``KeyboardInterrupt`` (SIGINT) or
    :func:`terminate`, raised where the main thread is, unless it is importing a module. An exception raised
    there does not reach massviz as itself: numpy's C extension turns it into "Importing the numpy C-extensions
    failed", pybind11 into ``ImportError("initialization failed")`` (and the module cannot be imported again in
    that process), and in one of importlib's weakref callbacks it is printed as "Exception ignored" and lost. So
    during an import the signal waits: a thread watches the main thread's frames and hands the signal back
    (``_thread.interrupt_main``) within 10 ms of the import's end."""
    if _importing(frame):
        if not _deferred:
            _deferred.append(signum)
            threading.Thread(target=_deliver_after_import, name="massviz-deferred-signal", daemon=True).start()
        return
    if signum == signal.SIGINT:
        raise KeyboardInterrupt
    terminate(signum, frame)


def _deliver_after_import() -> None:
    main = threading.main_thread()
    while main.is_alive() and _importing(sys._current_frames().get(main.ident)):
        time.sleep(0.01)
    signum = _deferred.pop()
    if main.is_alive():
        _thread.interrupt_main(signum)  # runs the main thread's handler for signum (which may defer it again)


def interrupt_behind(err: BaseException) -> KeyboardInterrupt | None:
    """The Ctrl-C or :class:`Terminated` that ``err`` was raised from or while handling, if any: a native module
    (pybind11's, e.g. pyrealsense2) turns an interrupt raised during its import into ``ImportError("initialization
    failed")``, which a caller may turn into its own error in turn."""
    seen = set()
    while err is not None and id(err) not in seen:
        if isinstance(err, KeyboardInterrupt):
            return err
        seen.add(id(err))
        err = err.__cause__ or err.__context__
    return None


def install_handlers(handler, previous: dict) -> None:
    """Put ``handler`` in for SIGINT and :data:`CLEANUP_SIGNALS`, each one's previous handler recorded in ``previous``
    before it is replaced (an interrupt half-way leaves a complete record of what to restore). A signal ignored when
    massviz started (nohup's SIGHUP, a background job's SIGINT) stays ignored."""
    for sig in (signal.SIGINT, *CLEANUP_SIGNALS):
        current = signal.getsignal(sig)
        if current == signal.SIG_IGN:
            continue
        previous[sig] = current
        signal.signal(sig, handler)


@contextlib.contextmanager
def signals_end_like_ctrl_c():
    """SIGTERM/SIGHUP raise :class:`Terminated` and SIGINT ``KeyboardInterrupt`` while the command runs, not in the
    middle of an import (:func:`end_like_ctrl_c`; main thread only; the previous handlers are restored after)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {}
    try:  # a Ctrl-C while they go in: the ones already in come out again
        install_handlers(end_like_ctrl_c, previous)
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


@contextlib.contextmanager
def deferred() -> Iterator[None]:
    """Hold SIGINT, SIGTERM and SIGHUP while the block runs (main thread only; elsewhere the block just runs): a
    signal that arrives is remembered and acted on by the handler that was in place once the block is done (raised
    right after it). For the few steps that must not stop half-way: renaming a finished output into place, removing
    a temporary one."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    pending: list[int] = []
    previous: dict = {}

    def hold(signum, frame):
        if not pending:
            pending.append(signum)

    try:
        for sig in (signal.SIGINT, *CLEANUP_SIGNALS):
            current = signal.getsignal(sig)
            if current in (signal.SIG_IGN, None):
                continue
            previous[sig] = current
            signal.signal(sig, hold)
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        if pending:
            handler = previous.get(pending[0])
            if callable(handler):
                handler(pending[0], sys._getframe())
            elif handler == signal.SIG_DFL:
                os.kill(os.getpid(), pending[0])


__all__ = ["Terminated", "CLEANUP_SIGNALS", "terminate", "end_like_ctrl_c", "interrupt_behind", "install_handlers",
           "signals_end_like_ctrl_c", "deferred"]
