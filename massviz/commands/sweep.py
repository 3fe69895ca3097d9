"""``massviz sweep``: the CORSMAL score of every (threshold, K) pair, from cached traces."""
from __future__ import annotations

import argparse
import sys

from massviz.commands._common import PIPELINE_HELP, add_dataset_args, add_pipeline_args
from massviz.commands._runner import ENGINE_HELP, add_engine_args


def register(sub) -> None:
    p = sub.add_parser(
        "sweep", help="score every (detection threshold, K) pair from cached detections",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Score every (threshold, K) pair over a dataset without running any detector: the "
        "detections cached at the lowest threshold of the grid serve every higher threshold, and each detection "
        "already carries its mass prediction. Recordings missing from the cache are processed once (at the "
        "lowest threshold) first, unless --cached-only; --engine says where (when every recording is cached, the cache "
        "is read in this process whatever the engine). A dataset whose recordings are unchanged since they were last "
        "opened and all cached is swept from the cache's selection indexes alone: no recording opened, no model "
        "loaded (docs/datasets.md: Speed at dataset scale).",
        epilog="examples:\n"
        "  massviz sweep data_samples --detector depth --threshold 0.3:0.9:0.05 --k 1:10 --plot heatmap.png\n"
        "  massviz sweep /data/CCM/train --annotations Val_annotations.csv --csv sweep.csv\n"
        "  massviz sweep /data/CCM/train --engine ray --ray-address auto --threshold 0.3:0.9:0.05\n"
        + PIPELINE_HELP + ENGINE_HELP)
    add_dataset_args(p, metavar="DATASET")
    p.add_argument("--annotations", metavar="ANN.csv",
                   help="CCM annotation CSV (default: ground truth from each recording's meta.json)")
    p.add_argument("--threshold", default="0.4:0.9:0.05", metavar="A:B:STEP",
                   help="detection thresholds (default: 0.4:0.9:0.05; a list a,b,c or one value also works)")
    p.add_argument("--k", default="1:10", metavar="A:B", help="K values (default: 1:10)")
    p.add_argument("--classes", metavar="MAP", help="container→class mapping (as massviz score --classes)")
    p.add_argument("--plot", metavar="PNG", help="write a threshold × K heatmap")
    p.add_argument("--csv", metavar="OUT", help="write the table as CSV")
    p.add_argument("--cached-only", action="store_true",
                   help="fail instead of running the detector for recordings not in the cache")
    add_pipeline_args(p, selection=False)
    add_engine_args(p)
    p.set_defaults(func=run)


def slim_trace(trace, recording, extra):
    """What a worker sends back for one recording: the trace without masks and patches (the sweep needs the
    detections' d, score and prediction only)."""
    import dataclasses

    dets = trace.detections
    n = len(dets)
    return dataclasses.replace(trace, detections=dataclasses.replace(dets, masks=[None] * n, patches=[None] * n))


