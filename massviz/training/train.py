"""Training the mass CNN with the paper's protocol: patch extraction, splits, normalisation, augmentation, the loop.

Two steps, each a plain function the CLI wraps:

1. :func:`extract_patches` runs detection and the K-nearest selection over recordings (through the trace cache) and
   writes a *patch set*: ``PATCHES/images/<recording>_<rank>.png`` (RGB crops) and ``PATCHES/index.csv`` (one row
   per patch, :data:`INDEX_COLUMNS`), every patch labelled with its recording's annotation (the format is
   :mod:`massviz.io.patch_set`'s: its reader, its writer; the names are also importable from here).
2. :func:`train_run` splits a patch set by recording (:func:`split_recordings`), computes the min-max
   :class:`~massviz.core.model.Ranges` on the training split only (:func:`compute_ranges`), trains :class:`MassNet`
   (:func:`fit`) and keeps the epoch with the lowest validation loss as ``RUN/best.torch``.

The protocol (Apicella et al., ICASSP 2022, "Model training" and "Experimental setup"): MSE loss on min-max
normalised mass, batch 32, Adam at lr 0.0015 with weight decay 0.001, exponential decay 0.9985 every 20 steps;
augmentation by horizontal and vertical flips (p = 0.5), a rotation in [0°, 180°] that does not crop
(``expand=True``) and colour jitter (brightness, contrast, saturation in [0.8, 1.2], hue in [-0.2, 0.2]); the
training set is multiplied 3× (folds) or 5× (random split), i.e. each patch plus 2 or 4 augmented copies, as the
authors' ``Encoder/Dataset/augmentation.py`` does; 100 epochs for the folds, 300 for the random split; 80:20
training/validation of the non-test recordings; the best model on validation is kept. Folds leave one container of
each class out: F1 tests containers 3/6/9, F2 2/5/8, F3 1/4/7.

Where this differs from the authors' ``Encoder/Training_CNN_encoder.py`` and ``Encoder/Models/DataExtractor.py``
(github.com/CORSMAL/Visual, MIT licence), deliberately:

- one Adam optimiser for the whole run; the original builds a new one every batch, which resets Adam's moments;
- the learning rate decays per optimiser step, ``lr = 0.0015 · 0.9985^floor(step / 20)`` (the paper's "decay rate
  0.9985, decay steps 20"); the original multiplies it once per epoch n by ``0.9985^(n / 20)``;
- augmented copies are drawn afresh each time they are used instead of written to disk once; the original also
  flips and rotates (0–90°) *every* image, validation included, once when loading it: massviz validates on the
  untouched patches;
- the split is by recording (patches of one recording never straddle training and validation), the ranges come
  from the training split only, and the best epoch is the one with the lowest validation loss (as the paper says;
  the original picks the lowest validation error in grams, which ``metrics.csv`` also reports);
- the last incomplete batch is kept unless it holds a single patch (BatchNorm needs two); the original drops it.

Kept from the original: gradient-norm clipping at 5 (``max_grad_norm`` of its ConfigurationFile.json).
"""
from __future__ import annotations

import math
import random
import sys
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np
import pandas as pd
import torch
from PIL import Image
from torch import nn
from torch.utils.data import DataLoader, Dataset
from tqdm.auto import tqdm

from massviz.core.model import MassNet, Ranges, preprocess_patch
from massviz.errors import DataError, MassvizError
from massviz.io.atomic import atomic_dir, check_replaceable
from massviz.io.checkpoint import load_checkpoint, save_checkpoint
from massviz.io.patch_set import (  # noqa: F401 - the patch set's names, also here
    DIMENSIONS,
    IMAGES_DIR,
    INDEX_COLUMNS,
    INDEX_NAME,
    Annotation,
    ExtractResult,
    annotation_for,
    check_extract,
    flag_columns,
    patch_files,
    patch_rows,
    read_index,
    write_patch_set,
)
from massviz.io.untrusted import csv_writer, number, write_csv

