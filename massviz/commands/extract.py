"""``massviz extract``: the K selected patches of every recording, labelled, as a patch set to train on."""
from __future__ import annotations

import argparse
import functools
import sys

from massviz.commands._common import PIPELINE_HELP, add_dataset_args, add_pipeline_args
from massviz.commands._runner import ENGINE_HELP, add_engine_args


def register(sub) -> None:
    p = sub.add_parser(
        "extract", help="save the K selected patches of every recording, labelled, for training",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Run detection and the K-nearest selection over every recording (reusing cached traces) and "
        "write a patch set: OUT/images/<recording>_<rank>.png (RGB crops) and OUT/index.csv (file, recording, "
        "rank, frame, a, b, d, mass_g, container_id, dimensions, class, score, box, source, flagged, cues). Each patch gets its "
        "recording's annotation: its row in --annotations (CCM annotation CSV, matched on 'id'), else the "
        "container.mass_g of the recording's meta.json. The set is written to a temporary folder and moved into "
        "place when complete.",
        epilog="examples:\n  massviz extract /data/CCM/train --annotations ccm_train_annotation.csv --out patches/\n"
        "  massviz extract data_samples --detector depth --out patches/\n"
        "  massviz extract /data/CCM/train --engine ray --ray-address auto --report run.json --out patches/\n"
        + PIPELINE_HELP + ENGINE_HELP)
    add_dataset_args(p, metavar="DATASET")
    p.add_argument("--out", required=True, metavar="PATCHES", help="output folder (must not exist unless --force)")
    p.add_argument("--annotations", metavar="CSV", help="CCM annotation CSV (default: each recording's meta.json)")
    p.add_argument("--force", action="store_true",
                   help="replace an existing patch set in PATCHES (a folder holding anything else, or a symlink, is "
                   "refused, never emptied)")
    p.add_argument("--exclude", metavar="FILE",
                   help="never select the detections listed in FILE (massviz.exclusions/1 JSON, as for estimate; "
                   "e.g. written by notebooks 03 and 04)")
    p.add_argument("--skip-flagged", action="store_true",
                   help="leave out the chosen patches flagged as probably not the container (index.csv column "
                   "'flagged'; by default they are kept, flagged, with a warning line per recording)")
    add_pipeline_args(p)
    add_engine_args(p)
    p.set_defaults(func=run)


def collect_patches(trace, recording, label, *, exclusions=None, skip_flagged: bool = False) -> dict:
    """What a worker sends back for one recording: ``files`` (its patches as PNG bytes with their index rows, the
    flagged ones left out with ``skip_flagged``), ``warning`` (the flags' line) and ``notes`` (unmatched exclusions)."""
    from massviz.commands._common import flag_warning, unmatched_line
    from massviz.evaluation.failures import exclude_detections
    from massviz.io.patch_set import patch_files

    notes = []
    if exclusions:
        trace, unmatched = exclude_detections(trace, exclusions)
        if unmatched:
            notes.append(unmatched_line("extract", trace, unmatched))
    files = patch_files(trace, label)
    warning = flag_warning("extract", trace)
    if skip_flagged:
        files = [f for f in files if not f[2]["flagged"]]
        warning = warning and f"{warning} (left out: --skip-flagged)"
    return {"files": files, "warning": warning, "notes": notes}


def run(args) -> int:
    from massviz.commands._common import build
    from massviz.commands._runner import exit_status, open_dataset, run_tasks
    from massviz.io.atomic import check_output_dir
    from massviz.io.ccm_annotations import read_annotations
    from massviz.io.patch_set import check_extract, write_patch_set
    from massviz.runners.dataset import Task

    check_output_dir(args.out, "--out")
    tasks, failed, recordings, on_error = open_dataset(args)
    table = read_annotations(args.annotations) if args.annotations else None
    labels = check_extract([recordings[t.index] for t in tasks], args.out, table, args.annotations,
                           force=args.force)
    tasks = [Task(t.index, t.path, t.id, label) for t, label in zip(tasks, labels)]
    exclusions = None
    if args.exclude:
        from massviz.evaluation.failures import load_exclusions

        exclusions = load_exclusions(args.exclude)
    collect = functools.partial(collect_patches, exclusions=exclusions, skip_flagged=args.skip_flagged)
    outcomes = run_tasks(args, "extract", build(args), tasks, failed, on_error, collect, desc="extract",
                         recordings=recordings)
    for o in outcomes:
        if o.ok:
            for line in [*o.value["notes"], *([o.value["warning"]] if o.value["warning"] else [])]:
                print(line, file=sys.stderr)
    result = write_patch_set(args.out, [(o.id, o.value["files"]) for o in outcomes if o.ok],
                             n_recordings=len(outcomes))
    if result.empty:
        print(f"no patch (no detection with depth) in {len(result.empty)} recording(s): "
              f"{', '.join(result.empty[:10])}{' ...' if len(result.empty) > 10 else ''}", file=sys.stderr)
    n_failed = sum(not o.ok for o in outcomes)
    print(f"wrote {result.out}: {result.n_patches} patches from "
          f"{result.n_recordings - len(result.empty) - n_failed} of {result.n_recordings} recordings"
          + (f" ({n_failed} failed)" if n_failed else ""), file=sys.stderr)
    return exit_status(outcomes)
