"""``massviz estimate``: mass estimates of one or many recordings, written as a CORSMAL challenge CSV."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from massviz.commands._common import PIPELINE_HELP, add_dataset_args, add_pipeline_args
from massviz.commands._runner import ENGINE_HELP, add_engine_args


def register(sub) -> None:
    p = sub.add_parser(
        "estimate", help="estimate container masses and write the CORSMAL challenge CSV",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Run the pipeline over recordings and write one CSV row per recording (CORSMAL challenge "
        "columns; properties massviz does not estimate are -1; 'Execution time' is the pipeline's wall time in "
        "seconds recorded in the trace by the run that computed it, see --exec-time). Rows are in input order and "
        "the CSV is written when every recording is done, the same bytes with --engine local or ray.\n\n"
        "REC may be a massviz recording folder, a CCM video (ROOT/viewN/rgb/NNNNNN.mp4), a CCM dataset root "
        "(all recordings of --view), or a folder of massviz recordings. Interrupted runs resume: finished "
        "recordings come back from the trace cache.",
        epilog="example:\n  massviz estimate data_samples --detector depth --out preds.csv\n"
        "  massviz estimate /data/CCM/train --view 3 --out train.csv\n"
        "  massviz estimate /data/CCM/test --engine ray --ray-address auto --report run.json --out test.csv\n"
        + PIPELINE_HELP + ENGINE_HELP)
    add_dataset_args(p, metavar="REC")
    p.add_argument("--out", required=True, metavar="CSV", help="output CSV (written when every recording is done)")
    p.add_argument("--exact", action="store_true",
                   help="write masses with 2 decimals (default: truncated to int, as the paper's code)")
    p.add_argument("--exclude", metavar="FILE",
                   help="never select the detections listed in FILE (JSON, format massviz.exclusions/1: entries "
                   "recording id + frame + box, e.g. exported by notebooks/03_failure_cases.ipynb)")
    p.add_argument("--exec-time", choices=["measured", "none"], default="measured",
                   help="'Execution time' column: measured (default) = the pipeline's seconds recorded in the trace "
                   "when its detections were computed (a cached trace keeps them, so re-runs and both engines write "
                   "the same bytes); none = -1, a CSV that depends on the inputs only (fresh runs diff equal)")
    add_pipeline_args(p)
    add_engine_args(p)
    p.set_defaults(func=run)


def apply_exclusions(trace, exclusions):
    """The trace re-selected without the detections the exclusion entries name (matched by recording id, frame and
    box; ``massviz.evaluation.failures.match_exclusions``); entries of this recording that match nothing are reported."""
    from massviz.commands._common import unmatched_line
    from massviz.evaluation.failures import exclude_detections

    trace, unmatched = exclude_detections(trace, exclusions)
    if unmatched:
        print(unmatched_line("estimate", trace, unmatched), file=sys.stderr)
    return trace


def estimate_row(trace, recording, extra, *, exclusions=None, exec_time: str = "measured") -> dict:
    """What a worker sends back for one recording (the CSV row's values and the one-line summary's numbers).

    'Execution time' is the pipeline time recorded in the trace by the run that computed its detections (a trace
    reused from the cache keeps it), so that a re-run and the other engine write the same bytes; ``exec_time="none"``
    writes -1 instead (a CSV that depends on the inputs only)."""
    from massviz.commands._common import flag_warning

    if exclusions is not None:
        trace = apply_exclusions(trace, exclusions)
    seconds = float(trace.timings.get("total", -1.0)) if exec_time == "measured" else -1.0
    detector = trace.detector.get("name", "?") + (f" {trace.detector['precision']}" if "precision" in trace.detector
                                                   else "")
    device = str((getattr(trace, "compute", None) or {}).get("device", ""))
    if device and device != "cpu":  # where it ran, when not on the CPU (e.g. "on cuda:0 (NVIDIA H200)")
        detector += f" on {device}"
    return {"config_id": recording.config_id, "mass_g": float(trace.estimate), "exec_time_s": seconds,
            "k": len(trace.selection), "detections": len(trace.detections), "detector": detector,
            "warning": flag_warning("estimate", trace)}


def _warm_or_build(args, recordings):
    """The warm pipeline (``massviz.commands._warm``: cached traces only, no model loaded, no torch) when every
    recording is unchanged and cached with a model whose id is remembered; else the pipeline built."""
    from massviz.commands._warm import all_cached, build_remembering, warm_pipeline

    warm = warm_pipeline(args) if args.engine == "local" and not args.threads else None
    if warm is not None and recordings and all_cached(warm, recordings):
        return warm.used()
    return build_remembering(args)


def run(args) -> int:
    import functools

    from massviz.commands._runner import exit_status, open_dataset, run_tasks
    from massviz.errors import MassvizError
    from massviz.io.atomic import check_output_file
    from massviz.io.challenge_csv import write_challenge_csv

    check_output_file(args.out, "--out")
    tasks, failed, recordings, on_error = open_dataset(args)
    seen = {}
    for rec in recordings.values():  # one CSV row per recording: say so now, not after the work
        if (first := seen.setdefault(rec.config_id, rec.path)) != rec.path:
            raise MassvizError(f"configuration id {rec.config_id} is also the id of {first} (one CSV row per id; "
                               "set distinct ids or config_ids in meta.json)", rec.path)
    exclusions = None
    if args.exclude:
        from massviz.evaluation.failures import load_exclusions

        exclusions = load_exclusions(args.exclude)
    pipeline = _warm_or_build(args, list(recordings.values()))
    collect = functools.partial(estimate_row, exclusions=exclusions, exec_time=args.exec_time)
    outcomes = run_tasks(args, "estimate", pipeline, tasks, failed, on_error, collect, recordings=recordings)
    rows = []
    for o in outcomes:
        if o.ok:
            rows.append(o.value)
            if o.value.get("warning"):  # flagged chosen patches: one line per recording
                print(o.value["warning"], file=sys.stderr)
        else:  # a failed recording: "not estimated", nothing measured
            rec = recordings.get(o.index)
            rows.append({"config_id": rec.config_id if rec is not None else o.id, "mass_g": -1, "exec_time_s": -1})
    if len(outcomes) == 1 and outcomes[0].ok:
        v = outcomes[0].value
        mass = "not estimated" if v["mass_g"] < 0 else f"{v['mass_g']:.1f} g"
        print(f"{outcomes[0].id}: {mass} "
              f"(K={v['k']}, {v['detections']} detections, {v['detector']}, {outcomes[0].seconds:.1f} s)",
              file=sys.stderr)
    write_challenge_csv(Path(args.out), rows, exact=args.exact)
    done = sum(r["mass_g"] >= 0 for r in rows)
    failed_n = sum(not o.ok for o in outcomes)
    print(f"wrote {args.out}: {len(rows)} recordings, {done} estimated"
          + (f", {failed_n} failed (see above{' and ' + args.report if args.report else ''})" if failed_n else ""),
          file=sys.stderr)
    return exit_status(outcomes)