#: test containers of each fold (one cup, one glass, one box left out).
FOLDS = {"fold1": (3, 6, 9), "fold2": (2, 5, 8), "fold3": (1, 4, 7)}
SPLITS = ("random", *FOLDS)
#: how many times augmentation multiplies the training set (the patch itself + augmented copies).
AUGMENT_FACTOR = {"random": 5, **{f: 3 for f in FOLDS}}
#: largest augmentation factor (the training set is this many times as long).
MAX_AUGMENT = 100
DEFAULT_EPOCHS = {"random": 300, **{f: 100 for f in FOLDS}}
#: what a run folder holds: all ``--force`` may replace (anything else in RUN is refused, never deleted).
RUN_FILES = ("best.torch", "metrics.csv", "train.rrd", "split.csv")


# ======================================================================================================= extraction
def extract_patches(recordings: Sequence, labels: Sequence[Annotation], pipeline, out: str | Path, *,
                    progress: bool = False) -> ExtractResult:
    """Write the K selected patches of every recording, labelled with its annotation, as a patch set.

    ``labels`` come from :func:`check_extract`. Traces come from ``pipeline.process`` (a
    ``massviz.app.Pipeline``, with its cache), so recordings processed before are not detected again. The set
    is written into a temporary folder beside ``out`` and renamed into place when complete, replacing an existing
    ``out`` (``massviz.io.atomic.atomic_dir``). (``massviz extract`` runs the same through a dataset runner:
    :func:`patch_files` on the workers, :func:`write_patch_set` at the end.)
    """
    if len(labels) != len(recordings):
        raise ValueError(f"{len(recordings)} recordings but {len(labels)} labels")
    found = []
    for rec, label in tqdm(list(zip(recordings, labels)), desc="extract", unit="rec", file=sys.stderr,
                           disable=not progress):
        found.append((rec.id, patch_files(pipeline.process(rec, progress=False), label)))
    return write_patch_set(out, found)


# ============================================================================================ split and normalisation
@dataclass(frozen=True)
class Split:
    """Recording ids of each part of a split: ``test`` is empty for the random split."""

    name: str
    train: tuple[str, ...]
    val: tuple[str, ...]
    test: tuple[str, ...]

    def part_of(self, recording: str) -> str:
        """"train", "val" or "test"."""
        return next(p for p in ("train", "val", "test") if recording in getattr(self, p))


def split_recordings(index: pd.DataFrame, split: str, seed: int, val_fraction: float = 0.2) -> Split:
    """Split the recordings of a patch index, never a recording across parts.

    ``random``: every recording is shuffled (numpy ``default_rng(seed)``) and ``round(val_fraction · n)`` (at least
    one) go to validation. ``fold1``/``fold2``/``fold3``: the recordings of the fold's test containers
    (:data:`FOLDS`) are the test part, the others are split as for ``random``; the container ids must be known.
    """
    if split not in SPLITS:
        raise MassvizError(f"unknown split {split!r} (choose from {', '.join(SPLITS)})")
    containers = index.groupby("recording")["container_id"].first()
    test: list[str] = []
    if split in FOLDS:
        if (unknown := containers[containers < 0]).size:
            raise DataError(f"--split {split} needs container ids, but recording {unknown.index[0]} (and "
                            f"{unknown.size - 1} more) has none; extract with --annotations, or use --split random")
        test = sorted(containers[containers.isin(FOLDS[split])].index)
    rest = sorted(set(containers.index) - set(test))
    if len(rest) < 2:
        raise DataError(f"--split {split}: {len(rest)} recording(s) left for training and validation; need at "
                        "least 2")
    order = [rest[i] for i in np.random.default_rng(seed).permutation(len(rest))]
    n_val = min(max(1, round(val_fraction * len(rest))), len(rest) - 1)
    return Split(split, tuple(sorted(order[n_val:])), tuple(sorted(order[:n_val])), tuple(test))


def compute_ranges(rows: pd.DataFrame) -> Ranges:
    """Min-max normalisation ranges of d, a, b and mass over ``rows`` (the training split's patches)."""
    values = {}
    for col, what in (("d", "distance d"), ("a", "width ratio a"), ("b", "height ratio b"), ("mass_g", "mass")):
        lo, hi = float(rows[col].min()), float(rows[col].max())
        if not hi > lo:
            raise DataError(f"every training patch has the same {what} ({lo:g}); min-max normalisation needs two "
                            "distinct values (more recordings, or other containers, in the training split)")
        values[col] = (lo, hi)
    return Ranges(*values["d"], *values["a"], *values["b"], *values["mass_g"])


