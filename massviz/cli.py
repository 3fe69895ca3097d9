"""``massviz`` command line: a thin layer over the library.

Each sub-command lives in ``massviz/commands/<name>.py`` and exposes ``register(subparsers)``, which adds its parser
and sets ``func`` (a callable taking the parsed args and returning an exit code). Any ``MassvizError`` becomes one
line on stderr and exit code 2, as does any ``OSError`` (the path and what the OS said); no traceback reaches the
user.
"""
from __future__ import annotations

import argparse
import importlib
import os
import pkgutil
import sys

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


def os_error_line(err: OSError) -> str:
    """``PATH: what the OS said`` for an ``OSError`` (both paths of a failed rename), in one line."""
    what = err.strerror or str(err) or type(err).__name__
    names = [str(n) for n in (err.filename, err.filename2) if n is not None]
    return f"{' -> '.join(names)}: {what}" if names else f"{what} ({type(err).__name__})"


def main(argv: list[str] | None = None) -> int:
    _quiet_native_logs()
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help(sys.stderr)
        return 2
    try:
        return int(args.func(args) or 0)
    except MassvizError as err:
        print(f"massviz {args.command}: error: {err}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # e.g. `massviz score ... | head`: the reader left; nothing more to say
        sys.stderr.close()
        return 141
    except KeyboardInterrupt:
        print(f"massviz {args.command}: interrupted", file=sys.stderr)
        return 130
    except OSError as err:  # a file system refusal the command did not foresee: still one line naming the path
        if os.environ.get("MASSVIZ_DEBUG"):
            raise
        print(f"massviz {args.command}: error: {os_error_line(err)}", file=sys.stderr)
        return 2
    except Exception as err:  # noqa: BLE001 - last line of defence: one line, no traceback
        if os.environ.get("MASSVIZ_DEBUG"):
            raise
        print(f"massviz {args.command}: internal error: {type(err).__name__}: {err} "
              "(set MASSVIZ_DEBUG=1 for a traceback)", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
