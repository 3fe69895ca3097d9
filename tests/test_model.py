"""massviz.core.model / massviz.io.weights: parity with the original code, checkpoint formats, ranges, download."""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image
from torchvision import transforms
from torchvision.transforms import InterpolationMode
from torchvision.transforms import functional as TF

from massviz.core.model import MassNet, Ranges, preprocess_patch, preprocess_patches, square_pad
from massviz.core.predictor import MassPredictor
from massviz.errors import WeightsError
from massviz.io import weights as W
from massviz.io.checkpoint import load_checkpoint, save_checkpoint

# The README's table (shared/weights/corsmal_visual/README.md), written out independently of massviz.io.weights.
README_RANGES = {
    "Encoder_pool_aug_158.torch": (291.53, 1533.87, 0.01, 0.46, 0.03, 0.90, 2.0, 134.0),
    "Encoder_pool_aug_fold0_94.torch": (276.0, 1534.06, 0.01, 0.45, 0.03, 0.96, 2.0, 134.0),
    "Encoder_pool_aug_fold1_35.torch": (276.0, 1523.34, 0.01, 0.45, 0.03, 0.96, 3.0, 86.0),
    "Encoder_pool_aug_fold2_86.torch": (310.14, 1534.06, 0.04, 0.38, 0.08, 0.86, 2.0, 134.0),
}
EXPECTED_KEYS = {f"{layer}.{p}" for layer in ("conv1", "conv2", "conv3", "conv4", "linear1", "linear2", "linear3")
                 for p in ("weight", "bias")} | {
    f"bn{i}.{p}" for i in range(1, 6)
    for p in ("weight", "bias", "running_mean", "running_var", "num_batches_tracked")}


@pytest.fixture(scope="module")
def weights_dir(shared_dir) -> Path:
    return shared_dir / "weights" / "corsmal_visual"


@pytest.fixture(scope="module")
def golden(shared_dir) -> dict:
    return json.loads((shared_dir / "golden" / "golden_public.json").read_text())


@pytest.fixture(scope="module")
def golden_inputs(shared_dir, golden):
    patches = [np.asarray(Image.open(shared_dir / "golden" / c["patch"]).convert("RGB")) for c in golden["cases"]]
    feats = np.array([[c["ar_w"], c["ar_h"], c["avg_d"]] for c in golden["cases"]])
    return patches, feats


@pytest.fixture(scope="module")
def model158(weights_dir) -> MassPredictor:
    return load_checkpoint(weights_dir / "Encoder_pool_aug_158.torch")


@pytest.fixture
def no_weights_env(monkeypatch, tmp_path):
    monkeypatch.delenv(W.ENV_WEIGHTS, raising=False)
    monkeypatch.setenv(W.ENV_CACHE_DIR, str(tmp_path / "cache"))
    return tmp_path / "cache" / "weights"


def random_patches(seed: int, n: int) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 256, (int(rng.integers(5, 90)), int(rng.integers(5, 90)), 3), dtype=np.uint8)
            for _ in range(n)]


# ------------------------------------------------------------------------------------------------------- parity
def test_golden_parity(model158, golden, golden_inputs):
    assert golden["weights"] == "Encoder_pool_aug_158.torch"
    assert model158.ranges.to_dict() == pytest.approx(golden["ranges"])
    patches, feats = golden_inputs
    pred = model158.predict(patches, feats)
    expected = np.array([c["mass_g"] for c in golden["cases"]])
    assert pred.dtype == np.float32 and pred.shape == (len(expected),)
    np.testing.assert_allclose(pred, expected, rtol=0.005)


def test_predict_is_batch_independent_and_handles_empty(model158, golden_inputs):
    patches, feats = golden_inputs
    whole = model158.predict(patches, feats)
    one_by_one = model158.predict(patches, feats, batch_size=1)
    np.testing.assert_allclose(one_by_one, whole, rtol=1e-5)
    empty = model158.predict([], np.zeros((0, 3)))
    assert empty.shape == (0,) and empty.dtype == np.float32
    with pytest.raises(ValueError):
        model158.predict(patches[:2], feats)


