"""``massviz`` command line: a thin layer over the library.

Each sub-command lives in ``massviz/commands/<name>.py`` and exposes ``register(subparsers)``, which adds its parser
and sets ``func`` (a callable taking the parsed args and returning an exit code). Any ``MassvizError`` becomes one
line on stderr and exit code 2, as does any ``OSError`` (the path and what the OS said); no traceback reaches the
user.

Two things are done here once for every command: SIGTERM and SIGHUP end a command the way Ctrl-C (SIGINT) does
(:class:`Terminated` is a ``KeyboardInterrupt``: every ``atomic_path``/``atomic_dir`` and runner removes its
temporary files on the way out; exit code 128 + the signal), and everything written to stderr goes through
:func:`massviz.io.untrusted.printable` (a name from a data file cannot send terminal escape sequences).
"""
from __future__ import annotations

import _thread
import argparse
import importlib
import contextlib
import os
import pkgutil
import re
import signal
import sys
import threading
import time

from massviz import __version__
from massviz.errors import MassvizError
from massviz.logs import to_stderr

# Order in ``massviz --help``; modules not listed here are appended alphabetically.
_ORDER = ["log", "view", "estimate", "score", "sweep", "baseline", "samples", "cloud", "render", "view3d", "extract", "train"]


def _command_modules():
    import massviz.commands as pkg

    names = [m.name for m in pkgutil.iter_modules(pkg.__path__) if not m.name.startswith("_")]
    names.sort(key=lambda n: (_ORDER.index(n) if n in _ORDER else len(_ORDER), n))
    return [importlib.import_module(f"massviz.commands.{n}") for n in names]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="massviz",
        description="Estimate the empty mass of a container handed to a robot from one fixed RGB-D camera "
        "(Apicella et al., ICASSP 2022) and inspect every stage of the estimate in Rerun, Open3D and notebooks.",
        epilog="Run 'massviz COMMAND --help' for the options of each command.",
    )
    parser.add_argument("--version", action="version", version=f"massviz {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for module in _command_modules():
        module.register(sub)
    return parser


def _quiet_native_logs() -> None:
    """OpenCV and its FFmpeg backend print their own warnings about unreadable files straight to stderr; massviz
    reports those files itself (one line), so silence them unless MASSVIZ_DEBUG is set. Must run before cv2 loads."""
    if not os.environ.get("MASSVIZ_DEBUG"):
        os.environ.setdefault("OPENCV_LOG_LEVEL", "OFF")
        os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # AV_LOG_QUIET
        os.environ.setdefault("RUST_LOG", "off")  # Rerun's own log lines (a failed file sink): massviz says it once


def os_error_line(err: OSError) -> str:
    """``PATH: what the OS said`` for an ``OSError`` (both paths of a failed rename), in one line."""
    what = err.strerror or str(err) or type(err).__name__
    names = [str(n) for n in (err.filename, err.filename2) if n is not None]
    return f"{' -> '.join(names)}: {what}" if names else f"{what} ({type(err).__name__})"


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
def _signals_end_like_ctrl_c():
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


#: what tqdm writes to move between its bars (cursor up): let through; any other escape is printed escaped.
_TQDM_MOVES = re.compile(r"(\x1b\[A)+")


class EscapingStream:
    """A text stream that writes to ``raw`` with every control character escaped
    (:func:`massviz.io.untrusted.printable`) except newline, carriage return and tab (progress bars need them) and
    tqdm's own cursor-up moves written on their own."""

    def __init__(self, raw):
        self.raw = raw

    def write(self, text: str) -> int:
        from massviz.io.untrusted import printable

        if not _TQDM_MOVES.fullmatch(text):
            text = printable(text, keep="\n\r\t")
        self.raw.write(text)
        return len(text)

    def __getattr__(self, name):  # flush, isatty, fileno, encoding, close ... of the real stream (not an IOBase:
        return getattr(self.raw, name)  # being garbage-collected must not close the real stderr)


def error_line(command: str, message) -> str:
    """``massviz CMD: error: MESSAGE`` as one line: control characters (newlines too) escaped."""
    from massviz.io.untrusted import printable

    return f"massviz {command}: error: {printable(message)}"


def main(argv: list[str] | None = None) -> int:
    real_stderr = sys.stderr
    try:
        _quiet_native_logs()
        sys.stderr = EscapingStream(real_stderr)
        with to_stderr(), _signals_end_like_ctrl_c():  # the library's log records: one line each on stderr
            return _run(build_parser(), argv)
    except KeyboardInterrupt as err:  # before the command started (its parser built, the handlers going in) or
        return _interrupted(_command_word(argv), err)  # after it ended (the handlers coming out): nothing to undo
    finally:
        if isinstance(sys.stderr, EscapingStream) and sys.stderr.raw is real_stderr:
            sys.stderr = real_stderr


def _interrupted(command: str, err: KeyboardInterrupt) -> int:
    """``massviz CMD: interrupted`` (with the signal's name unless it was Ctrl-C); returns the exit code 128 + N."""
    signum = getattr(err, "signum", signal.SIGINT)
    how = "" if signum == signal.SIGINT else f" ({signal.Signals(signum).name})"
    print(f"massviz{' ' + command if command else ''}: interrupted{how}", file=sys.stderr)
    return 128 + int(signum)


def _command_word(argv) -> str:
    """The command named on the command line (the first word that is not an option), "" if none: for the
    "interrupted" line when a signal comes before argparse has said which command it is."""
    words = [str(w) for w in (sys.argv[1:] if argv is None else argv) if not str(w).startswith("-")]
    return words[0] if words else ""


def _run(parser: argparse.ArgumentParser, argv) -> int:
    args = parser.parse_args(argv)  # a signal while the arguments are read: ``main`` says "interrupted"
    if not getattr(args, "func", None):
        parser.print_help(sys.stderr)
        return 2
    try:
        from massviz.commands._common import check_int_options

        try:
            check_int_options(args)
            return int(args.func(args) or 0)
        except Exception as err:  # an interrupt turned into another error on its way out is still an interrupt
            stop = interrupt_behind(err)
            if stop is None:
                raise
            raise stop from None
    except MassvizError as err:
        print(error_line(args.command, err), file=sys.stderr)
        return 2
    except BrokenPipeError:  # e.g. `massviz score ... | head`: the reader left; nothing more to say
        sys.stderr.close()
        return 141
    except KeyboardInterrupt as err:
        return _interrupted(args.command, err)
    except OSError as err:  # a file system refusal the command did not foresee: still one line naming the path
        if os.environ.get("MASSVIZ_DEBUG"):
            raise
        print(error_line(args.command, os_error_line(err)), file=sys.stderr)
        return 2
    except Exception as err:  # noqa: BLE001 - last line of defence: one line, no traceback
        if os.environ.get("MASSVIZ_DEBUG"):
            raise
        from massviz.io.untrusted import printable

        print(f"massviz {args.command}: internal error: {type(err).__name__}: {printable(err)} "
              "(set MASSVIZ_DEBUG=1 for a traceback)", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
