"""``massviz estimate``: mass estimates of one or many recordings, written as a CORSMAL challenge CSV."""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from massviz.commands._common import PIPELINE_HELP, add_dataset_args, add_pipeline_args


def register(sub) -> None:
    p = sub.add_parser(
        "estimate", help="estimate container masses and write the CORSMAL challenge CSV",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Run the pipeline over recordings and write one CSV row per recording (CORSMAL challenge "
        "columns; properties massviz does not estimate are -1; 'Execution time' is the pipeline's wall time in "
        "seconds, for a cached trace that of the run which made it).\n\n"
        "REC may be a massviz recording folder, a CCM video (ROOT/viewN/rgb/NNNNNN.mp4), a CCM dataset root "
        "(all recordings of --view), or a folder of massviz recordings. Interrupted runs resume: finished "
        "recordings come back from the trace cache.",
        epilog="example:\n  massviz estimate data_samples --detector depth --out preds.csv\n"
        "  massviz estimate /data/CCM/train --view 3 --out train.csv\n" + PIPELINE_HELP)
    add_dataset_args(p, metavar="REC")
    p.add_argument("--out", required=True, metavar="CSV", help="output CSV (written when every recording is done)")
    p.add_argument("--exact", action="store_true",
                   help="write masses with 2 decimals (default: truncated to int, as the paper's code)")
    p.add_argument("--exclude", metavar="FILE",
                   help="never select the detections listed in FILE (JSON, format massviz.exclusions/1: entries "
                   "recording id + frame + box, e.g. exported by notebooks/03_failure_cases.ipynb)")
    add_pipeline_args(p)
    p.set_defaults(func=run)


def apply_exclusions(trace, exclusions):
    """The trace re-selected without the detections the exclusion entries name (matched by recording id, frame and
    box; ``massviz.evaluation.failures.match_exclusions``); entries of this recording that match nothing are reported."""
    from massviz.evaluation.failures import match_exclusions

    indices, unmatched = match_exclusions(trace, exclusions)
    if unmatched:
        print(f"massviz estimate: {trace.recording.id}: {len(unmatched)} exclusion(s) match no detection "
              f"(first: frame {unmatched[0].frame}, box {list(unmatched[0].box)})", file=sys.stderr)
    if len(indices) == 0:
        return trace
    return trace.reselect(exclude=indices)


def run(args) -> int:
    from tqdm.auto import tqdm

    from massviz.io.challenge_csv import write_challenge_csv
    from massviz.commands._common import build, flag_warning
    from massviz.io.recording import collect_recordings

    from massviz.errors import MassvizError
    from massviz.io.atomic import check_output_file

    check_output_file(args.out, "--out")
    recordings = collect_recordings(args.recordings, args.view, allow_partial=args.allow_partial)
    seen = {}
    for rec in recordings:  # one CSV row per recording: say so now, not after the work
        if (first := seen.setdefault(rec.config_id, rec.path)) != rec.path:
            raise MassvizError(f"configuration id {rec.config_id} is also the id of {first} (one CSV row per id; "
                               "set distinct ids or config_ids in meta.json)", rec.path)
    exclusions = None
    if args.exclude:
        from massviz.evaluation.failures import load_exclusions

        exclusions = load_exclusions(args.exclude)
    pipeline = build(args)
    rows = []
    many = len(recordings) > 1
    for rec in tqdm(recordings, desc="recordings", unit="rec", file=sys.stderr, disable=args.quiet or not many):
        t0 = time.perf_counter()
        trace = pipeline.process(rec)
        if exclusions is not None:
            trace = apply_exclusions(trace, exclusions)
        elapsed = time.perf_counter() - t0
        # Execution time: the pipeline's wall time for this recording; for a trace reused from the cache, the time
        # of the run that made it (recorded in the trace) plus the time spent reusing it.
        exec_time = elapsed + (trace.timings.get("total", 0.0) if "cache" in trace.timings else 0.0)
        rows.append({"config_id": rec.config_id, "mass_g": trace.estimate, "exec_time_s": exec_time})
        if not many:
            print(f"{rec.id}: {'not estimated' if trace.estimate < 0 else f'{trace.estimate:.1f} g'} "
                  f"(K={len(trace.selection)}, {len(trace.detections)} detections, {trace.detector.get('name', '?')}"
                  + (f" {trace.detector['precision']}" if "precision" in trace.detector else "")
                  + f", {elapsed:.1f} s)",
                  file=sys.stderr)
        warning = flag_warning("estimate", trace)
        if warning:
            tqdm.write(warning, file=sys.stderr)
    write_challenge_csv(Path(args.out), rows, exact=args.exact)
    done = sum(r["mass_g"] >= 0 for r in rows)
    print(f"wrote {args.out}: {len(rows)} recordings, {done} estimated", file=sys.stderr)
    return 0
