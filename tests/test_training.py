"""Training: patch sets, splits, normalisation, augmentation, the loop, extract → train → estimate."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pandas as pd
import pytest
import torch
from PIL import Image

from massviz.cli import main
from massviz.core.model import MassNet
from massviz.errors import DataError, MassvizError
from massviz.io.checkpoint import load_checkpoint
from massviz.training.train import (
    AUGMENT_FACTOR,
    FOLDS,
    INDEX_COLUMNS,
    INDEX_NAME,
    PatchDataset,
    TrainConfig,
    annotation_for,
    compute_ranges,
    fit,
    make_augmentation,
    read_index,
    split_recordings,
    train_run,
)


def make_patch_set(root, n_recordings=10, per_recording=3, seed=0):
    """A synthetic patch set: recording r holds container (r % 9) + 1 whose mass shows as the patch's colour."""
    rng = np.random.default_rng(seed)
    (root / "images").mkdir(parents=True)
    rows = []
    for r in range(n_recordings):
        container = r % 9 + 1
        mass = 5.0 + 10.0 * container
        for rank in range(per_recording):
            h, w = rng.integers(20, 60, size=2)
            img = np.zeros((h, w, 3), np.uint8)
            img[..., 0] = int(mass * 2)
            img[..., 1] = rng.integers(0, 255)
            img[..., 2] = rng.integers(0, 255, size=(h, w))
            name = f"images/{r:06d}_{rank}.png"
            Image.fromarray(img).save(root / name)
            rows.append({"file": name, "recording": f"{r:06d}", "config_id": str(r), "rank": rank, "frame": rank,
                         "a": w / 480, "b": h / 270, "d": float(rng.uniform(400, 1400)), "mass_g": mass,
                         "container_id": container})
    pd.DataFrame(rows).reindex(columns=list(INDEX_COLUMNS)).to_csv(root / INDEX_NAME, index=False)
    return root


@pytest.fixture
def patch_set(tmp_path):
    return make_patch_set(tmp_path / "patches")


# --------------------------------------------------------------------------------------------------- splits, ranges
@pytest.mark.parametrize("split", sorted(FOLDS))
def test_fold_leaves_its_containers_out(split):
    index = pd.DataFrame({"recording": [f"{r:03d}" for r in range(90)],
                          "container_id": [r % 9 + 1 for r in range(90)]})
    s = split_recordings(index, split, seed=3)
    by_rec = dict(zip(index["recording"], index["container_id"], strict=False))
    assert {by_rec[r] for r in s.test} == set(FOLDS[split])
    assert not {by_rec[r] for r in s.train + s.val} & set(FOLDS[split])
    assert len(s.test) == 30 and len(s.val) == 12 and len(s.train) == 48  # 80:20 of the 60 others
    assert not set(s.train) & set(s.val) and not set(s.train + s.val) & set(s.test)


def test_random_split_is_80_20_by_recording_and_seeded():
    index = pd.DataFrame({"recording": [f"{r // 5:03d}" for r in range(500)], "container_id": -1})
    s = split_recordings(index, "random", seed=1)
    assert (len(s.train), len(s.val), len(s.test)) == (80, 20, 0)
    assert set(s.train) | set(s.val) == set(index["recording"]) and not set(s.train) & set(s.val)
    assert split_recordings(index, "random", seed=1) == s
    assert split_recordings(index, "random", seed=2).val != s.val


def test_fold_split_needs_container_ids():
    index = pd.DataFrame({"recording": ["a", "b", "c"], "container_id": [1, -1, 2]})
    with pytest.raises(DataError, match="needs container ids.*recording b"):
        split_recordings(index, "fold1", seed=0)


def test_ranges_come_from_the_training_split_only(patch_set):
    index = read_index(patch_set)
    s = split_recordings(index, "fold1", seed=0)
    train = index[index["recording"].isin(s.train)]
    r = compute_ranges(train)
    assert (r.min_mass, r.max_mass) == (train["mass_g"].min(), train["mass_g"].max())
    assert (r.min_distance, r.max_distance) == (train["d"].min(), train["d"].max())
    assert (r.min_ratio_width, r.max_ratio_height) == (train["a"].min(), train["b"].max())
    # the fold's test containers include the heaviest (9): it is not in the training ranges
    assert r.max_mass < index["mass_g"].max()
    with pytest.raises(DataError, match="same mass"):
        compute_ranges(train.assign(mass_g=10.0))


