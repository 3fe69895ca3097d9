"""``massviz compare``: what another precision, detector, threshold or weights changes (or two recordings differ); on
datasets, two runs of every recording side by side (``massviz.commands._compare_runs``)."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from massviz.commands._common import PIPELINE_HELP, add_pipeline_args
from massviz.commands._compare_runs import HELP as RUNS_HELP
from massviz.core.types import PRECISIONS

#: side-B options: ``--b-NAME`` overrides pipeline option NAME for B.
B_OPTIONS = ("detector", "threshold", "precision", "weights", "detector_weights", "replay", "k", "stride")


def register(sub) -> None:
    p = sub.add_parser(
        "compare", help="compare two runs: of one recording (traces: matched detections, score/d/prediction deltas, chosen "
        "patches, estimate) or of a dataset (two run folders, or DATASET --a/--b: errors, ties, per-class scores)",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Compare two runs: A and B are each a saved trace (.npz) or a recording (run with the pipeline "
        "options below; for B the --b-* options override them). B defaults to A, so 'massviz compare REC "
        "--b-precision bf16' shows what bf16 changes on REC. Detections are matched frame by frame (IoU, one to "
        "one); the report lists the settings that differ, matched and unmatched detections, the B - A differences "
        "of score, d and prediction, the chosen patches rank by rank and the estimate difference. --rrd writes both "
        "traces into one Rerun file as two recordings (named 'A: ...' and 'B: ...'), each with the report under "
        "/compare.",
        epilog="examples:\n"
        "  massviz compare rec/ --detector maskrcnn --b-precision bf16\n"
        "  massviz compare rec/ --detector maskrcnn --b-detector depth --rrd both.rrd\n"
        "  massviz compare a_trace.npz b_trace.npz --json diff.json\n" + RUNS_HELP + PIPELINE_HELP)
    p.add_argument("a", metavar="A", help="a trace file (.npz) or a recording (folder or CCM video); or a run folder "
                   "('massviz log DATASET --rrd-dir'), or with --a/--b a dataset")
    p.add_argument("b", metavar="B", nargs="?", help="the same for B (default: A again, with the --b-* options); or "
                   "a second run folder (its settings are its own: of the --b-* options it takes --b-weights, "
                   "--b-detector-weights, --b-precision, --b-replay)")
    p.add_argument("--iou", type=float, default=0.5, metavar="X",
                   help="boxes of one frame with IoU >= X are the same detection (default: 0.5)")
    p.add_argument("--rrd", metavar="OUT.rrd", help="write both traces into one Rerun file as two recordings")
    p.add_argument("--json", metavar="OUT.json", help="also write the figures as JSON")
    p.add_argument("--video", choices=["auto", "asset", "images"], default="auto",
                   help="how an mp4 input is logged with --rrd (see 'massviz log --help')")
    gr = p.add_argument_group("two runs of a dataset (see 'two runs of a dataset' below)")
    gr.add_argument("--a", dest="a_settings", metavar="SETTINGS",
                    help="run A of dataset A: NAME=VALUE,... over the pipeline options (detector, threshold, k, "
                    "stride, weights, detector_weights, precision, replay)")
    gr.add_argument("--b", dest="b_settings", metavar="SETTINGS", help="run B, the same (the --b-* options too)")
    gr.add_argument("--out", metavar="TABLE", help="write the comparison table (.csv or .parquet)")
    gr.add_argument("--rrd-dir", metavar="DIR", help="write one recording per input with both runs and their "
                    "_a/_b/delta_ properties (for 'massviz serve DIR'); with two run folders, from the traces of "
                    "the settings they record")
    gr.add_argument("--rows", type=int, default=20, metavar="N", help="rows of the table printed (default: 20)")
    add_pipeline_args(p)
    gb = p.add_argument_group("side B (override the pipeline options for B)")
    gb.add_argument("--b-detector", choices=["auto", "maskrcnn", "nanodet", "depth", "replay"], metavar="NAME",
                    help="B's detector")
    gb.add_argument("--b-threshold", type=float, metavar="T", help="B's detection threshold")
    gb.add_argument("--b-precision", choices=PRECISIONS, help="B's Mask R-CNN precision")
    gb.add_argument("--b-weights", metavar="PATH", help="B's mass-CNN checkpoint")
    gb.add_argument("--b-detector-weights", metavar="PATH", help="B's Mask R-CNN state_dict")
    gb.add_argument("--b-replay", metavar="PATH", help="B's --replay input")
    gb.add_argument("--b-k", type=int, metavar="K", help="B's K")
    gb.add_argument("--b-stride", type=int, metavar="N", help="B's stride")
    p.set_defaults(func=run)


def _is_trace(path: str) -> bool:
    return Path(path).suffix.lower() == ".npz"


def _side(spec: str, args, overrides: dict, label: str):
    """(trace, recording or None, description) of one side."""
    from massviz.app import PipelineOptions, build_pipeline
    from massviz.errors import MassvizError
    from massviz.io.recording import open_recording
    from massviz.io.trace_file import load_trace

    if _is_trace(spec):
        if overrides:
            raise MassvizError(f"{label} is a saved trace: --b-* options apply to recordings only", spec)
        if not Path(spec).is_file():
            raise MassvizError("no such trace file", spec)
        return load_trace(spec), None, spec
    rec = open_recording(spec)
    options = PipelineOptions.from_args(args, **overrides)
    trace = build_pipeline(options).process(rec)
    return trace, rec, spec


def _recording_of(trace, rec, label: str):
    from massviz.errors import MassvizError
    from massviz.io.recording import open_recording

    if rec is not None:
        return rec
    path = trace.recording.path
    if not path or not Path(path).exists():
        raise MassvizError(f"--rrd needs the frames of {label}'s recording, which is not at {path!r}")
    return open_recording(path)


def run(args) -> int:
    from massviz.commands import _compare_runs as compare_runs
    from massviz.errors import MassvizError
    from massviz.evaluation.compare import compare_traces

    if compare_runs.wants_runs(args):
        return compare_runs.run(args, B_OPTIONS)
    for name in ("out", "rrd_dir"):
        if getattr(args, name):
            raise MassvizError(f"--{name.replace('_', '-')} is for two runs of a dataset (two run folders, or "
                               "DATASET --a SETTINGS --b SETTINGS); for one recording use --rrd and --json")
    overrides = {n: getattr(args, f"b_{n}") for n in B_OPTIONS if getattr(args, f"b_{n}") is not None}
    b_spec = args.b or args.a
    if args.b is None and not overrides:
        raise MassvizError("nothing to compare: give B, or change something for B with a --b-* option "
                           "(e.g. --b-precision bf16)")
    for out in (args.rrd, args.json):
        if out and Path(out).is_dir():
            raise MassvizError("is a directory; give a file path", out)
    trace_a, rec_a, name_a = _side(args.a, args, {}, "A")
    trace_b, rec_b, name_b = _side(b_spec, args, overrides, "B")
    changed = ", ".join(f"{k}={v}" for k, v in overrides.items())
    label_a, label_b = name_a, name_b + (f" ({changed})" if changed else "")
    result = compare_traces(trace_a, trace_b, iou=args.iou, labels=(label_a, label_b))
    sys.stdout.write(result.table())
    if args.json:
        from massviz.io.atomic import atomic_path

        with atomic_path(args.json) as tmp:
            tmp.write_text(json.dumps(result.summary(), indent=1, default=str) + "\n")
        print(f"wrote {args.json}", file=sys.stderr)
    if args.rrd:
        from massviz.measure3d.stage import measured_replay
        from massviz.views.rerun_compare import log_two_traces

        sides = [(f"A: {label_a}", trace_a, _recording_of(trace_a, rec_a, "A")),
                 (f"B: {label_b}", trace_b, _recording_of(trace_b, rec_b, "B"))]
        log_two_traces(sides, args.rrd, markdown=result.markdown(), progress=not args.quiet, video=args.video,
                       replay=measured_replay)
        print(f"wrote {args.rrd} (two recordings: A and B)", file=sys.stderr)
    return 0
