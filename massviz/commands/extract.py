"""``massviz extract``: the K selected patches of every recording, labelled, as a patch set to train on."""
from __future__ import annotations

import argparse
import sys

from massviz.commands._common import PIPELINE_HELP, add_dataset_args, add_pipeline_args
from massviz.commands._runner import ENGINE_HELP, add_engine_args


def register(sub) -> None:
    p = sub.add_parser(
        "extract", help="save the K selected patches of every recording, labelled, for training",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Run detection and the K-nearest selection over every recording (reusing cached traces) and "
        "write a patch set: OUT/images/<recording>_<rank>.png (RGB crops) and OUT/index.csv (file, recording, "
        "rank, frame, a, b, d, mass_g, container_id, dimensions, class, score, box, source). Each patch gets its "
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
    p.add_argument("--force", action="store_true", help="replace an existing PATCHES folder")
    add_pipeline_args(p)
    add_engine_args(p)
    p.set_defaults(func=run)


def collect_patches(trace, recording, label):
    """What a worker sends back for one recording: its patches as PNG bytes with their index rows."""
    from massviz.training.train import patch_files

    return patch_files(trace, label)


def run(args) -> int:
    from massviz.commands._common import build
    from massviz.commands._runner import exit_status, open_dataset, run_tasks
    from massviz.evaluation.metrics import read_annotations
    from massviz.runners.dataset import Task
    from massviz.training.train import check_extract, write_patch_set

    from massviz.io.atomic import check_output_dir

    check_output_dir(args.out, "--out")
    tasks, failed, recordings, on_error = open_dataset(args)
    table = read_annotations(args.annotations) if args.annotations else None
    labels = check_extract([recordings[t.index] for t in tasks], args.out, table, args.annotations,
                           force=args.force)
    tasks = [Task(t.index, t.path, t.id, label) for t, label in zip(tasks, labels)]
    outcomes = run_tasks(args, "extract", build(args), tasks, failed, on_error, collect_patches, desc="extract")
    result = write_patch_set(args.out, [(o.id, o.value) for o in outcomes if o.ok], n_recordings=len(outcomes))
    if result.empty:
        print(f"no patch (no detection with depth) in {len(result.empty)} recording(s): "
              f"{', '.join(result.empty[:10])}{' ...' if len(result.empty) > 10 else ''}", file=sys.stderr)
    n_failed = sum(not o.ok for o in outcomes)
    print(f"wrote {result.out}: {result.n_patches} patches from "
          f"{result.n_recordings - len(result.empty) - n_failed} of {result.n_recordings} recordings"
          + (f" ({n_failed} failed)" if n_failed else ""), file=sys.stderr)
    return exit_status(outcomes)