# ----------------------------------------------------------------------------------------------------- augmentation
def test_augmentation_keeps_shape_and_range_and_multiplies_the_set(patch_set):
    index = read_index(patch_set)
    ranges = compute_ranges(index)
    torch.manual_seed(0)
    data = PatchDataset(patch_set, index.iloc[:4], ranges, AUGMENT_FACTOR["fold1"], make_augmentation())
    assert len(data) == 12
    items = [data[i] for i in range(len(data))]
    for image, _feats, _target in items:
        assert image.shape == (3, 112, 112) and image.dtype == torch.float32
        assert 0.0 <= float(image.min()) and float(image.max()) <= 1.0
    plain = PatchDataset(patch_set, index.iloc[:4], ranges)
    assert len(plain) == 4 and len(PatchDataset(patch_set, index, ranges, 5, make_augmentation())) == 5 * len(index)
    for i in range(4):
        assert torch.equal(items[i][0], plain[i][0])  # the first copy is the patch itself
        assert torch.equal(items[i + 4][1], plain[i][1]) and items[i + 8][2] == plain[i][2]  # same labels
    assert any(not torch.equal(items[i + 4][0], plain[i][0]) for i in range(4))  # augmented copies differ


# ------------------------------------------------------------------------------------------------------------ loop
@pytest.mark.slow
def test_overfits_a_handful_of_patches(patch_set):
    index = read_index(patch_set).iloc[:4]
    ranges = compute_ranges(index)
    data = PatchDataset(patch_set, index, ranges)
    torch.manual_seed(0)
    config = TrainConfig(epochs=12, batch_size=4, augment_factor=1).resolved()  # one step per epoch
    losses = [m.train_loss for m in fit(MassNet(), data, PatchDataset(patch_set, index.iloc[:1], ranges),
                                        ranges, config)]
    assert max(losses[-3:]) < losses[0] / 10, losses


@pytest.mark.slow
def test_same_seed_gives_the_same_checkpoint(tmp_path):
    patch_set = make_patch_set(tmp_path / "patches", n_recordings=5, per_recording=2)
    config = TrainConfig(split="random", epochs=1, batch_size=8, augment_factor=2, seed=7)
    a = train_run(patch_set, tmp_path / "a", config)
    b = train_run(patch_set, tmp_path / "b", config)
    sa = torch.load(a.best, weights_only=True)["state_dict"]
    sb = torch.load(b.best, weights_only=True)["state_dict"]
    assert sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)
    c = train_run(patch_set, tmp_path / "c", replace(config, seed=8))
    sc = torch.load(c.best, weights_only=True)["state_dict"]
    assert not all(torch.equal(sa[k], sc[k]) for k in sa)


@pytest.mark.slow
def test_run_writes_metrics_rrd_split_and_a_loadable_checkpoint(patch_set, tmp_path):
    result = train_run(patch_set, tmp_path / "run", TrainConfig(split="fold2", epochs=2, batch_size=8,
                                                               augment_factor=1))
    metrics = pd.read_csv(tmp_path / "run" / "metrics.csv")
    assert list(metrics.columns) == ["epoch", "train_loss", "val_loss", "val_mae_g", "lr", "steps"]
    assert list(metrics["epoch"]) == [0, 1, 2] and np.isnan(metrics["train_loss"][0])
    assert list(metrics["steps"]) == [0, 3, 6]  # 6 training recordings × 3 patches = 18: batches of 8, 8, 2
    trained = metrics[metrics["epoch"] > 0]
    assert result.best_epoch == int(trained["epoch"][trained["val_loss"].idxmin()])
    assert (tmp_path / "run" / "train.rrd").stat().st_size > 0
    split = pd.read_csv(tmp_path / "run" / "split.csv", dtype={"recording": str})
    assert sorted(split["part"].value_counts().items()) == [("test", 3), ("train", 6), ("val", 1)]
    index = read_index(patch_set)
    train_rows = index[index["recording"].isin(split["recording"][split["part"] == "train"])]
    model = load_checkpoint(result.best)
    assert model.ranges == result.ranges == compute_ranges(train_rows)
    extra = torch.load(result.best, weights_only=True)["extra"]
    assert extra["split"] == "fold2" and extra["epoch"] == result.best_epoch


