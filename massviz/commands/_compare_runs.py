"""``massviz compare`` on datasets: two runs of every recording side by side (``massviz.evaluation.runs``).

    massviz compare RUN_A/ RUN_B/                               two folders of 'massviz log DATASET --rrd-dir'
                                                                (--rrd-dir: their traces from the trace cache)
    massviz compare DATASET --a "threshold=0.4" --b "k=3"       one dataset, two settings, from the trace cache
"""
from __future__ import annotations

import sys
from pathlib import Path

from massviz.errors import MassvizError

HELP = """
two runs of a dataset (one row per recording, ranked by how much the relative error changed):
  massviz compare RUN_A/ RUN_B/ --out diff.csv --rrd-dir both/
      RUN_A and RUN_B are folders written by 'massviz log DATASET --rrd-dir': the table is made of their index.csv
      and patches.csv (nothing recomputed). --rrd-dir needs each run's traces: they come from the trace cache with
      the settings index.csv records per recording (detector, threshold, k, stride) for the recording at its
      source (absolute, else from the current directory, else from the folder or a folder above it); --weights
      (B: --b-weights) must be the checkpoint of the folder's weights_id; --detector-weights, --precision and
      --replay (B: their --b-* options) as given. A recording the cache cannot serve is processed once and cached;
      each trace's estimate must be the folder's estimate_g. The settings are the folders': --detector,
      --threshold, --b-detector, --b-threshold, --b-k and --b-stride are refused
  massviz compare DATASET --detector depth --a "threshold=0.4" --b "threshold=0.5,k=3" --out diff.parquet \\
      --rrd-dir both/
      DATASET's recordings run twice with the pipeline options, --a and --b overriding them (NAME=VALUE,...:
      detector, threshold, k, stride, weights, detector_weights, precision, replay); from the trace cache when
      there (a higher threshold, another K or other weights never run the detector again). --rrd-dir writes one
      recording per input with both runs (A at the usual paths, B under /b, one timeline) and the properties
      <figure>_a, <figure>_b, delta_<figure> that 'massviz serve' shows in its table
"""


def is_run_folder(path: str) -> bool:
    """A folder written by ``massviz log DATASET --rrd-dir`` (it has an ``index.csv``)."""
    from massviz.io.run_folder import INDEX_NAME

    return Path(path).is_dir() and (Path(path) / INDEX_NAME).is_file()


def wants_runs(args) -> bool:
    """Whether ``massviz compare`` compares two runs of a dataset (--a/--b settings, or two run folders)."""
    return bool(args.a_settings or args.b_settings) or (args.b is not None and is_run_folder(args.a)
                                                        and is_run_folder(args.b))


def _check(args) -> None:
    for name in ("rrd", "json"):
        if getattr(args, name):
            raise MassvizError(f"--{name} compares one recording; for two runs of a dataset use --out TABLE and "
                               "--rrd-dir DIR")
    if args.out and Path(args.out).suffix.lower() not in (".csv", ".parquet"):
        raise MassvizError("--out: the table's file must end in .csv or .parquet", args.out)
    if args.out and Path(args.out).is_dir():
        raise MassvizError("is a directory; give a file path (.csv or .parquet)", args.out)
    if args.rrd_dir and Path(args.rrd_dir).exists() and not Path(args.rrd_dir).is_dir():
        raise MassvizError("--rrd-dir: not a folder", args.rrd_dir)


def _runs(args, b_options=()):
    """(run A, run B) from two folders or from DATASET with --a/--b (``b_options``: the names of compare's
    ``--b-NAME`` options, which B takes too)."""
    from massviz.evaluation.runs import describe_settings, parse_settings, run_from_cache

    if not (args.a_settings or args.b_settings):
        return _folder_runs(args, b_options)
    if args.b is not None:
        raise MassvizError(f"with --a/--b give one dataset, not two ({args.a}, {args.b})")
    from massviz.app import PipelineOptions
    from massviz.io.recording import collect_recordings

    sa = parse_settings(args.a_settings or "", "--a")
    sb = {n: getattr(args, f"b_{n}") for n in b_options if getattr(args, f"b_{n}") is not None}
    sb.update(parse_settings(args.b_settings or "", "--b"))
    if not Path(args.a).exists():
        raise MassvizError("no such dataset folder or recording", args.a)
    recordings = collect_recordings([args.a], allow_partial=args.allow_partial)
    if not recordings:
        raise MassvizError("holds no recording", args.a)
    options = PipelineOptions.from_args(args)
    run_a = run_from_cache(recordings, options, label=describe_settings(sa), progress=not args.quiet, **sa)
    run_b = run_from_cache(recordings, options, label=describe_settings(sb), progress=not args.quiet, **sb)
    return run_a, run_b


#: the pipeline options B may change when two run folders are compared (their settings are the folders')
FOLDER_B_OPTIONS = ("weights", "detector_weights", "precision", "replay")


