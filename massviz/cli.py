"""``massviz`` command line: a thin layer over the library.

Each sub-command lives in ``massviz/commands/<name>.py`` and exposes ``register(subparsers)``, which adds its parser
and sets ``func`` (a callable taking the parsed args and returning an exit code). Any ``MassvizError`` becomes one
line on stderr and exit code 2, as does any ``OSError`` (the path and what the OS said); no traceback reaches the
user.

Two things are done here once for every command: SIGTERM and SIGHUP end a command the way Ctrl-C (SIGINT) does
(:mod:`massviz.signals`: :class:`~massviz.signals.Terminated` is a ``KeyboardInterrupt``: every
``atomic_path``/``atomic_dir`` and runner removes its temporary files on the way out; exit code 128 + the signal), and everything written to stderr goes through
:func:`massviz.io.untrusted.printable` (a name from a data file cannot send terminal escape sequences).
"""
from __future__ import annotations

import argparse
import importlib
import os
import pkgutil
import re
import signal
import sys

from massviz import __version__
from massviz.errors import MassvizError
from massviz.logs import to_stderr
from massviz.signals import CLEANUP_SIGNALS, Terminated, interrupt_behind, signals_end_like_ctrl_c

__all__ = ["main", "build_parser", "error_line", "os_error_line", "EscapingStream", "Terminated", "CLEANUP_SIGNALS"]

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
        with to_stderr(), signals_end_like_ctrl_c():  # the library's log records: one line each on stderr
            return _run(build_parser(), argv)
    except KeyboardInterrupt as err:  # before the command started (its parser built, the handlers going in) or
        return _interrupted(_command_word(argv), err)  # after it ended (the handlers coming out): nothing to undo
    finally:
        if isinstance(sys.stderr, EscapingStream) and sys.stderr.raw is real_stderr:
            sys.stderr = real_stderr


def _out_of_memory_line(err: BaseException) -> str | None:
    """The line for a run that ran out of memory or address space (a ``MemoryError``, or a native library that could
    not be mapped: ``ulimit -v`` set too low for torch), naming the limit when one is set; None for other errors."""
    import resource

    text = str(err).splitlines()[0] if str(err).strip() else type(err).__name__
    if isinstance(err, ImportError) and not re.search(r"map segment|allocate memory|Cannot allocate", text):
        return None
    limit = resource.getrlimit(resource.RLIMIT_AS)[0]
    why = (f"the address-space limit (ulimit -v {limit // 1024} KiB) is too low" if limit != resource.RLIM_INFINITY
           else "not enough memory")
    what = f"cannot load a library ({text})" if isinstance(err, ImportError) else "out of memory"
    return f"{what}: {why}"


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
        from massviz.commands._common import check_float_options, check_int_options

        try:
            check_int_options(args)
            check_float_options(args)
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
    except (MemoryError, ImportError) as err:
        line = _out_of_memory_line(err)
        if line is None or os.environ.get("MASSVIZ_DEBUG"):
            raise
        print(error_line(args.command, line), file=sys.stderr)
        return 2
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
