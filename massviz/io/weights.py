"""Where the mass CNN's weights come from: the published checkpoints, the cache, the one-time download.

The four checkpoints of Apicella et al. (ICASSP 2022) are published in the authors' repository
(github.com/CORSMAL/Visual, MIT licence, Copyright (c) 2021 CORSMAL) under ``demo/``. We pin the commit, know each
file's sha256 and the normalisation ranges it was trained with (the ranges are not stored in the files; the authors
keep them as commented-out constants in ``demo/generate_video_inference.py``), so a published file identifies itself
by its hash wherever it lives.

Resolution order of :func:`resolve_weights`: an explicit path, else ``$MASSVIZ_WEIGHTS``, else the cached copy
(``$MASSVIZ_CACHE_DIR`` or ``platformdirs.user_cache_dir("massviz")``, sub-folder ``weights/``: put there by
:func:`install_checkpoint`, as ``scripts/setup.sh`` does with a reference copy it finds, or by the download), else
downloaded once from ``$MASSVIZ_WEIGHTS_URL`` (default :data:`DEFAULT_URL_BASE`), sha256-checked and written
atomically.

Importing this module needs neither torch nor numpy (:func:`download` imports ``torch.hub`` when it runs).
"""
from __future__ import annotations

import hashlib
import os
import re
import urllib.error
from dataclasses import dataclass
from pathlib import Path

from massviz.errors import WeightsError

#: the authors' repository commit the published checkpoints are pinned to.
PINNED_COMMIT = "5dd86a0a6a9960da308341853caba37ada2ffc1a"
#: base URL of the published checkpoints; a file name is appended. Overridden by ``$MASSVIZ_WEIGHTS_URL``.
DEFAULT_URL_BASE = f"https://github.com/CORSMAL/Visual/raw/{PINNED_COMMIT}/demo/"
#: the paper's VAL / challenge model, trained on the whole CCM training set.
DEFAULT_NAME = "Encoder_pool_aug_158.torch"

ENV_WEIGHTS = "MASSVIZ_WEIGHTS"
ENV_CACHE_DIR = "MASSVIZ_CACHE_DIR"
ENV_URL = "MASSVIZ_WEIGHTS_URL"

OFFLINE_HINT = f"to run offline pass --weights PATH or set {ENV_WEIGHTS}=PATH"


@dataclass(frozen=True)
class PublishedCheckpoint:
    """One of the authors' checkpoints: file name, sha256, training split, ranges (in ``massviz.core.model.RANGE_KEYS`` order)."""

    name: str
    sha256: str
    trained_on: str
    ranges: tuple[float, float, float, float, float, float, float, float]


PUBLISHED: dict[str, PublishedCheckpoint] = {c.name: c for c in (
    PublishedCheckpoint("Encoder_pool_aug_158.torch",
                        "e0a9eb00f6e95996dc5697dba87f445758c5f44a20d9c556fc7f67a4eba470b9",
                        "whole CCM training set, random 80:20 split (VAL / challenge model)",
                        (291.53, 1533.87, 0.01, 0.46, 0.03, 0.90, 2.0, 134.0)),
    PublishedCheckpoint("Encoder_pool_aug_fold0_94.torch",
                        "69835f645db2a4aff6f350d597f5638c89d95c88e70d7e1a9491e24581e4bdeb",
                        "fold F1 (test containers 3, 6, 9)",
                        (276.0, 1534.06, 0.01, 0.45, 0.03, 0.96, 2.0, 134.0)),
    PublishedCheckpoint("Encoder_pool_aug_fold1_35.torch",
                        "4b313a1dd5afa79c2cd36b8abd574f6624ca8900a9375bf8397ee70cfc782eef",
                        "fold F2 (test containers 2, 5, 8)",
                        (276.0, 1523.34, 0.01, 0.45, 0.03, 0.96, 3.0, 86.0)),
    PublishedCheckpoint("Encoder_pool_aug_fold2_86.torch",
                        "ecd4f41c7c2be51e249935f254a66c1b591e11bff60796cc9d1b9bd27269d8eb",
                        "fold F3 (test containers 1, 4, 7)",
                        (310.14, 1534.06, 0.04, 0.38, 0.08, 0.86, 2.0, 134.0)),
)}


def published_by_sha256(sha256: str) -> PublishedCheckpoint | None:
    """The published checkpoint with this sha256, or None."""
    return next((c for c in PUBLISHED.values() if c.sha256 == sha256.lower()), None)


def sha256_file(path: str | Path) -> str:
    """Hex sha256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def cache_dir() -> Path:
    """Folder the downloaded weights live in: ``$MASSVIZ_CACHE_DIR/weights`` or the user cache's ``weights``."""
    base = os.environ.get(ENV_CACHE_DIR)
    if not base:
        import platformdirs  # only for the default folder (a CUDA image without it runs with --weights)

        base = platformdirs.user_cache_dir("massviz")
    return Path(base) / "weights"


def url_base() -> str:
    """Base URL for downloads: ``$MASSVIZ_WEIGHTS_URL`` (e.g. a ``file://`` folder) or :data:`DEFAULT_URL_BASE`."""
    base = os.environ.get(ENV_URL) or DEFAULT_URL_BASE
    return base if base.endswith("/") else base + "/"