def run(args) -> int:
    from massviz.commands._runner import open_dataset, run_tasks
    from massviz.commands._warm import build_remembering
    from massviz.core.detector import detector_info
    from massviz.core.selection import Selection
    from massviz.errors import MassvizError
    from massviz.evaluation.metrics import default_class_of, parse_class_map
    from massviz.evaluation.sweep import MAX_SWEEP_PAIRS, parse_range
    from massviz.io.atomic import check_output_file
    from massviz.io.ccm_annotations import read_annotations

    thresholds = parse_range(args.threshold, float, "--threshold")
    ks = parse_range(args.k, int, "--k")
    try:  # every value of the grid as the pipeline's options are checked
        for name, values in (("threshold", thresholds), ("k", ks)):
            for v in values:
                Selection.check(name, v, f"--{name}")
    except ValueError as err:
        raise MassvizError(str(err)) from None
    if len(thresholds) * len(ks) > MAX_SWEEP_PAIRS:
        raise MassvizError(f"--threshold x --k is {len(thresholds)} x {len(ks)} = {len(thresholds) * len(ks)} pairs "
                           f"(at most {MAX_SWEEP_PAIRS}); use larger steps")
    for option in ("csv", "plot"):
        if getattr(args, option):
            check_output_file(getattr(args, option), f"--{option}")
    ann = read_annotations(args.annotations) if args.annotations else None
    class_of = parse_class_map(args.classes) if args.classes else default_class_of
    args.k = 1
    indexes = _warm_indexes(args, min(thresholds))
    if indexes is not None:  # every recording unchanged and in the cache: no recording opened, no model loaded
        return _report_table(args, indexes, thresholds, ks, ann, class_of, [])
    tasks, failed, opened, on_error = open_dataset(args)
    recordings = [opened[t.index] for t in tasks]
    pipeline = build_remembering(args, threshold=min(thresholds))
    cache, selection = pipeline.cache, pipeline.selection
    info = detector_info(pipeline.detector)
    missing = [r.id for r in recordings if cache is None or
               cache.lookup(r, info, selection.stride, selection.threshold) is None]
    if args.cached_only and missing:
        raise MassvizError(f"{len(missing)} recording(s) not in the cache at threshold <= {min(thresholds)} "
                           f"(first: {missing[0]}); run without --cached-only")
    if not missing and args.engine != "local":  # nothing to detect: reading the cache here beats starting workers
        if not args.quiet:
            print("massviz sweep: every recording is in the cache; reading it here (--engine local)", file=sys.stderr)
        args.engine, args.workers, args.ray_address = "local", None, None
    outcomes = run_tasks(args, "sweep", pipeline, tasks, failed, on_error, slim_trace, desc="traces",
                         recordings=opened)
    return _report_table(args, [o.value for o in outcomes if o.ok], thresholds, ks, ann, class_of, outcomes)


def _warm_indexes(args, threshold: float):
    """The selection index of every recording's cached trace, found from file identities alone
    (``massviz.commands._warm``), or None (then the recordings are opened and the pipeline built)."""
    from massviz.commands._warm import cache_root, cached_indexes, locate_all, warm_pipeline
    from massviz.io.recording import find_recordings

    pipeline = warm_pipeline(args, threshold)
    if pipeline is None:
        return None
    paths = [p for path in args.recordings for p in find_recordings(path, view=args.view)]
    recordings = locate_all(paths, cache_root(args), getattr(args, "allow_partial", False))
    if not recordings:
        return None
    indexes = cached_indexes(pipeline, recordings)
    if indexes is not None:
        pipeline.used()
    if indexes is not None and args.report:
        from massviz.runners.dataset import Outcome, write_report

        write_report(args.report, [Outcome(i, r.id, str(r.path), "cached") for i, r in enumerate(recordings)],
                     command="sweep", engine="local", ray_address=None, on_error=args.on_error or "skip",
                     workers=0, threads=0, seconds=0.0, stopped=False)
    return indexes


def _report_table(args, traces, thresholds, ks, ann, class_of, outcomes) -> int:
    from pathlib import Path

    from massviz.commands._runner import exit_status
    from massviz.errors import MassvizError
    from massviz.evaluation.sweep import best_pair, sweep
    from massviz.io.atomic import atomic_path
    from massviz.io.untrusted import write_csv

    if not traces:
        raise MassvizError("no recording could be processed (see the errors above)")
    table = sweep(traces, thresholds, ks, ann, class_of)
    grid = table.pivot(index="threshold", columns="k", values="score")
    print(f"CORSMAL score (%) over {int(table['recordings'].iloc[0])} recordings; rows: threshold, columns: K")
    print(grid.to_string(float_format=lambda v: f"{v:6.2f}"))
    best = best_pair(table)
    print(f"best: {best['score']:.2f} % at threshold {best['threshold']:.2f}, K {int(best['k'])} "
          f"({int(best['estimated'])} estimated)")
    if args.csv:
        with atomic_path(Path(args.csv)) as tmp:
            write_csv(table, tmp, float_format="%.4f")
    if args.plot:
        from massviz.views.score_plot import plot_heatmap

        plot_heatmap(table, args.plot)
    if len(traces) < len(outcomes):
        print(f"massviz sweep: {len(outcomes) - len(traces)} failed recording(s) left out of the table",
              file=sys.stderr)
    return exit_status(outcomes)