def test_predict_uses_eval_mode_and_restores_training_flag(weights_dir, golden_inputs):
    model = load_checkpoint(weights_dir / "Encoder_pool_aug_158.torch")
    patches, feats = golden_inputs
    expected = model.predict(patches, feats)
    model.net.train()
    np.testing.assert_array_equal(model.predict(patches, feats), expected)
    assert model.net.training


# -------------------------------------------------------------------------------------------------- preprocessing
def test_square_pad_split_matches_original():
    # SquarePad: left/top = (side - size) // 2, the remainder right/bottom.
    img = Image.fromarray(np.full((3, 6, 3), 200, np.uint8))  # H=3, W=6
    out = np.asarray(square_pad(img))
    assert out.shape == (6, 6, 3)
    assert (out[0] == 0).all() and (out[1:4] == 200).all() and (out[4:] == 0).all()  # 1 top, 2 bottom

    img = Image.fromarray(np.full((4, 1, 3), 7, np.uint8))  # H=4, W=1 → 1 left, 2 right
    out = np.asarray(square_pad(img))
    assert out.shape == (4, 4, 3)
    assert (out[:, 0] == 0).all() and (out[:, 1] == 7).all() and (out[:, 2:] == 0).all()

    square = np.arange(27, dtype=np.uint8).reshape(3, 3, 3)
    np.testing.assert_array_equal(np.asarray(square_pad(Image.fromarray(square))), square)


def test_preprocess_matches_independent_torchvision_pipeline():
    reference = transforms.Compose([
        transforms.Resize((112, 112), interpolation=InterpolationMode.BILINEAR),
        transforms.ToTensor(),
    ])
    rng = np.random.default_rng(7)
    odd = [rng.integers(0, 256, shape, dtype=np.uint8) for shape in
           ((1, 37, 3), (301, 2, 3), (113, 111, 3), (720, 1280, 3), (57, 57, 3), (3, 4, 3))]
    for patch in random_patches(0, 6) + odd + [np.full((1, 1, 3), 255, np.uint8)]:
        h, w, _ = patch.shape
        side = max(h, w)
        top, left = (side - h) // 2, (side - w) // 2
        # square_pad is torchvision's pad as the original's SquarePad calls it
        img = Image.fromarray(patch)
        np.testing.assert_array_equal(np.asarray(square_pad(img)), np.asarray(
            TF.pad(img, [left, top, side - w - left, side - h - top], fill=0, padding_mode="constant")))
        padded = np.zeros((side, side, 3), np.uint8)
        padded[top:top + h, left:left + w] = patch
        expected = reference(Image.fromarray(padded))
        got = preprocess_patch(patch)
        assert got.dtype == torch.float32 and got.shape == (3, 112, 112)
        torch.testing.assert_close(got, expected, rtol=0, atol=0)


def test_preprocess_is_not_a_plain_or_unpadded_resize():
    # A 112x112 patch passes through unchanged (scaled to [0, 1]); a wide one gets black bands top and bottom.
    patch = np.random.default_rng(1).integers(0, 256, (112, 112, 3), dtype=np.uint8)
    torch.testing.assert_close(preprocess_patch(patch), torch.from_numpy(patch).permute(2, 0, 1).float() / 255)
    wide = preprocess_patch(np.full((20, 100, 3), 255, np.uint8))
    assert float(wide[:, :40].max()) == 0.0 and float(wide[:, -40:].max()) == 0.0
    assert float(wide[:, 56].min()) == 1.0


