"""Mass-CNN checkpoint files: :func:`load_checkpoint` reads one (a published state_dict or a massviz checkpoint) into
a ``massviz.core.predictor.MassPredictor`` (the ``massviz.core.model.MassNet`` network with its normalisation ranges),
:func:`save_checkpoint` writes one atomically.
"""
from __future__ import annotations

from pathlib import Path

import torch

from massviz.core.model import MassNet, Ranges
from massviz.core.predictor import MassPredictor
from massviz.errors import WeightsError
from massviz.io.atomic import atomic_path
from massviz.io.weights import PUBLISHED, published_by_sha256, sha256_file

#: value of ``"format"`` in checkpoints written by :func:`save_checkpoint`.
CHECKPOINT_FORMAT = "massviz.massnet/1"
#: suffix of the ranges file expected beside a checkpoint that carries no ranges: ``<checkpoint>.ranges.json``.
SIDECAR_SUFFIX = ".ranges.json"
#: largest magnitude a normalisation range may have (distances in mm, ratios, grams: all far below).
MAX_RANGE_MAGNITUDE = 1e7
#: smallest span (max - min) of a normalisation range: below it normalised features overflow float32.
MIN_RANGE_SPAN = 1e-6
#: largest magnitude of a weight (float32's range, with room for the products a forward pass makes).
MAX_WEIGHT_MAGNITUDE = 1e6


def load_checkpoint(path: str | Path, ranges: Ranges | None = None) -> MassPredictor:
    """Load a checkpoint: a :class:`MassPredictor` whose network is on the CPU in eval mode, with the checkpoint's
    normalisation ranges and ``weights_id``.

    Ranges, first found wins: the ``ranges`` argument; the ``"ranges"`` of a massviz checkpoint (see
    :func:`save_checkpoint`); the table of published checkpoints, by the file's sha256; the sidecar
    ``<checkpoint>.ranges.json`` (the eight keys of :data:`massviz.core.model.RANGE_KEYS`). None of these, an
    unreadable file or a state_dict that does not fit raises :class:`WeightsError` naming the file.
    """
    path = Path(path)
    if not path.is_file():
        raise WeightsError("checkpoint file not found", path)
    try:
        sha = sha256_file(path)
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises many types for a corrupt / foreign file
        first = str(e).splitlines()[0][:200] if str(e).strip() else "empty or truncated file"
        raise WeightsError(f"cannot read checkpoint ({type(e).__name__}: {first})", path) from None
    embedded = None
    if isinstance(obj, dict) and "state_dict" in obj:
        state, embedded = obj["state_dict"], obj.get("ranges")
    else:
        state = obj
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise WeightsError("not a MassNet state_dict (nor a massviz checkpoint holding one)", path)

    if ranges is None:
        if embedded is not None:
            ranges = Ranges.from_dict(embedded, path)
        elif (pub := published_by_sha256(sha)) is not None:
            ranges = Ranges(*pub.ranges)
        else:
            ranges = _read_sidecar(path)

    check_ranges(ranges, path)
    net = MassNet()
    _check_state_dict(net, state, path)
    _check_tensors(state, path)
    net.load_state_dict(state, strict=True)
    # the path is named by the error of a prediction that still overflows
    model = MassPredictor(net.eval(), ranges, sha[:12], checkpoint_path=str(path))
    _probe(model, path)
    return model


def check_ranges(ranges: Ranges, path) -> None:
    """Ranges that would make normalised features or masses overflow float32: a span below MIN_RANGE_SPAN or a
    value beyond MAX_RANGE_MAGNITUDE. :class:`WeightsError` naming ``path``."""
    from massviz.core.model import RANGE_KEYS

    values = ranges.as_tuple()
    for key, v in zip(RANGE_KEYS, values):
        if abs(v) > MAX_RANGE_MAGNITUDE:
            raise WeightsError(f"range {key} = {v:g} is beyond +-{MAX_RANGE_MAGNITUDE:g}", path)
    for lo_key, lo, hi in zip(RANGE_KEYS[0::2], values[0::2], values[1::2]):
        if hi - lo < MIN_RANGE_SPAN:
            raise WeightsError(f"range {lo_key[3:]} spans {hi - lo:g} (max - min must be at least "
                               f"{MIN_RANGE_SPAN:g})", path)


