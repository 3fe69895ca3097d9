"""``python -m massviz`` and the ``massviz`` script: :func:`massviz.cli.main`, with a Ctrl-C that comes while
the command line module itself is still being imported ended as every later one is (one line, exit 130)."""
import gc
import sys


def run() -> int:
    try:
        from massviz.cli import main
    except KeyboardInterrupt:
        print("massviz: interrupted", file=sys.stderr)
        return 130
    code = main()
    gc.freeze()  # the process ends now: the collector's last sweeps over every object (seconds, with torch and Rerun
    return code  # loaded, on a busy machine) are skipped; the command has closed and written everything already


if __name__ == "__main__":
    sys.exit(run())