# ------------------------------------------------------------------------------------------------------ bad inputs
def test_bad_patch_sets_are_one_line_errors(tmp_path, capsys):
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(DataError, match=f"{empty / INDEX_NAME}: missing index.csv"):
        read_index(empty)
    header_only = tmp_path / "header"
    header_only.mkdir()
    (header_only / INDEX_NAME).write_text(",".join(INDEX_COLUMNS) + "\n")
    with pytest.raises(DataError, match="no patches"):
        read_index(header_only)
    assert main(["train", str(empty), "--out", str(tmp_path / "run"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(empty / INDEX_NAME) in err


def test_missing_image_and_non_empty_run_folder(patch_set, tmp_path):
    (patch_set / "images" / "000001_2.png").unlink()
    with pytest.raises(DataError, match="000001_2.png is missing"):
        read_index(patch_set)
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "x").write_text("")
    (patch_set / "images" / "000001_2.png").write_bytes((patch_set / "images" / "000001_1.png").read_bytes())
    with pytest.raises(MassvizError, match="not empty"):
        train_run(patch_set, tmp_path / "run", TrainConfig(epochs=1))


def test_annotation_mismatch_names_the_csv(shared_dir):
    from massviz.io.ccm_annotations import read_annotations
    from massviz.io.recording import open_recording

    ann = shared_dir / "ccm" / "annotations" / "Val_annotations.csv"
    rec = open_recording(shared_dir / "ccm_real" / "view1" / "rgb" / "000000.mp4")  # recording 0 is not in VAL
    with pytest.raises(DataError, match=f"{ann}: no annotation for recording 000000"):
        annotation_for(rec, read_annotations(ann), ann)
    train = shared_dir / "ccm" / "annotations" / "ccm_train_annotation.csv"
    label = annotation_for(rec, read_annotations(train), train)
    assert (label.mass_g, label.container_id) == (2.0, 2) and dict(label.dims)["height_mm"] == 72.0


# ------------------------------------------------------------------------------ extract → train → estimate, by CLI
@pytest.mark.slow
def test_extract_train_estimate_on_the_samples(samples_dir, shared_dir, weights, tmp_path, capsys):
    import json

    from massviz.evaluation.metrics import read_predictions

    recordings = sorted(p for p in samples_dir.iterdir() if (p / "meta.json").is_file())
    if not recordings:
        pytest.skip("no bundled samples in data_samples/")
    pipeline = ["--detector", "depth", "--stride", "4", "--cache", str(tmp_path / "cache"), "--quiet"]
    patches = tmp_path / "patches"
    assert main(["extract", str(samples_dir), "--out", str(patches), "--weights", str(weights),
                 *pipeline]) == 0, capsys.readouterr().err
    index = read_index(patches)
    assert list(index.columns) == list(INDEX_COLUMNS)
    assert set(index["recording"]) == {p.name for p in recordings} and index["rank"].max() == 4
    for rec in recordings:
        mass = json.loads((rec / "meta.json").read_text())["container"]["mass_g"]
        assert (index.loc[index["recording"] == rec.name, "mass_g"] == mass).all()
    assert np.isfinite(index["d"]).all() and (index["d"] > 0).all()
    first = Image.open(patches / index["file"][0])
    assert first.mode == "RGB" and first.size == (index["x2"][0] - index["x1"][0], index["y2"][0] - index["y1"][0])
    assert not list(tmp_path.glob(".patches.*"))  # the temporary folder was moved into place
    assert main(["extract", str(samples_dir), "--out", str(patches), *pipeline]) == 2  # exists: no --force
    assert "already exists" in capsys.readouterr().err

    run = tmp_path / "run"
    assert main(["train", str(patches), "--out", str(run), "--epochs", "3", "--seed", "0", "--quiet"]) == 0, \
        capsys.readouterr().err
    metrics = pd.read_csv(run / "metrics.csv")
    assert metrics["val_loss"][metrics["epoch"] > 0].min() < metrics["val_loss"][0]  # training lowered it

    preds = tmp_path / "preds.csv"
    ccm = shared_dir / "ccm_real" / "view1" / "rgb" / "000000.mp4"
    assert main(["estimate", str(ccm), "--weights", str(run / "best.torch"), "--out", str(preds), *pipeline]) == 0, \
        capsys.readouterr().err
    table = read_predictions(preds)
    assert list(table["Configuration ID"]) == [0] and np.isfinite(table["Container mass"]).all()


def test_extract_with_an_annotation_csv_missing_a_recording(shared_dir, weights, tmp_path, capsys):
    ann = shared_dir / "ccm" / "annotations" / "test_annotations_fold0.csv"  # recording 0 is in fold 1's test set
    ccm = shared_dir / "ccm_real" / "view1" / "rgb" / "000000.mp4"
    out = tmp_path / "patches"
    assert main(["extract", str(ccm), "--annotations", str(ann), "--out", str(out), "--detector", "depth",
                 "--weights", str(weights), "--no-cache", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{ann}: no annotation for recording 000000" in err
    assert not out.exists() and not list(tmp_path.iterdir())