# =========================================================================================== dataset and augmentation
def make_augmentation():
    """The paper's augmentation of a PIL patch: flips (p = 0.5 each), a rotation in [0°, 180°] on an expanded canvas
    (nothing cropped, black corners), colour jitter (brightness, contrast, saturation × [0.8, 1.2], hue ± 0.2)."""
    from torchvision import transforms  # here: its import costs 2 s that `extract` does not need

    return transforms.Compose([
        transforms.RandomHorizontalFlip(0.5),
        transforms.RandomVerticalFlip(0.5),
        transforms.RandomRotation((0, 180), expand=True),
        transforms.ColorJitter(brightness=(0.8, 1.2), contrast=(0.8, 1.2), saturation=(0.8, 1.2), hue=(-0.2, 0.2)),
    ])


class PatchDataset(Dataset):
    """Patches of a patch set as ``(image 3×112×112 in [0, 1], normalised [a, b, d], normalised mass)``.

    With ``factor`` m > 1 the set is m times as long: item ``i`` is patch ``i % n``, untouched for ``i < n`` and
    passed through ``augment`` (a fresh random draw at every access) for the m - 1 copies after it. Images are
    read from disk when used and preprocessed exactly as at inference (:func:`massviz.core.model.preprocess_patch`).
    """

    def __init__(self, root: str | Path, rows: pd.DataFrame, ranges: Ranges, factor: int = 1, augment=None):
        if factor < 1:
            raise ValueError("factor must be >= 1")
        if factor > 1 and augment is None:
            raise ValueError("factor > 1 needs an augmentation")
        self.files = [Path(root) / f for f in rows["file"]]
        self.features = torch.from_numpy(ranges.normalise_features(rows[["a", "b", "d"]].to_numpy()))
        mass = rows["mass_g"].to_numpy(np.float64)
        self.targets = torch.from_numpy(((mass - ranges.min_mass) / (ranges.max_mass - ranges.min_mass))
                                        .astype(np.float32))
        self.factor, self.augment = factor, augment

    def __len__(self) -> int:
        return len(self.files) * self.factor

    def __getitem__(self, i: int):
        n = len(self.files)
        j = i % n
        try:
            with Image.open(self.files[j]) as img:
                image = img.convert("RGB")
        except (OSError, ValueError, Image.DecompressionBombError) as err:  # truncated, not an image, missing
            raise DataError(f"patch image cannot be read ({type(err).__name__}: {str(err)[:120]})",
                            self.files[j]) from None
        if i >= n:
            image = self.augment(image)
        return preprocess_patch(np.asarray(image)), self.features[j], self.targets[j]


# ===================================================================================================== training loop
@dataclass(frozen=True)
class TrainConfig:
    """Hyper-parameters; ``None`` epochs / augment_factor take the split's default (:data:`DEFAULT_EPOCHS`,
    :data:`AUGMENT_FACTOR`); ``augment_factor`` 1 trains without augmentation."""

    split: str = "random"
    epochs: int | None = None
    batch_size: int = 32
    lr: float = 0.0015
    lr_decay: float = 0.9985
    lr_decay_steps: int = 20
    weight_decay: float = 0.001
    max_grad_norm: float = 5.0
    augment_factor: int | None = None
    val_fraction: float = 0.2
    seed: int = 0
    device: str = "cpu"

    def resolved(self) -> "TrainConfig":
        """A copy with the split's defaults filled in, checked."""
        if self.split not in SPLITS:
            raise MassvizError(f"unknown split {self.split!r} (choose from {', '.join(SPLITS)})")
        cfg = replace(self, epochs=DEFAULT_EPOCHS[self.split] if self.epochs is None else self.epochs,
                      augment_factor=AUGMENT_FACTOR[self.split] if self.augment_factor is None else self.augment_factor)
        checks = (("--epochs", cfg.epochs, 1, 1_000_000, True), ("--batch-size", cfg.batch_size, 2, 1_000_000, True),
                  ("--augment", cfg.augment_factor, 1, MAX_AUGMENT, True), ("--lr", cfg.lr, 0, 10.0, False),
                  ("val fraction", cfg.val_fraction, 0, 1, False))
        for option, value, lo, hi, integral in checks:
            number(value, option, lo=lo, hi=hi, lo_open=not integral, integral=integral, error=MassvizError)
        if not cfg.val_fraction < 1:
            raise MassvizError(f"val fraction must be < 1, got {cfg.val_fraction}")
        return cfg


