"""``massviz score``: the CORSMAL challenge score of prediction CSVs, per class and per container, optionally plotted."""
from __future__ import annotations

import argparse
import json
import sys
import textwrap
from pathlib import Path

from massviz.errors import MassvizError


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "score",
        help="score challenge prediction CSVs against CCM annotations (overall, per class, per container)",
        description=textwrap.fill(
            "Print the CORSMAL challenge score s (%) of each prediction CSV, then per-class and per-container "
            "tables of score and mean relative error ε. s averages exp(-ε) over ALL annotated recordings, a "
            "recording missing from the predictions or predicted negative (-1) counting 0; mean ε is over the "
            "estimated recordings only. Predicted recordings absent from the annotations are ignored and listed. "
            "Several PRED files are paired with the --annotations files in order, or all with a single one.", 100),
        epilog="examples:\n"
        "  massviz score VAL.csv --annotations Val_annotations.csv --json val_score.json\n"
        "  massviz score F1.csv F2.csv F3.csv VAL.csv --annotations test_annotations_fold0.csv "
        "test_annotations_fold1.csv test_annotations_fold2.csv Val_annotations.csv --labels F1 F2 F3 VAL "
        "--plot fig4.png",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("predictions", nargs="+", metavar="PRED.csv", help="CORSMAL challenge prediction CSV(s)")
    parser.add_argument("--annotations", nargs="+", required=True, metavar="ANN.csv",
                        help="CCM annotation CSV(s): one for all PRED files, or one per PRED file, in order")
    parser.add_argument("--labels", nargs="+", metavar="LABEL",
                        help="a name per PRED file for the output and the plot (default: the file names)")
    parser.add_argument("--classes", metavar="SPEC",
                        help="container→class mapping, '1=cup,2=cup,3=cup,...' or a JSON file {\"1\": \"cup\", ...} "
                        "(default: cup 1-3, glass 4-6, box 7-9)")
    parser.add_argument("--json", metavar="OUT.json",
                        help="also write the report(s) as JSON: one object, or a list of them for several PRED files")
    parser.add_argument("--plot", metavar="OUT.png",
                        help="also draw the paper's Fig. 4 analogue: per-class and total score (top) and mean ε "
                        "(bottom), one group of bars per PRED file")
    parser.add_argument("--only-predicted", action="store_true",
                        help="score over the annotated recordings the predictions name only (default: over every "
                        "annotated recording, a missing one counting 0; when predictions cover fewer recordings than "
                        "the annotations hold, a warning says so)")
    parser.set_defaults(func=run)


def _pairs(args: argparse.Namespace) -> list[tuple[str, str, str]]:
    """(label, predictions, annotations) for each PRED file."""
    preds, anns = args.predictions, args.annotations
    if len(anns) == 1:
        anns = anns * len(preds)
    elif len(anns) != len(preds):
        raise MassvizError(f"{len(preds)} prediction files but {len(anns)} annotation files "
                           "(give one annotation file for all, or one per prediction file)")
    labels = args.labels or [Path(p).stem for p in preds]
    if len(labels) != len(preds):
        raise MassvizError(f"{len(preds)} prediction files but {len(labels)} labels")
    return list(zip(labels, preds, anns))


def run(args: argparse.Namespace) -> int:
    from massviz.evaluation.metrics import PRED_ID, default_class_of, parse_class_map, read_predictions, score
    from massviz.io.atomic import atomic_path, check_output_file
    from massviz.io.ccm_annotations import ANN_ID, read_annotations
    from massviz.io.untrusted import json_safe

    for option in ("json", "plot"):
        if getattr(args, option):
            check_output_file(getattr(args, option), f"--{option}")
    class_of = parse_class_map(args.classes) if args.classes else default_class_of
    pairs = _pairs(args)
    annotations = {path: read_annotations(path) for path in dict.fromkeys(ann for _, _, ann in pairs)}
    reports, notes = [], []  # notes go to stderr at the end: an error before then stays the only line
    for label, pred_path, ann_path in pairs:
        pred, ann = read_predictions(pred_path), annotations[ann_path]
        covered = ann[ANN_ID].isin(pred[PRED_ID])
        if not covered.all():
            if args.only_predicted:
                if not covered.any():
                    raise MassvizError(f"--only-predicted: none of the recordings {pred_path} predicts is annotated "
                                       f"in {ann_path}")
                notes.append(f"massviz score: {label}: scored the {int(covered.sum())} predicted of the {len(ann)} "
                             f"annotated recordings (--only-predicted)")
                ann = ann[covered]
            else:
                notes.append(f"massviz score: warning: {label}: {pred_path} predicts {int(covered.sum())} of the "
                             f"{len(ann)} recordings in {ann_path}; the {int((~covered).sum())} missing count 0 in "
                             "the score (score the predicted ones only with --only-predicted)")
        try:
            reports.append(score(pred, ann, class_of))
        except MassvizError as err:  # a container without a class: name the annotations (or the mapping)
            if err.path is not None:
                raise
            raise MassvizError(str(err), args.classes if args.classes and "mapping" in str(err) else ann_path) \
                from None

    for (label, pred, ann), report in zip(pairs, reports):
        if len(pairs) > 1:
            print(f"== {label}: {pred} vs {ann}")
        print(report.format())
        if len(pairs) > 1:
            print()
    if args.json:
        docs = [{"label": label, "predictions": pred, "annotations": ann, **report.to_dict()}
                for (label, pred, ann), report in zip(pairs, reports)]
        with atomic_path(args.json) as tmp:
            tmp.write_text(json.dumps(json_safe(docs[0] if len(docs) == 1 else docs), indent=1, allow_nan=False)
                           + "\n")
        print(f"wrote {args.json}")
    if args.plot:
        from massviz.views.score_plot import plot_score_analysis, save_figure  # matplotlib only when plotting

        save_figure(plot_score_analysis(reports, [label for label, _, _ in pairs]), args.plot)
        print(f"wrote {args.plot}")
    for note in notes:
        print(note, file=sys.stderr)
    return 0