def _published(name: str) -> PublishedCheckpoint:
    try:
        return PUBLISHED[name]
    except KeyError:
        raise WeightsError(f"unknown published checkpoint; choose one of {', '.join(PUBLISHED)}", name) from None


def download(url: str, dst: str | Path, sha256: str, *, progress: bool = True, hint: str = OFFLINE_HINT) -> Path:
    """Download ``url`` to the file ``dst`` (its folder is created) and return ``dst``; the one downloader of massviz.

    ``torch.hub.download_url_to_file`` does the transfer: the bytes go to a temporary file beside ``dst``, are hashed
    on the way and only moved into place when their sha256 is ``sha256``, so a failed or corrupt download leaves
    nothing behind. A tqdm bar on stderr shows progress (``progress``). Any failure raises :class:`WeightsError`
    naming the URL, ending with ``hint`` (how to do without the download).
    """
    from torch.hub import download_url_to_file

    dst = Path(dst)
    expected = str(sha256).lower()
    if not re.fullmatch(r"[0-9a-f]{64}", expected):  # torch.hub checks a prefix: an empty one would check nothing
        raise ValueError(f"sha256 must be 64 hex digits, got {sha256!r}"[:200])
    try:
        dst.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise WeightsError(f"cannot create the download folder ({e.strerror or e}); {hint}", dst.parent) from e
    try:
        download_url_to_file(url, str(dst), hash_prefix=expected, progress=progress)
    except RuntimeError as e:  # torch.hub's hash mismatch; its temporary file is removed
        raise WeightsError(f"downloaded file does not have sha256 {expected} ({e}); nothing was kept; {hint}",
                           url) from e
    except (urllib.error.URLError, OSError, ValueError) as e:
        reason = getattr(e, "reason", None) or getattr(e, "strerror", None) or e
        raise WeightsError(f"cannot download ({reason}); {hint}", url) from e
    return dst


def download_published(name: str = DEFAULT_NAME, dest_dir: str | Path | None = None, *,
                       base_url: str | None = None, expected_sha256: str | None = None,
                       progress: bool = True) -> Path:
    """Download a published checkpoint into ``dest_dir`` (default :func:`cache_dir`) with :func:`download` and return
    its path (checked against ``expected_sha256``, default the published one)."""
    expected = expected_sha256 or _published(name).sha256
    dest_dir = Path(dest_dir) if dest_dir is not None else cache_dir()
    url = (base_url if base_url is not None else url_base()).rstrip("/") + "/" + name
    return download(url, dest_dir / name, expected, progress=progress)


def resolve_weights(path: str | Path | None = None, *, name: str = DEFAULT_NAME) -> Path:
    """The checkpoint file to use.

    1. ``path`` given: that file (missing → :class:`WeightsError`).
    2. else ``$MASSVIZ_WEIGHTS``: that file (missing → :class:`WeightsError`).
    3. else the published checkpoint ``name`` from the cache, downloaded once (see :func:`download`). A cached file
       whose sha256 does not match is downloaded again.
    """
    explicit = path if path is not None else (os.environ.get(ENV_WEIGHTS) or None)
    if explicit is not None:
        p = Path(explicit).expanduser()
        if not p.is_file():
            source = "weights file" if path is not None else f"weights file (from ${ENV_WEIGHTS})"
            raise WeightsError(f"{source} not found", p)
        return p
    pub = _published(name)
    cached = cache_dir() / name
    if cached.is_file() and sha256_file(cached) == pub.sha256:
        return cached
    return download_published(name)


def install_checkpoint(src: str | Path) -> Path:
    """Copy a published checkpoint found on disk (e.g. a reference copy beside the repository) into the cache, where
    :func:`resolve_weights` finds it without ``$MASSVIZ_WEIGHTS`` and without a download; return the cached path.

    The file must be one of :data:`PUBLISHED` (recognised by its sha256), else :class:`WeightsError`; an identical
    cached copy is kept as it is. The copy is written whole or not at all.
    """
    from massviz.io.atomic import atomic_path

    src = Path(src).expanduser()
    if not src.is_file():
        raise WeightsError("weights file not found", src)
    pub = published_by_sha256(sha256_file(src))
    if pub is None:
        raise WeightsError("not one of the published checkpoints (sha256 unknown); pass it with --weights instead",
                           src)
    cached = cache_dir() / pub.name
    if cached.is_file() and sha256_file(cached) == pub.sha256:
        return cached
    try:
        cached.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise WeightsError(f"cannot create the cache folder ({e.strerror or e})", cached.parent) from e
    with atomic_path(cached) as tmp:
        tmp.write_bytes(src.read_bytes())
    return cached


__all__ = [
    "PINNED_COMMIT", "DEFAULT_URL_BASE", "DEFAULT_NAME", "PublishedCheckpoint", "PUBLISHED",
    "published_by_sha256", "sha256_file", "cache_dir", "url_base", "download", "download_published",
    "resolve_weights", "install_checkpoint"]