def test_preprocess_patches_and_bad_input():
    batch = preprocess_patches(random_patches(2, 3))
    assert batch.shape == (3, 3, 112, 112)
    assert preprocess_patches([]).shape == (0, 3, 112, 112)
    for bad in (np.zeros((4, 4, 3), np.float32), np.zeros((4, 4), np.uint8), np.zeros((0, 4, 3), np.uint8)):
        with pytest.raises(ValueError):
            preprocess_patch(bad)


# ----------------------------------------------------------------------------------------- checkpoints and ranges
@pytest.mark.parametrize("name", sorted(README_RANGES))
def test_published_checkpoints_load_strictly_with_their_ranges(weights_dir, name):
    path = weights_dir / name
    state = torch.load(path, map_location="cpu", weights_only=True)
    assert set(state) == EXPECTED_KEYS
    net = MassNet()
    net.load_state_dict(state, strict=True)
    assert sum(p.numel() for p in net.parameters()) == 532_752

    model = load_checkpoint(path)
    assert not model.net.training
    assert next(model.net.parameters()).device.type == "cpu" == model.device.type
    assert model.ranges == Ranges(*README_RANGES[name])
    assert model.weights_id == W.PUBLISHED[name].sha256[:12] == W.sha256_file(path)[:12]
    for k, v in model.net.state_dict().items():
        assert torch.equal(v, state[k]), k


def test_published_table_matches_readme(weights_dir):
    readme = (weights_dir / "README.md").read_text()
    for name, pub in W.PUBLISHED.items():
        assert pub.sha256 in readme and name in readme
        assert pub.ranges == README_RANGES[name]


def test_ranges_normalise_and_denormalise():
    r = Ranges(*README_RANGES["Encoder_pool_aug_fold1_35.torch"])
    f = r.normalise_features([[0.01, 0.03, 276.0], [0.45, 0.96, 1523.34], [0.23, 0.495, 899.67]])
    assert f.dtype == np.float32
    np.testing.assert_allclose(f, [[0, 0, 0], [1, 1, 1], [0.5, 0.5, 0.5]], atol=1e-6)
    np.testing.assert_allclose(r.denormalise_mass([0.0, 1.0, 0.5, -1.0]), [3.0, 86.0, 44.5, 0.0], rtol=1e-6)
    assert Ranges.from_dict(r.to_dict()) == r
    with pytest.raises(ValueError):
        r.normalise_features(np.zeros((2, 2)))
    with pytest.raises(ValueError):
        Ranges(1, 0, 0, 1, 0, 1, 0, 1)  # max below min


def test_clamp_at_zero(weights_dir, golden_inputs):
    model = load_checkpoint(weights_dir / "Encoder_pool_aug_158.torch")
    patches, feats = golden_inputs
    with torch.no_grad():
        model.net.linear3.bias.fill_(-50.0)
        raw = model.net(preprocess_patches(patches), torch.from_numpy(model.ranges.normalise_features(feats)))
    assert (raw < -1).all()  # unclamped this would be far below 0 g
    pred = model.predict(patches, feats)
    np.testing.assert_array_equal(pred, np.zeros(len(patches), np.float32))


def _unpublished_copy(weights_dir: Path, dest: Path) -> Path:
    """A plain state_dict equal to the 158 weights but not byte-identical to any published file."""
    state = torch.load(weights_dir / "Encoder_pool_aug_158.torch", map_location="cpu", weights_only=True)
    torch.save({k: v.clone() for k, v in state.items()}, dest)
    assert W.published_by_sha256(W.sha256_file(dest)) is None
    return dest


def test_sidecar_ranges(weights_dir, tmp_path, golden_inputs):
    ckpt = _unpublished_copy(weights_dir, tmp_path / "mine.torch")
    ranges = Ranges(*README_RANGES["Encoder_pool_aug_fold1_35.torch"])
    (tmp_path / "mine.torch.ranges.json").write_text(json.dumps(ranges.to_dict()))
    model = load_checkpoint(ckpt)
    assert model.ranges == ranges
    assert model.weights_id == W.sha256_file(ckpt)[:12]
    reference = load_checkpoint(weights_dir / "Encoder_pool_aug_158.torch", ranges=ranges)
    patches, feats = golden_inputs
    np.testing.assert_array_equal(model.predict(patches, feats), reference.predict(patches, feats))
    # and the ranges do matter: the same weights with the 158 ranges predict something else
    assert not np.allclose(model.predict(patches, feats),
                           load_checkpoint(weights_dir / "Encoder_pool_aug_158.torch").predict(patches, feats))


