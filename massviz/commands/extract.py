"""``massviz extract``: the K selected patches of every recording, labelled, as a patch set to train on."""
from __future__ import annotations

import argparse
import sys

from massviz.commands._common import PIPELINE_HELP, add_dataset_args, add_pipeline_args


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
        "  massviz extract data_samples --detector depth --out patches/\n" + PIPELINE_HELP)
    add_dataset_args(p, metavar="DATASET")
    p.add_argument("--out", required=True, metavar="PATCHES", help="output folder (must not exist unless --force)")
    p.add_argument("--annotations", metavar="CSV", help="CCM annotation CSV (default: each recording's meta.json)")
    p.add_argument("--force", action="store_true", help="replace an existing PATCHES folder")
    add_pipeline_args(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from massviz.commands._common import build
    from massviz.io.recording import collect_recordings
    from massviz.evaluation.metrics import read_annotations
    from massviz.training.train import check_extract, extract_patches

    from massviz.io.atomic import check_output_dir

    check_output_dir(args.out, "--out")
    recordings = collect_recordings(args.recordings, args.view, allow_partial=args.allow_partial)
    table = read_annotations(args.annotations) if args.annotations else None
    labels = check_extract(recordings, args.out, table, args.annotations, force=args.force)
    result = extract_patches(recordings, labels, build(args), args.out, progress=not args.quiet)
    if result.empty:
        print(f"no patch (no detection with depth) in {len(result.empty)} recording(s): "
              f"{', '.join(result.empty[:10])}{' ...' if len(result.empty) > 10 else ''}", file=sys.stderr)
    print(f"wrote {result.out}: {result.n_patches} patches from {result.n_recordings - len(result.empty)} of "
          f"{result.n_recordings} recordings", file=sys.stderr)
    return 0
