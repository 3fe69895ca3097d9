"""``massviz train``: train the mass CNN on a patch set with the paper's protocol."""
from __future__ import annotations

import argparse
import sys

# Literal here so that building the CLI does not import torch; massviz.training.train.SPLITS checks it again.
_SPLITS = ("random", "fold1", "fold2", "fold3")


def register(sub) -> None:
    p = sub.add_parser(
        "train", help="train the mass CNN on a patch set (paper's protocol)",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Train MassNet on a patch set made by 'massviz extract': MSE loss, batch 32, Adam lr 0.0015 "
        "decayed by 0.9985 every 20 steps, weight decay 0.001; a, b, d and mass min-max normalised with the "
        "training split's ranges; flips, 0-180 degree rotation and colour jitter multiply the training set "
        "(3x for folds, 5x for random); 100 / 300 epochs. Recordings are split 80:20 into training and validation; "
        "a fold first leaves out the recordings of its test containers (fold1: 3/6/9, fold2: 2/5/8, fold3: "
        "1/4/7), which needs container ids in the index. The epoch with the lowest validation loss is "
        "saved as RUN/best.torch; per-epoch metrics go to RUN/metrics.csv and RUN/train.rrd (Rerun), each "
        "recording's part to RUN/split.csv.",
        epilog="examples:\n  massviz train patches/ --split fold1 --out runs/fold1\n"
        "  massviz train patches/ --split random --out runs/val --seed 1\n"
        "  massviz train patches/ --split random --out runs/ft --init Encoder_pool_aug_158.torch --epochs 20\n"
        "  massviz estimate data_samples/* --weights runs/val/best.torch --out preds.csv")
    p.add_argument("patches", metavar="PATCHES", help="patch set folder (index.csv + images/)")
    p.add_argument("--out", required=True, metavar="RUN", help="run folder (must be empty unless --force)")
    p.add_argument("--split", default="random", choices=_SPLITS, help="random 80:20, or a fold (default: random)")
    p.add_argument("--epochs", type=int, metavar="N", help="epochs (default: 100 for folds, 300 for random)")
    p.add_argument("--augment", type=int, metavar="M",
                   help="multiply the training set M times with augmentation; 1 = none (default: 3 folds, 5 random)")
    p.add_argument("--batch-size", type=int, default=32, metavar="B", help="batch size (default: 32)")
    p.add_argument("--lr", type=float, default=0.0015, help="initial learning rate (default: 0.0015)")
    p.add_argument("--seed", type=int, default=0,
                   help="seed of the split, the initialisation, the shuffling and the augmentation (default: 0); "
                   "the same seed on the CPU gives the same checkpoint")
    p.add_argument("--init", metavar="CKPT", help="fine-tune from this checkpoint's weights")
    p.add_argument("--keep-ranges", action="store_true",
                   help="with --init: keep its normalisation ranges instead of the training split's")
    p.add_argument("--device", default="auto", help="auto (CUDA when present, else CPU), cpu, cuda, cuda:1 ...")
    p.add_argument("--force", action="store_true",
                   help="replace a previous run in RUN (a folder holding anything but a run's files is refused, "
                   "never emptied)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args) -> int:
    from massviz.io.atomic import check_output_dir
    from massviz.training.train import TrainConfig, resolve_device, train_run

    check_output_dir(args.out, "--out")
    config = TrainConfig(split=args.split, epochs=args.epochs, batch_size=args.batch_size, lr=args.lr,
                         augment_factor=args.augment, seed=args.seed, device=str(resolve_device(args.device)))
    result = train_run(args.patches, args.out, config, init=args.init, keep_ranges=args.keep_ranges,
                       force=args.force, progress=not args.quiet)
    split = result.split
    print(f"split {split.name}: {len(split.train)} training, {len(split.val)} validation, {len(split.test)} test "
          f"recordings", file=sys.stderr)
    n_train, n_val = result.flagged.get("train", 0), result.flagged.get("val", 0)
    line = f"flagged patches in the split: {n_train} training, {n_val} validation"
    if n_train + n_val:
        line = (f"massviz train: warning: {line} (probably not the container, index.csv column 'flagged'; "
                "leave them out with massviz extract --skip-flagged or --exclude FILE)")
    print(line, file=sys.stderr)
    print(f"best epoch {result.best_epoch}/{len(result.metrics) - 1}: val loss {result.best_val_loss:.4f}, "
          f"val MAE {result.best_val_mae_g:.1f} g -> {result.best}", file=sys.stderr)
    return 0
