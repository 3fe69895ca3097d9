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

import argparse
import importlib
import contextlib
import os
import pkgutil
import re
import signal
import sys
import threading

from massviz import __version__
from massviz.errors import MassvizError

# Order in ``massviz --help``; modules not listed here are appended alphabetically.
_ORDER = ["log", "estimate", "score", "sweep", "baseline", "samples", "cloud", "render", "view3d", "extract", "train"]


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


@contextlib.contextmanager
def _signals_end_like_ctrl_c():
    """SIGTERM/SIGHUP raise :class:`Terminated` while the command runs (main thread only; restored after)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {sig: signal.getsignal(sig) for sig in CLEANUP_SIGNALS}
    for sig in CLEANUP_SIGNALS:
        signal.signal(sig, terminate)
    try:
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
    _quiet_native_logs()
    parser = build_parser()
    real_stderr = sys.stderr
    sys.stderr = EscapingStream(real_stderr)
    try:
        with _signals_end_like_ctrl_c():
            return _run(parser, argv)
    finally:
        if isinstance(sys.stderr, EscapingStream) and sys.stderr.raw is real_stderr:
            sys.stderr = real_stderr


def _interrupted(command: str, err: KeyboardInterrupt) -> int:
    """``massviz CMD: interrupted`` (with the signal's name unless it was Ctrl-C); returns the exit code 128 + N."""
    signum = getattr(err, "signum", signal.SIGINT)
    how = "" if signum == signal.SIGINT else f" ({signal.Signals(signum).name})"
    print(f"massviz{' ' + command if command else ''}: interrupted{how}", file=sys.stderr)
    return 128 + int(signum)


def _run(parser: argparse.ArgumentParser, argv) -> int:
    try:
        args = parser.parse_args(argv)
    except KeyboardInterrupt as err:  # a signal while the arguments are read: the command had not started
        words = [str(w) for w in (sys.argv[1:] if argv is None else argv) if not str(w).startswith("-")]
        return _interrupted(words[0] if words else "", err)
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
