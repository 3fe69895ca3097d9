"""``massviz log``: run the pipeline on one recording and log every stage to Rerun."""
from __future__ import annotations

import argparse
import sys

from massviz.commands._common import PIPELINE_HELP, add_pipeline_args
from massviz.commands._runner import ENGINE_HELP, add_engine_args


def register(sub) -> None:
    p = sub.add_parser(
        "log", help="run one recording and log every stage to Rerun (.rrd file or live viewer)",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Run the pipeline on one recording (a massviz folder, a CCM .mp4 or a RealSense .db3/.bag) and "
        "log the trace to "
        "Rerun: frames, depth, detections, masks, point cloud, the chosen patches as the model saw them, "
        "per-patch predictions, the estimate, the decisions and the stage timings (entity tree in docs/entity-tree.md). "
        "A recording without depth (no depth/ folder) is logged RGB only: what the detector finds and its tracks, "
        "no mass (give --detector nanodet or maskrcnn; the depth detector needs depth).",
        epilog="examples:\n  massviz log data_samples/cup_handover --rrd cup.rrd && massviz view cup.rrd\n"
        "  massviz log data_samples/glass_handover --spawn --k 3\n"
        "  massviz log side_view_rgb_only/ --detector nanodet --rrd side.rrd   # no depth: detections and tracks\n"
        "  massviz log data_samples --rrd-dir out/samples && massviz serve out/samples\n"
        "  massviz log /data/CCM/train --view 3 --annotations ann.csv --rrd-dir out/train --engine ray\n"
        + PIPELINE_HELP + ENGINE_HELP)
    p.add_argument("recording", metavar="REC", help="recording folder, CCM video path or RealSense file (.db3, .bag); "
                   "with --rrd-dir also a CCM dataset root or a folder of recordings")
    out = p.add_argument_group("output (one of them is required)")
    out.add_argument("--rrd-dir", metavar="OUT", help="a dataset: one .rrd per recording of REC (a dataset root or "
                     "folder of recordings) with recording properties (id, class, ground truth, estimate, error, "
                     "score, flags, settings), plus OUT/index.csv and OUT/patches.csv; browse with 'massviz serve "
                     "OUT'. Light recordings by default (overlays, chosen patches, predictions, decisions, the best "
                     "frame; the source frames are referenced, not copied); --full logs everything")
    out.add_argument("--rrd", metavar="OUT.rrd", help="write the Rerun recording to this file")
    out.add_argument("--spawn", action="store_true", help="spawn (or connect to) a Rerun viewer")
    p.add_argument("--video", choices=["auto", "asset", "images"], default="auto",
                   help="how an mp4 input is logged: 'asset' = the file once as a Rerun video asset with per-frame "
                   "references (not re-encoded); 'images' = a JPEG per processed frame; 'auto' (default) = asset "
                   "when Rerun can decode the codec, else images (CCM's MPEG-4 Part 2 'mp4v' it cannot)")
    p.add_argument("--points", action="store_true",
                   help="also log /world/points: every 4th pixel's depth back-projected and coloured by RGB (a larger "
                   "recording); by default the 3D view shows the depth image back-projected by Rerun itself")
    p.add_argument("--ply", metavar="DIR", help="also write the chosen frames' point clouds (.ply) into DIR "
                   "(as 'massviz cloud' does)")
    ds = p.add_argument_group("dataset (--rrd-dir)")
    ds.add_argument("--full", action="store_true", help="with --rrd-dir: full recordings (every frame, depth, "
                    "masks, 3D), as 'massviz log REC --rrd' writes them")
    ds.add_argument("--view", type=int, default=3, choices=[1, 2, 3, 4],
                    help="camera view of a CCM dataset root (default: 3)")
    ds.add_argument("--annotations", metavar="CSV", help="with --rrd-dir: CCM annotation CSV for the ground truth "
                    "(default: each recording's meta.json)")
    ds.add_argument("--force", action="store_true", help="with --rrd-dir: replace the dataset already in OUT")
    add_pipeline_args(p)
    add_engine_args(p)
    p.set_defaults(func=run)


def run(args) -> int:
    import contextlib
    from pathlib import Path

    from massviz.commands._common import build, flag_warning
    from massviz.errors import MassvizError
    from massviz.io.recording import open_recording
    from massviz.measure3d.stage import MeasureStage
    from massviz.runners.logged import log_run

    if args.rrd_dir:
        from massviz.commands._dataset_log import run_rrd_dir

        return run_rrd_dir(args)
    if not args.rrd and not args.spawn:
        raise MassvizError("say where to log: --rrd OUT.rrd, --spawn or --rrd-dir OUT")
    from massviz.io.atomic import check_output_dir, check_output_file, staged_files

    if args.rrd:
        check_output_file(args.rrd, "--rrd")
    if args.ply:
        check_output_dir(args.ply, "--ply")
    rec = open_recording(args.recording, allow_partial=args.allow_partial, rgb_only=True)
    pipeline = build(args)
    rgb_only = getattr(rec, "rgb_only", False)
    if rgb_only and pipeline.detector.name == "depth":
        raise MassvizError("RGB only (no depth folder): the depth detector has nothing to work on; "
                           "--detector nanodet (or maskrcnn) logs what it finds and its tracks, without mass",
                           rec.path)
    ply_line = []
    # the measure stage makes every cloud once: those the Rerun recording shows (each detection above the threshold,
    # as its frame is processed), the measured sizes and the --ply files are the same clouds
    measure = MeasureStage(rec, clouds="active")

    def write_clouds(trace, stage):
        from massviz.views.open3d_view import write_ply_or_skip

        ply_line.append(write_ply_or_skip(stage, measure.ply_clouds(trace), recording_id=rec.id, skip=measure.skip)
                        .replace(str(stage), str(args.ply)))

    # the .ply files go to a hidden folder moved into --ply at the end, and are written before the .rrd is renamed
    # into place: a failure in either leaves neither (and no --ply folder this run created)
    with staged_files(args.ply) if args.ply else contextlib.nullcontext() as stage:
        # one pass: each frame is logged as the pipeline processes it (a trace from the cache is replayed once)
        trace, stats = log_run(pipeline, rec, rrd=Path(args.rrd) if args.rrd else None, spawn=args.spawn,
                               progress=not args.quiet, video=args.video, points=args.points, measure=measure,
                               before_close=(lambda trace: write_clouds(trace, stage)) if args.ply else None)
    if ply_line:
        print(ply_line[0], file=sys.stderr)
    est = "not estimated" if trace.estimate < 0 else f"{trace.estimate:.1f} g"
    if rgb_only:
        dets = trace.detections
        est = (f"RGB only (no depth): {len(dets)} detections in {len(set(dets.frame.tolist()))} of "
               f"{len(trace.frames)} frames, {len(set(dets.track.tolist()))} tracks logged; no mass (d needs depth)")
    gt = trace.ground_truth_mass
    print(f"{rec.id}: {est}" + (f" (ground truth {gt:.1f} g)" if gt is not None else "")
          + (f"; wrote {args.rrd}" if args.rrd else "") + f" [logging took {stats.get('log_seconds', 0):.1f} s]",
          file=sys.stderr)
    warning = None if rgb_only else flag_warning("log", trace)
    if warning:
        print(warning, file=sys.stderr)
    return 0