def test_missing_or_bad_sidecar(weights_dir, tmp_path):
    ckpt = _unpublished_copy(weights_dir, tmp_path / "mine.torch")
    with pytest.raises(WeightsError) as e:
        load_checkpoint(ckpt)
    assert "mine.torch.ranges.json" in str(e.value) and "\n" not in str(e.value)
    assert e.value.path == str(ckpt)

    sidecar = tmp_path / "mine.torch.ranges.json"
    good = Ranges(*README_RANGES["Encoder_pool_aug_158.torch"]).to_dict()
    for bad in ("{not json", json.dumps({k: v for k, v in good.items() if k != "maxMass"}),
                json.dumps({**good, "maxMass": "heavy"}), json.dumps([1, 2, 3])):
        sidecar.write_text(bad)
        with pytest.raises(WeightsError) as e:
            load_checkpoint(ckpt)
        assert "mine.torch.ranges.json" in str(e.value)


def test_unreadable_or_mismatched_checkpoint(weights_dir, tmp_path):
    with pytest.raises(WeightsError, match="not found"):
        load_checkpoint(tmp_path / "nope.torch")
    garbage = tmp_path / "garbage.torch"
    garbage.write_bytes(b"definitely not a checkpoint")
    with pytest.raises(WeightsError, match="garbage.torch"):
        load_checkpoint(garbage)
    state = torch.load(weights_dir / "Encoder_pool_aug_158.torch", map_location="cpu", weights_only=True)
    state["linear3.weight"] = torch.zeros(1, 8)
    del state["bn5.running_var"]
    wrong = tmp_path / "wrong.torch"
    torch.save(state, wrong)
    with pytest.raises(WeightsError) as e:
        load_checkpoint(wrong, ranges=Ranges(*README_RANGES["Encoder_pool_aug_158.torch"]))
    msg = str(e.value)
    assert "wrong.torch" in msg and "bn5.running_var" in msg and "linear3.weight" in msg and "\n" not in msg


def test_save_checkpoint_round_trip(model158, tmp_path, golden_inputs):
    ranges = Ranges(*README_RANGES["Encoder_pool_aug_fold2_86.torch"])
    path = save_checkpoint(tmp_path / "sub" / "trained.pt", model158, ranges, extra={"epoch": 3, "split": "F3"})
    assert [p.name for p in path.parent.iterdir()] == ["trained.pt"]  # no temporary file left behind
    umask = os.umask(0)
    os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask  # the usual permissions, not mkstemp's private 0600
    raw = torch.load(path, map_location="cpu", weights_only=True)
    assert raw["ranges"] == ranges.to_dict() and raw["extra"] == {"epoch": 3, "split": "F3"}
    loaded = load_checkpoint(path)
    assert loaded.ranges == ranges and not loaded.net.training
    assert loaded.weights_id == W.sha256_file(path)[:12] != model158.weights_id
    patches, feats = golden_inputs
    with_override = MassPredictor(MassNet(), ranges)
    with_override.net.load_state_dict(model158.net.state_dict())
    np.testing.assert_array_equal(loaded.predict(patches, feats), with_override.predict(patches, feats))


def test_predict_without_ranges_is_an_error():
    with pytest.raises(WeightsError):
        MassPredictor(MassNet()).predict(random_patches(3, 1), [[0.1, 0.1, 500.0]])


