"""``massviz cloud``: point clouds (.ply) and the measured size of the chosen detections."""
from __future__ import annotations

import argparse
import sys

from massviz.commands._3d import add_3d_args
from massviz.commands._common import PIPELINE_HELP


def register(sub) -> None:
    p = sub.add_parser(
        "cloud", help="write the scene's and the detections' point clouds (.ply) and measure the chosen containers",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Run (or reuse from the cache) the pipeline on one recording, back-project through Open3D with "
        "the recording's intrinsics and write, into DIR: scene_<frame>.ply for each frame with a chosen detection, "
        "detection_<id>.ply for every detection of those frames (id = index in the trace), chosen_<rank>.ply for "
        "the chosen ones, and measurements.csv / measurements.json: height, width and depth (mm) of each chosen "
        "detection from its cloud, with its oriented box, compared with the container's annotation when known "
        "(the recording's meta.json, or --annotations). Points are metres in the camera frame: x right, y down, "
        "z forward (OpenCV/RDF). A recording without intrinsics is an error (one line, exit code 2, nothing written).",
        epilog="examples:\n  massviz cloud data_samples/box_handover --detector depth --out box_3d\n"
        "  massviz cloud /data/CCM/test/view3/rgb/000012.mp4 --annotations ann.csv --out ccm12\n" + PIPELINE_HELP)
    add_3d_args(p)
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    p.add_argument("--all-frames", action="store_true",
                   help="write every processed frame's scene and detections (default: frames of chosen ones)")
    p.add_argument("--annotations", metavar="CSV",
                   help="CCM annotation CSV: compare with the row of this recording's id (width at the top/bottom, "
                   "height)")
    p.set_defaults(func=run)


def measurement_rows(trace, gt: dict | None) -> list[dict]:
    """One flat row per measurement, with the annotated size and relative errors when known."""
    from massviz.measure3d.geometry import compare

    rows = []
    for m in trace.measurements:
        row = {"rank": m.rank, "detection": m.detection, "frame": m.frame, "height_mm": m.height_mm,
               "width_mm": m.width_mm, "depth_mm": m.depth_mm, "n_points": m.n_points,
               "center_x_m": m.center[0], "center_y_m": m.center[1], "center_z_m": m.center[2]}
        row.update({f"gt_{k}": (gt or {}).get(k) for k in ("height_mm", "width_top_mm", "width_bottom_mm")})
        row.update(compare(m, gt))
        rows.append(row)
    return rows


def run(args) -> int:
    import json

    import pandas as pd

    from massviz.commands._3d import measured_trace
    from massviz.errors import MassvizError
    from massviz.io.atomic import atomic_path, check_output_dir, staged_files
    from massviz.io.recording import open_recording
    from massviz.io.untrusted import json_safe, write_csv
    from massviz.measure3d.geometry import annotation_size, ground_truth_size
    from massviz.measure3d.settings import skip_reason
    from massviz.views.open3d_view import write_ply

    out = check_output_dir(args.out, "--out")
    # clouds need the camera intrinsics: without them, one error line naming the recording (exit 2) before any
    # work, nothing written
    reason = skip_reason(open_recording(args.recording, allow_partial=args.allow_partial))
    if reason:
        what = reason.split(": ", 1)[-1].split(", so no 3D")[0]  # "no camera intrinsics (where they would be)"
        raise MassvizError(f"{what}: massviz cloud needs them, nothing written", args.recording)
    rec, trace, measure = measured_trace(args)
    est = "not estimated" if trace.estimate < 0 else f"{trace.estimate:.1f} g"
    gt = ground_truth_size(rec.meta)
    if args.annotations:
        from massviz.io.ccm_annotations import read_annotations

        gt = annotation_size(read_annotations(args.annotations), rec.config_id) or gt
    frames = [int(f) for f in trace.frames] if args.all_frames else None
    # every file goes to a hidden folder inside OUT first and is moved in at the end: a full disk or a signal
    # leaves OUT as it was (and no OUT at all when this run created it)
    with staged_files(out) as stage:
        written = write_ply(stage, measure.ply_clouds(trace, frames=frames))
        rows = measurement_rows(trace, gt)
        columns = list(rows[0]) if rows else ["rank", "detection", "frame", "height_mm", "width_mm", "depth_mm"]
        with atomic_path(stage / "measurements.csv") as tmp:
            write_csv(pd.DataFrame(rows, columns=columns), tmp)
        payload = {"recording": rec.id, "estimate_g": trace.estimate, "ground_truth": gt,
                   "axes": "camera frame, metres: x right, y down, z forward (OpenCV/RDF)",
                   "measurements": [{**m.to_dict(), **row} for m, row in zip(trace.measurements, rows)],
                   "files": written, "not_written": {n: "no depth points" for n in written.empty}}
        with atomic_path(stage / "measurements.json") as tmp:
            tmp.write_text(json.dumps(json_safe(payload), indent=1, allow_nan=False) + "\n")
    for row in rows:
        line = (f"chosen {row['rank']} (detection {row['detection']}, frame {row['frame']}): height "
                f"{row['height_mm']:.0f} mm, width {row['width_mm']:.0f} mm, depth {row['depth_mm']:.0f} mm "
                f"({row['n_points']} points)")
        if gt:
            line += (f" | annotated height {gt['height_mm']:.0f} mm ({row['height_err_pct']:+.1f}%), width "
                     f"{gt['width_top_mm']:.0f}/{gt['width_bottom_mm']:.0f} mm top/bottom "
                     f"({row['width_err_pct']:+.1f}% vs the larger)")
        print(line)
    print(f"{rec.id}: {est}; wrote {written.describe()} and measurements.csv/.json to {out}", file=sys.stderr)
    return 0
