"""``massviz baseline``: the paper's M4 (random) and M5 (average) baselines as challenge prediction CSVs."""
from __future__ import annotations

import argparse
import textwrap

#: M4's interval in grams, as ``massviz.evaluation.baselines.RANDOM_RANGE_G`` (which a test keeps equal); stated here
#: so that ``massviz --help`` does not load pandas.
RANDOM_RANGE_G = (1.0, 351.0)


def register(subparsers) -> None:
    lo, hi = (int(v) for v in RANDOM_RANGE_G)
    parser = subparsers.add_parser(
        "baseline",
        help="write the paper's random (M4) or average (M5) baseline predictions",
        description=textwrap.fill(
            f"Write a CORSMAL challenge prediction CSV for every recording of --annotations. 'random' (M4) draws "
            f"each container mass uniformly in [{lo}, {hi}] g with Python's Mersenne Twister (random.Random(SEED)), "
            f"in the order of the annotation file; 'average' (M5) predicts the mean container mass of the --train "
            f"recordings for all of them. As in the paper's code the mass is written truncated to an integer "
            f"(--exact keeps 2 decimals); the other tasks' columns are -1, the execution time 0.", 100),
        epilog="examples:\n"
        "  massviz baseline random --annotations Val_annotations.csv --seed 0 --out M4_val.csv\n"
        "  massviz baseline average --annotations test_annotations_fold0.csv --train train_fold0.csv "
        "--out M5_fold0.csv\n"
        "  massviz score M4_val.csv --annotations Val_annotations.csv",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("method", choices=("random", "average"), help="M4 (random) or M5 (average)")
    parser.add_argument("--annotations", required=True, metavar="ANN.csv",
                        help="CCM annotation CSV: the recordings to predict (only their ids are used)")
    parser.add_argument("--out", required=True, metavar="PRED.csv", help="challenge prediction CSV to write")
    parser.add_argument("--train", metavar="ANN_TRAIN.csv",
                        help="average: annotation CSV whose container masses are averaged (default: --annotations "
                        "itself, i.e. the mean of the very labels being predicted, an optimistic reference)")
    parser.add_argument("--seed", type=int, default=0, help="random: seed of random.Random (default: 0)")
    parser.add_argument("--exact", action="store_true",
                        help="write the mass with 2 decimals instead of truncating it to an integer")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from massviz.evaluation.baselines import RANDOM_RANGE_G, average_mass, random_baseline
    from massviz.io.atomic import check_output_file
    from massviz.io.ccm_annotations import ANN_ID, read_annotations
    from massviz.io.challenge_csv import write_challenge_csv

    check_output_file(args.out, "--out")
    ids = read_annotations(args.annotations)[ANN_ID].tolist()
    if args.method == "random":
        estimates = random_baseline(ids, args.seed)
        how = f"uniform in [{RANDOM_RANGE_G[0]:g}, {RANDOM_RANGE_G[1]:g}] g, seed {args.seed}"
    else:
        train = args.train or args.annotations
        mass = average_mass(read_annotations(train))
        estimates = dict.fromkeys(ids, mass)
        how = f"mean container mass of {train}: {mass:.2f} g"
    rows = [{"config_id": i, "mass_g": m, "exec_time_s": 0.0} for i, m in estimates.items()]
    write_challenge_csv(args.out, rows, exact=args.exact)
    print(f"wrote {len(rows)} {args.method} predictions ({how}) to {args.out}")
    return 0