@dataclass(frozen=True)
class EpochMetrics:
    """One epoch: mean training loss, validation loss (MSE, normalised units), validation MAE (g), the learning rate
    after the epoch and the optimiser steps so far."""

    epoch: int
    train_loss: float
    val_loss: float
    val_mae_g: float
    lr: float
    steps: int


def seed_everything(seed: int) -> None:
    """Seed python's, numpy's and torch's generators."""
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


@contextmanager
def deterministic():
    """Make torch use deterministic algorithms inside the block (restoring the previous setting after it)."""
    before = torch.are_deterministic_algorithms_enabled()
    torch.use_deterministic_algorithms(True, warn_only=True)
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(before)


def resolve_device(name: str = "auto") -> torch.device:
    """``auto`` → CUDA when available, else CPU; otherwise the named device (checked)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError as e:
        raise MassvizError(f"--device {name}: {e}") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise MassvizError(f"--device {name}: CUDA is not available here (use --device cpu)")
    if device.type == "mps" and not (getattr(torch.backends, "mps", None) and torch.backends.mps.is_available()):
        raise MassvizError(f"--device {name}: Apple's MPS is not available here (use --device cpu)")
    if device.type not in ("cpu", "cuda", "mps"):
        raise MassvizError(f"--device {name}: massviz trains on cpu, cuda or mps")
    return device


@torch.no_grad()
def evaluate(model: MassNet, data: Dataset, ranges: Ranges, device: torch.device,
             batch_size: int = 64) -> tuple[float, float]:
    """(MSE in normalised units, mean absolute error in grams after denormalising and clamping) over ``data``."""
    model.eval()
    sq, ab, n = 0.0, 0.0, 0
    for images, feats, target in DataLoader(data, batch_size=batch_size, shuffle=False, num_workers=0):
        y = model(images.to(device), feats.to(device))[:, 0].float().cpu()
        sq += float(((y - target) ** 2).sum())
        grams = ranges.denormalise_mass(y.numpy())
        truth = target.numpy() * (ranges.max_mass - ranges.min_mass) + ranges.min_mass
        ab += float(np.abs(grams - truth).sum())
        n += len(target)
    return sq / n, ab / n


def fit(model: MassNet, train_set: Dataset, val_set: Dataset, ranges: Ranges, config: TrainConfig,
        progress: bool = False) -> Iterator[EpochMetrics]:
    """Train ``model`` in place for ``config.epochs`` epochs, yielding each epoch's metrics (the model then holds
    that epoch's weights; the caller keeps what it wants). ``config`` must be :meth:`TrainConfig.resolved`.

    Adam (lr, weight decay), StepLR(step_size=lr_decay_steps, gamma=lr_decay) stepped after every batch, MSE loss,
    gradient norm clipped to ``max_grad_norm``. Batches are shuffled by a generator seeded with ``config.seed``.
    """
    device = torch.device(config.device)
    model.to(device)
    generator = torch.Generator().manual_seed(config.seed)
    loader = DataLoader(train_set, batch_size=config.batch_size, shuffle=True, generator=generator, num_workers=0,
                        drop_last=len(train_set) % config.batch_size == 1)
    optimiser = torch.optim.Adam(model.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    schedule = torch.optim.lr_scheduler.StepLR(optimiser, step_size=config.lr_decay_steps, gamma=config.lr_decay)
    loss_fn = nn.MSELoss()
    steps = 0
    bar = tqdm(total=config.epochs * len(loader), desc="train", unit="batch", file=sys.stderr, disable=not progress)
    try:
        for epoch in range(1, config.epochs + 1):
            model.train()
            total, seen = 0.0, 0
            for images, feats, target in loader:
                y = model(images.to(device), feats.to(device))[:, 0]
                loss = loss_fn(y, target.to(device))
                if not bool(torch.isfinite(loss)):
                    raise MassvizError(f"training stopped: the loss is {float(loss)} at epoch {epoch}, step "
                                       f"{steps + 1} (diverged; lower --lr, now {config.lr:g}); nothing was kept")
                optimiser.zero_grad()
                loss.backward()
                nn.utils.clip_grad_norm_(model.parameters(), config.max_grad_norm)
                optimiser.step()
                schedule.step()
                steps += 1
                total += float(loss.detach()) * len(target)
                seen += len(target)
                bar.update(1)
            val_loss, val_mae = evaluate(model, val_set, ranges, device)
            from massviz.io.checkpoint import MAX_WEIGHT_MAGNITUDE

            largest = max(float(t.detach().abs().max()) for t in model.state_dict().values() if t.is_floating_point())
            if not largest <= MAX_WEIGHT_MAGNITUDE:  # a checkpoint load_checkpoint would refuse: stop now
                raise MassvizError(f"training stopped: a weight reached {largest:g} after epoch {epoch} (beyond "
                                   f"+-{MAX_WEIGHT_MAGNITUDE:g}: diverged; lower --lr, now {config.lr:g}); nothing "
                                   "was kept")
            if not (math.isfinite(val_loss) and math.isfinite(val_mae)):
                raise MassvizError(f"training stopped: the validation loss is {val_loss} after epoch {epoch} "
                                   f"(diverged; lower --lr, now {config.lr:g}); nothing was kept")
            metrics = EpochMetrics(epoch, total / seen, val_loss, val_mae, schedule.get_last_lr()[0], steps)
            bar.set_postfix(epoch=epoch, train=f"{metrics.train_loss:.4f}", val=f"{val_loss:.4f}",
                            mae=f"{val_mae:.1f}g")
            yield metrics
    finally:
        bar.close()


# ========================================================================================================= a full run
@dataclass(frozen=True)
class TrainResult:
    """What :func:`train_run` wrote and found."""

    out: Path
    best: Path
    best_epoch: int
    best_val_loss: float
    best_val_mae_g: float
    ranges: Ranges
    split: Split
    metrics: tuple[EpochMetrics, ...]  # epoch 0 (before training) first
    #: flagged patches (``index.csv`` ``flagged``: probably not the container) in each part: {"train": n, "val": n}
    flagged: dict = field(default_factory=dict)


def _log_scalars(stream, m: EpochMetrics) -> None:
    import rerun as rr

    stream.set_time("epoch", sequence=m.epoch)
    for name, value in (("loss/train", m.train_loss), ("loss/val", m.val_loss), ("val_mae_g", m.val_mae_g),
                        ("lr", m.lr)):
        if math.isfinite(value):
            stream.log(name, rr.Scalars(value))


def train_run(patches: str | Path, out: str | Path, config: TrainConfig, *, init: str | Path | None = None,
              keep_ranges: bool = False, force: bool = False, progress: bool = False) -> TrainResult:
    """Train on a patch set with the paper's protocol and write a run folder.

    ``out`` gets ``best.torch`` (the lowest validation loss so far, a massviz checkpoint that ``massviz estimate
    --weights`` reads), ``metrics.csv`` (one row per epoch, appended as training goes; row 0 is the model before
    training, without a training loss, and never becomes the best), ``train.rrd`` (the same
    metrics as Rerun scalars on an ``epoch`` timeline) and ``split.csv`` (each recording's part). ``init``
    fine-tunes from a checkpoint's weights; its ranges are kept with ``keep_ranges``, else recomputed from the
    training split. A non-empty ``out`` is an error unless ``force`` (and then it may hold only a run's files, :data:`RUN_FILES`). The same ``config.seed`` on the CPU gives the
    same checkpoint. Nothing appears at ``out`` unless training ends (see :func:`massviz.io.atomic.atomic_dir`).
    """
    cfg = config.resolved()
    patches, out = Path(patches), Path(out)
    index = read_index(patches)
    if out.exists() and any(out.iterdir()) and not force:
        raise MassvizError("run folder is not empty (pass --force to overwrite)", out)
    if force:
        check_replaceable(out, RUN_FILES, "training run")
    split = split_recordings(index, cfg.split, cfg.seed, cfg.val_fraction)
    train_rows = index[index["recording"].isin(split.train)]
    val_rows = index[index["recording"].isin(split.val)]
    if keep_ranges and init is None:
        raise MassvizError("--keep-ranges needs --init CKPT (the ranges to keep come from it)")
    with deterministic():
        seed_everything(cfg.seed)
        ranges = None if keep_ranges else compute_ranges(train_rows)
        if init is None:
            model = MassNet()
        else:
            loaded = load_checkpoint(init, ranges=ranges)
            model, ranges = loaded.net, loaded.ranges
        augment = make_augmentation() if cfg.augment_factor > 1 else None
        train_set = PatchDataset(patches, train_rows, ranges, cfg.augment_factor, augment)
        val_set = PatchDataset(patches, val_rows, ranges)

        # The run is written in a hidden folder beside RUN and renamed to RUN when training ends: a failure, a
        # full disk, a diverged loss or a signal (SIGINT/SIGTERM/SIGHUP) leaves RUN as it was, never half-written.
        with atomic_dir(out) as tmp:
            best, history = _train_into(tmp, out, model, train_set, val_set, ranges, index, split, cfg, init,
                                        patches, len(train_rows), len(val_rows), progress)
    flagged = {"train": int(train_rows["flagged"].sum()), "val": int(val_rows["flagged"].sum())}
    return TrainResult(out, out / "best.torch", best.epoch, best.val_loss, best.val_mae_g, ranges, split,
                       tuple(history), flagged)


def _train_into(run: Path, out: Path, model, train_set, val_set, ranges, index, split, cfg, init, patches,
                n_train: int, n_val: int, progress: bool):
    """The body of :func:`train_run`, writing into the temporary folder ``run`` (renamed to ``out`` after)."""
    import rerun as rr

    write_csv(pd.DataFrame({"recording": sorted(index["recording"].unique())}).assign(
        part=lambda t: t["recording"].map(split.part_of)), run / "split.csv")
    stream = rr.RecordingStream("massviz_train")
    stream.save(run / "train.rrd")
    try:
        return _epochs(run, stream, model, train_set, val_set, ranges, split, cfg, init, patches, n_train, n_val,
                       progress)
    finally:
        stream.flush()
        stream.disconnect()


def _epochs(run, stream, model, train_set, val_set, ranges, split, cfg, init, patches, n_train, n_val, progress):
    best, history = None, []
    extra = {"split": cfg.split, "seed": cfg.seed, "patches": str(patches.resolve()),
             "init": None if init is None else str(init), "config": asdict(cfg),
             "n_train_patches": n_train, "n_val_patches": n_val}
    device = torch.device(cfg.device)
    start = EpochMetrics(0, math.nan, *evaluate(model.to(device), val_set, ranges, device), cfg.lr, 0)
    if not (math.isfinite(start.val_loss) and math.isfinite(start.val_mae_g)):
        raise MassvizError(f"the initial model's validation loss is {start.val_loss} (not a finite number)",
                           init)
    with open(run / "metrics.csv", "w", newline="") as f:
        writer = csv_writer(f)
        writer.writerow(["epoch", "train_loss", "val_loss", "val_mae_g", "lr", "steps"])
        for m in (start, *fit(model, train_set, val_set, ranges, cfg, progress=progress)):
            history.append(m)
            writer.writerow([m.epoch, "" if m.epoch == 0 else f"{m.train_loss:.6g}", f"{m.val_loss:.6g}", f"{m.val_mae_g:.4f}",
                             f"{m.lr:.6g}", m.steps])
            f.flush()
            _log_scalars(stream, m)
            if m.epoch > 0 and (best is None or m.val_loss < best.val_loss):
                best = m
                save_checkpoint(run / "best.torch", model, ranges,
                                extra={**extra, "epoch": m.epoch, "val_loss": m.val_loss,
                                       "val_mae_g": m.val_mae_g})
    return best, history


__all__ = ["INDEX_NAME", "IMAGES_DIR", "INDEX_COLUMNS", "FOLDS", "SPLITS", "AUGMENT_FACTOR", "DEFAULT_EPOCHS",
           "Annotation", "annotation_for", "flag_columns", "patch_rows", "ExtractResult", "check_extract", "extract_patches", "read_index", "Split",
           "split_recordings", "compute_ranges", "make_augmentation", "PatchDataset", "TrainConfig", "EpochMetrics",
           "seed_everything", "deterministic", "resolve_device", "evaluate", "fit", "TrainResult", "train_run"]
