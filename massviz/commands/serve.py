"""``massviz serve OUT/``: Rerun's catalog server on 127.0.0.1 with a dataset of .rrd recordings (made by
``massviz log DATASET --rrd-dir OUT/``, or two runs' by ``massviz compare ... --rrd-dir OUT/``), massviz's layouts
registered as the dataset's defaults, and a web viewer."""
from __future__ import annotations

import argparse
import sys


def register(sub) -> None:
    p = sub.add_parser(
        "serve", help="serve a folder of .rrd recordings (massviz log/compare --rrd-dir) as a Rerun catalog dataset",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Start Rerun's catalog server on 127.0.0.1 with OUT as one dataset (one segment per .rrd; the "
        "recording properties massviz wrote are the segment table's columns), register massviz's layouts as the "
        "dataset's defaults (the recording layout, and the segment table sorted by relative error whose first "
        "column, 'recording', is a button that opens the recording at its best frame), start a web "
        "viewer on 127.0.0.1 and print how to open it. A folder of two-run recordings ('massviz compare A B "
        "--rrd-dir OUT') gets the two-run layouts: A and B side by side in each recording, and a table of both "
        "runs' figures and their deltas ranked by how much the relative error changed (change_rank). Only the .rrd "
        "files Rerun reads whole are served; every other one (cut off, empty, not Rerun's, damaged, a second file of "
        "one recording) is named on stderr with its reason. Runs until Ctrl-C (or SIGTERM/SIGHUP), also while a "
        "browser page is open on it; then the server and the web viewer stop, nothing is left running, and the exit "
        "code is 0 (1 if the web viewer exited by itself, 2 if no file can be served).",
        epilog="examples:\n  massviz log data_samples --detector depth --rrd-dir out/samples\n"
        "  massviz serve out/samples                 # then open the printed http://127.0.0.1:... URL\n"
        "  massviz serve out/samples --no-web-viewer --port 51234   # it runs until Ctrl-C; then, in another\n"
        "  rerun rerun+http://127.0.0.1:51234                         # terminal, a native viewer (needs a display)\n"
        "  massviz compare data_samples --detector depth --a k=5 --b k=3 --rrd-dir out/k5_k3\n"
        "  massviz serve out/k5_k3                   # two runs: both in each recording, the deltas in the table")
    p.add_argument("folder", metavar="OUT", help="folder of .rrd files (massviz log DATASET --rrd-dir OUT, or massviz compare ... --rrd-dir OUT)")
    p.add_argument("--name", default=None, help="dataset name (default: the folder's name)")
    p.add_argument("--port", type=int, default=0, help="catalog server port (default: a free one)")
    p.add_argument("--web-port", type=int, default=0, help="web viewer port (default: a free one)")
    p.add_argument("--no-web-viewer", action="store_true", help="only the catalog server (open it with the native "
                   "viewer: rerun rerun+http://127.0.0.1:PORT)")
    p.add_argument("--k", type=int, default=5, metavar="K", help="patch tiles in the recording layout "
                   "(default: 5; two-run recordings: the most patches either run chose)")
    p.set_defaults(func=run)


def run(args) -> int:
    from massviz.views.rerun_serve import serve

    return serve(args.folder, name=args.name, port=args.port, web_port=args.web_port,
                 web_viewer=not args.no_web_viewer, k=args.k, out=sys.stdout)
