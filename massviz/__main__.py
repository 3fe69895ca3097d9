"""``python -m massviz`` and the ``massviz`` script: :func:`massviz.cli.main`, with a Ctrl-C that comes while
the command line module itself is still being imported ended as every later one is (one line, exit 130)."""
import sys


def run() -> int:
    try:
        from massviz.cli import main
    except KeyboardInterrupt:
        print("massviz: interrupted", file=sys.stderr)
        return 130
    return main()


if __name__ == "__main__":
    sys.exit(run())
