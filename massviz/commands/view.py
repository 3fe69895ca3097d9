"""``massviz view OUT.rrd``: a recording in Rerun's web viewer, served from this machine on 127.0.0.1 (no display
needed), until Ctrl-C or SIGTERM."""
from __future__ import annotations

import argparse
import sys


def register(sub) -> None:
    p = sub.add_parser(
        "view", help="open an .rrd in a browser: Rerun's web viewer served on 127.0.0.1 (works without a display)",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Serve one Rerun recording to a browser from this machine: the .rrd from a small HTTP server and "
        "Rerun's web viewer, both bound to 127.0.0.1, and print the page to open. Needs no display (the native "
        "viewer, 'rerun OUT.rrd', does). Idle, they use no CPU. Runs until Ctrl-C (or SIGTERM/SIGHUP), also while a "
        "page is open on it; then both stop, nothing is left running, and the exit code is 0.",
        epilog="examples:\n  massviz log data_samples/cup_handover --detector depth --rrd out/cup_handover.rrd\n"
        "  massviz view out/cup_handover.rrd          # then open the printed http://127.0.0.1:... URL\n"
        "  massviz view out/cup_handover.rrd --web-port 9090 --port 9091   # fixed ports (e.g. for ssh -L)")
    p.add_argument("rrd", metavar="OUT.rrd", help="a Rerun recording (massviz log REC --rrd OUT.rrd, massviz live "
                   "--rrd, a --rrd-dir file)")
    p.add_argument("--web-port", type=int, default=0, help="web viewer port (default: a free one)")
    p.add_argument("--port", type=int, default=0, help="port the .rrd is served from (default: a free one)")
    p.set_defaults(func=run)


def run(args) -> int:
    from massviz.views.rerun_serve import view

    return view(args.rrd, port=args.port, web_port=args.web_port, out=sys.stdout)