def _check_tensors(state: dict, path: Path) -> None:
    """Complex numbers, NaN, infinite (also once cast to the model's float32: a float64 1e300 is inf there), too
    large weights and negative BatchNorm variances would turn every prediction into NaN or inf, silently."""
    for name, value in state.items():
        if value.is_complex():  # loading would drop the imaginary part (torch warns), silently changing the model
            raise WeightsError(f"parameter {name} holds complex numbers ({str(value.dtype).removeprefix('torch.')}); "
                               "a MassNet checkpoint holds real weights", path)
        if not value.is_floating_point():
            continue
        as32 = value.detach().to(torch.float32)
        if not bool(torch.isfinite(as32).all()):
            raise WeightsError(f"parameter {name} holds NaN or infinite values (in float32; a diverged training?)",
                               path)
        if as32.numel() and float(as32.abs().max()) > MAX_WEIGHT_MAGNITUDE:
            raise WeightsError(f"parameter {name} holds values beyond +-{MAX_WEIGHT_MAGNITUDE:g} "
                               f"({float(as32.abs().max()):g}; a diverged training?)", path)
        if name.endswith("running_var") and bool((as32 < 0).any()):
            raise WeightsError(f"parameter {name} holds a negative variance", path)


def _probe(model: MassPredictor, path: Path) -> None:
    """One prediction on a grey patch at the middle of the ranges: a checkpoint whose numbers are each finite but
    overflow together is refused here, not after a whole recording."""
    import numpy as np

    r = model.ranges
    feats = np.array([[(r.min_ratio_width + r.max_ratio_width) / 2, (r.min_ratio_height + r.max_ratio_height) / 2,
                       (r.min_distance + r.max_distance) / 2]])
    try:
        with torch.no_grad():
            pred = model.predict([np.full((32, 32, 3), 128, np.uint8)], feats)
    except Exception as err:  # noqa: BLE001 - weights that fit the shapes but cannot be evaluated
        raise WeightsError(f"cannot evaluate the checkpoint ({type(err).__name__}: {err})"[:300], path) from None
    if not np.isfinite(pred).all():
        raise WeightsError("the checkpoint predicts a non-finite mass (its weights or ranges overflow)", path)


def _read_sidecar(path: Path) -> Ranges:
    sidecar = path.with_name(path.name + SIDECAR_SUFFIX)
    if not sidecar.is_file():
        hint = (" (it is named like a published checkpoint but its sha256 differs)" if path.name in PUBLISHED else "")
        raise WeightsError(f"checkpoint carries no normalisation ranges and its ranges file {sidecar} is missing"
                           f"{hint}", path)
    from massviz.io.untrusted import load_json

    data = load_json(sidecar, "ranges file", WeightsError)
    return Ranges.from_dict(data, sidecar)


def _check_state_dict(model: MassNet, state: dict, path: Path) -> None:
    """One-line :class:`WeightsError` for missing / unexpected / mis-shaped keys (load_state_dict's is multi-line)."""
    expected = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    got = {k: tuple(v.shape) for k, v in state.items()}
    problems = []
    if missing := sorted(set(expected) - set(got)):
        problems.append(f"missing {', '.join(missing)}")
    if unexpected := sorted(set(got) - set(expected)):
        problems.append(f"unexpected {', '.join(unexpected)}")
    if shapes := [f"{k} {got[k]} (want {expected[k]})" for k in sorted(set(got) & set(expected))
                  if got[k] != expected[k]]:
        problems.append(f"wrong shape {', '.join(shapes)}")
    if problems:
        raise WeightsError(f"state_dict does not fit MassNet: {'; '.join(problems)}", path)


def save_checkpoint(path: str | Path, model: MassNet | MassPredictor, ranges: Ranges,
                    extra: dict | None = None) -> Path:
    """Write a massviz checkpoint ``{"format", "state_dict", "ranges", "extra"}`` atomically (temp file + rename):
    the weights of ``model`` (a :class:`MassNet`, or a :class:`MassPredictor`'s network) with ``ranges``.

    ``extra`` (e.g. epoch, split, metrics) must hold plain Python values (str, int, float, bool, lists, dicts) so the
    file loads with ``torch.load(weights_only=True)``. :func:`load_checkpoint` reads the file back.
    """
    path = Path(path)
    net = model.net if isinstance(model, MassPredictor) else model
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {
        "format": CHECKPOINT_FORMAT,
        "state_dict": {k: v.detach().cpu().clone() for k, v in net.state_dict().items()},
        "ranges": ranges.to_dict(),
        "extra": dict(extra or {}),
    }
    with atomic_path(path) as tmp:
        torch.save(payload, tmp)
    return path


def published_ranges(name: str) -> Ranges:
    """Ranges of a published checkpoint, by file name (e.g. ``"Encoder_pool_aug_158.torch"``)."""
    return Ranges(*PUBLISHED[name].ranges)


__all__ = ["CHECKPOINT_FORMAT", "SIDECAR_SUFFIX", "load_checkpoint", "save_checkpoint", "published_ranges"]