def _folder_runs(args, b_options=()):
    """(run A, run B) of two run folders; with --rrd-dir each with the traces of the recordings both hold, made
    with the settings the folder records per recording over the pipeline options (B: the ``--b-NAME`` options of
    ``FOLDER_B_OPTIONS`` too), every input checked before any runs."""
    from massviz.app import PipelineOptions
    from massviz.evaluation.runs import load_run, plan_traces, with_traces

    given = [f"--{n}" for n in ("detector", "threshold") if getattr(args, n, None) not in (None, "auto")]
    given += [f"--b-{n}" for n in b_options if n not in FOLDER_B_OPTIONS and getattr(args, f"b_{n}") is not None]
    if given:
        raise MassvizError(f"{given[0].replace('_', '-')}: two run folders record their settings (detector, threshold, "
                           "k, stride: their index.csv)")
    a, b = load_run(args.a), load_run(args.b)
    if not args.rrd_dir:
        return a, b
    ids = [i for i in a.recordings.index if i in b.recordings.index]
    options_a = PipelineOptions.from_args(args)
    options_b = PipelineOptions.from_args(args, **{n: getattr(args, f"b_{n}") for n in FOLDER_B_OPTIONS
                                                   if n in b_options and getattr(args, f"b_{n}") is not None})
    option_a = "--weights" if args.weights else "the default --weights"
    option_b = "--b-weights" if getattr(args, "b_weights", None) else option_a
    plans = [plan_traces(run, options, ids, weights_option=option, allow_partial=args.allow_partial)
             for run, options, option in ((a, options_a, option_a), (b, options_b, option_b))]
    return tuple(with_traces(plan, progress=not args.quiet) for plan in plans)


def run(args, b_options=()) -> int:
    from massviz.evaluation.runs import TIE_G, compare_runs, run_scores, write_table

    _check(args)
    a, b = _runs(args, b_options)
    table = compare_runs(a, b, iou=args.iou)
    scores = run_scores(table)
    out = sys.stdout
    out.write(f"A: {a.label}\nB: {b.label}\n{len(table)} recordings, ranked by the change of the relative error "
              "(B - A):\n")
    cols = ["id", "container_class", "estimate_g_a", "estimate_g_b", "delta_estimate_g", "rel_error_a", "rel_error_b",
            "delta_rel_error", "outcome", "n_patches_changed", "n_flags_appeared", "n_flags_gone"]
    grams, errors = _fixed(1), _fixed(4)
    formats = {"estimate_g_a": grams, "estimate_g_b": grams, "delta_estimate_g": _fixed(1, sign=True),
               "rel_error_a": errors, "rel_error_b": errors, "delta_rel_error": _fixed(4, sign=True)}
    out.write(table[cols].head(args.rows).to_string(index=False, formatters=formats) + "\n")
    if len(table) > args.rows:
        out.write(f"... {len(table) - args.rows} more (--out writes them all)\n")
    out.write(f"(a tie: both estimates within {TIE_G:g} g of each other; estimates in g, errors relative)\n")
    out.write("\nscore per class (%; best: each recording's better run; b better / a better / ties: recordings):\n")
    score_formats = {c: (_fixed(4) if c.startswith("mean") else _fixed(2)) for c in scores.columns
                     if scores[c].dtype.kind == "f"}
    out.write(scores.to_string(formatters=score_formats) + "\n")
    if args.out:
        write_table(table, args.out)
        print(f"wrote {args.out} ({len(table)} rows)", file=sys.stderr)
    if args.rrd_dir:
        n = write_rrd_dir(a, b, table, args.rrd_dir, iou=args.iou)
        print(f"wrote {n} recording(s) with both runs to {args.rrd_dir} (see them: massviz serve {args.rrd_dir})",
              file=sys.stderr)
    return 0


def _fixed(places: int, sign: bool = False):
    """A number with ``places`` decimals, as the estimates are printed: "-0.0" printed as "0.0", NaN as "-"."""
    def fmt(v) -> str:
        if v is None or v != v:
            return "-"
        v = round(float(v), places) + 0.0  # + 0.0: no negative zero
        return f"{v:+.{places}f}" if sign and v != 0 else f"{v:.{places}f}"
    return fmt


def write_rrd_dir(a, b, table, out_dir, *, iou: float = 0.5) -> int:
    """One two-run recording per recording both runs hold (``massviz.views.rerun_runs``) and ``comparison.csv``."""
    from massviz.evaluation.compare import compare_traces
    from massviz.evaluation.runs import write_table
    from massviz.views.rerun_runs import COMPARISON_NAME, row_markdown, write_two_runs

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    traces_b = {t.recording.id: t for t in b.traces}
    labels = (a.label, b.label)
    n = 0
    for trace_a, recording in zip(a.traces, a.recordings_of):
        trace_b = traces_b.get(trace_a.recording.id)
        if trace_b is None:
            continue
        report = compare_traces(trace_a, trace_b, iou=iou, labels=labels).table()
        row = table.loc[trace_a.recording.id].to_dict()
        write_two_runs(trace_a, trace_b, recording, out_dir, row, labels, row_markdown(row, labels, report))
        n += 1
    write_table(table, out_dir / COMPARISON_NAME)
    return n


__all__ = ["HELP", "is_run_folder", "wants_runs", "run", "write_rrd_dir"]