# ------------------------------------------------------------------------------------------------ weights resolution
def test_resolve_explicit_and_env(weights_dir, tmp_path, monkeypatch, no_weights_env):
    p = weights_dir / "Encoder_pool_aug_fold0_94.torch"
    assert W.resolve_weights(p) == p
    with pytest.raises(WeightsError, match="missing.torch"):
        W.resolve_weights(tmp_path / "missing.torch")
    monkeypatch.setenv(W.ENV_WEIGHTS, str(p))
    assert W.resolve_weights() == p
    monkeypatch.setenv(W.ENV_WEIGHTS, str(tmp_path / "gone.torch"))
    with pytest.raises(WeightsError, match="gone.torch"):
        W.resolve_weights()


def test_download_via_file_url_into_cache(weights_dir, monkeypatch, no_weights_env):
    monkeypatch.setenv(W.ENV_URL, weights_dir.as_uri())
    got = W.resolve_weights(name="Encoder_pool_aug_fold1_35.torch")
    assert got == no_weights_env / "Encoder_pool_aug_fold1_35.torch"
    assert W.sha256_file(got) == W.PUBLISHED["Encoder_pool_aug_fold1_35.torch"].sha256
    assert sorted(p.name for p in no_weights_env.iterdir()) == ["Encoder_pool_aug_fold1_35.torch"]
    assert load_checkpoint(got).ranges == Ranges(*README_RANGES["Encoder_pool_aug_fold1_35.torch"])
    # second call is served from the cache: no source needed any more
    monkeypatch.setenv(W.ENV_URL, (no_weights_env.parent / "no-such-folder").as_uri())
    assert W.resolve_weights(name="Encoder_pool_aug_fold1_35.torch") == got
    # a corrupted cached file is fetched again (here: cannot be, so it is an error, not a silent bad file)
    got.write_bytes(b"corrupt")
    with pytest.raises(WeightsError, match="--weights PATH"):
        W.resolve_weights(name="Encoder_pool_aug_fold1_35.torch")


def test_download_wrong_checksum_leaves_nothing(weights_dir, tmp_path):
    dest = tmp_path / "cache"
    with pytest.raises(WeightsError, match="sha256"):
        W.download_published("Encoder_pool_aug_158.torch", dest, base_url=weights_dir.as_uri(), expected_sha256="0" * 64,
                   progress=False)
    assert list(dest.iterdir()) == []


def test_download_failure_says_how_to_run_offline(tmp_path):
    with pytest.raises(WeightsError) as e:
        W.download_published("Encoder_pool_aug_158.torch", tmp_path / "c", base_url=(tmp_path / "nowhere").as_uri(),
                   progress=False)
    assert "--weights PATH" in str(e.value) and W.ENV_WEIGHTS in str(e.value)
    assert list((tmp_path / "c").iterdir()) == []
    with pytest.raises(WeightsError, match="unknown published checkpoint"):
        W.download_published("Encoder_77.torch", tmp_path)


def test_a_run_with_the_mass_cnn_does_not_import_torchvision(weights, samples_dir):
    """Start-up: torchvision's import pulls in ``torch._dynamo`` (2.2 of a command's 4.7 s); the mass CNN's
    preprocessing calls Pillow directly (held equal to torchvision's transforms above), so only Mask R-CNN (and
    training) import torchvision."""
    import subprocess
    import sys

    code = f"""
import sys
import massviz as mv
pipeline = mv.build_pipeline(detector="depth", weights={str(weights)!r}, stride=9, quiet=True)
trace = pipeline.process(mv.open_recording({str(samples_dir / "cup_handover")!r}))
assert trace.estimate > 0 and len(trace.selection), trace.estimate
print(sorted(m for m in sys.modules if m.split(".")[0] == "torchvision"))
"""
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                         cwd=Path(__file__).resolve().parents[1])
    assert run.returncode == 0, run.stderr[-2000:]
    assert run.stdout.strip().splitlines()[-1] == "[]", run.stdout[-2000:]
