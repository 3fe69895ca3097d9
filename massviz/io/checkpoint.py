"""Mass-CNN checkpoint files: :func:`load_checkpoint` reads one (a published state_dict or a massviz checkpoint) into
a ``massviz.core.model.MassNet`` with its normalisation ranges, :func:`save_checkpoint` writes one atomically.
"""
from __future__ import annotations

from pathlib import Path

import torch

from massviz.core.model import MassNet, Ranges
from massviz.errors import WeightsError
from massviz.io.atomic import atomic_path
from massviz.io.weights import PUBLISHED, published_by_sha256, sha256_file

#: value of ``"format"`` in checkpoints written by :func:`save_checkpoint`.
CHECKPOINT_FORMAT = "massviz.massnet/1"
#: suffix of the ranges file expected beside a checkpoint that carries no ranges: ``<checkpoint>.ranges.json``.
SIDECAR_SUFFIX = ".ranges.json"


def load_checkpoint(path: str | Path, ranges: Ranges | None = None) -> MassNet:
    """Load a checkpoint on the CPU in eval mode, with its normalisation ranges.

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

    model = MassNet(ranges=ranges, weights_id=sha[:12])
    _check_state_dict(model, state, path)
    for name, value in state.items():  # NaN weights would turn every prediction into NaN, silently
        if value.is_floating_point() and not bool(torch.isfinite(value).all()):
            raise WeightsError(f"parameter {name} holds NaN or infinite values (a diverged training?)", path)
    model.load_state_dict(state, strict=True)
    return model.eval()


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


def save_checkpoint(path: str | Path, model: MassNet, ranges: Ranges, extra: dict | None = None) -> Path:
    """Write a massviz checkpoint ``{"format", "state_dict", "ranges", "extra"}`` atomically (temp file + rename).

    ``extra`` (e.g. epoch, split, metrics) must hold plain Python values (str, int, float, bool, lists, dicts) so the
    file loads with ``torch.load(weights_only=True)``. :func:`load_checkpoint` reads the file back.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {
        "format": CHECKPOINT_FORMAT,
        "state_dict": {k: v.detach().cpu().clone() for k, v in model.state_dict().items()},
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
