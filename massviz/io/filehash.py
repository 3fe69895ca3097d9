"""Content digests of input files, remembered by each file's identity so that a large dataset is hashed once.

The trace cache keys a recording by the *bytes* of its files: an edit that keeps the size and sets the modification
time back (``touch -d``) still changes the key. Hashing every frame on every run would cost as much as reading the
dataset, so each file's digest is remembered with the file's (path, size, mtime_ns, ctime_ns, inode, device) and the
file is hashed again when any of them changes. A user can set mtime back but not ctime: every write changes it.

Digests are BLAKE2b-128 (``hashlib``, no extra dependency). With a ``store`` folder (the trace cache's
``hashes/``) the digests also outlive the process: one small JSON file per recording, written atomically; an
unreadable one is ignored and rewritten.
"""
from __future__ import annotations

import hashlib
import json
import os
import threading
from pathlib import Path

from massviz.errors import MassvizError
from massviz.io.atomic import atomic_path

DIGEST_SIZE = 16


def file_digest(path: str | Path) -> str:
    """BLAKE2b-128 of a file's bytes (hex)."""
    with open(path, "rb") as fh:
        return hashlib.file_digest(fh, lambda: hashlib.blake2b(digest_size=DIGEST_SIZE)).hexdigest()


def bytes_digest(data: bytes) -> str:
    """BLAKE2b-128 of ``data`` (hex): ``file_digest`` of a file whose bytes were read already."""
    return hashlib.blake2b(data, digest_size=DIGEST_SIZE).hexdigest()


def identity(st: os.stat_result) -> list[int]:
    """What must not change for a remembered digest to stand: size, mtime, ctime, inode, device."""
    return [st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino, st.st_dev]


class FileHasher:
    """``digests(paths, group)``: the content digest of each path, remembered by identity in memory and, with a
    ``store`` folder, on disk (``store/<sha1(group)>.json``; ``group`` is e.g. the recording's path)."""

    def __init__(self, store: str | Path | None = None):
        self.store = Path(store) if store else None
        self._memory: dict[str, tuple[list[int], str]] = {}
        self._lock = threading.Lock()

    def _memo_path(self, group: str) -> Path | None:
        if self.store is None:
            return None
        return self.store / f"{hashlib.sha1(group.encode()).hexdigest()[:20]}.json"

    def digests(self, paths, group: str, known: dict | None = None, read: bool = True) -> list[str] | None:
        """The digest of each of ``paths``. ``known`` (``{absolute path: (identity, digest) or None}``): the digests
        of the bytes a run read (``massviz.io.formats.common.read_bytes``), used first, so the key is of what the
        run processed; remembered only while the file's identity is the one read (a file changed since is hashed
        again next time); None for a file that changed while it was read: no key (None returned). Else the digest
        remembered (in memory, or in ``store`` under ``group``) while the file's identity is unchanged, else the file
        is read and hashed; ``read`` False: None instead of reading any file."""
        memo = self._memo_path(group)
        disk = read_memo(memo) if memo is not None else {}
        known = known or {}
        out, changed = [], False
        for p in paths:
            key = os.path.abspath(p)
            ident = identity(os.stat(p))
            if key in known:
                if known[key] is None:
                    return None
                read_ident, digest = known[key]
                if read_ident != ident:  # changed since the run read it: the key is of what the run read
                    out.append(digest)
                    continue
            else:
                with self._lock:
                    remembered = self._memory.get(key)
                on_disk = tuple(disk[key]) if isinstance(disk.get(key), list) and len(disk[key]) == 2 else None
                digest = next((c[1] for c in (remembered, on_disk)
                               if c is not None and c[0] == ident and isinstance(c[1], str)), None)
            if digest is None:
                if not read:
                    return None
                digest = file_digest(p)
                if identity(os.stat(p)) != ident:  # written while read: do not remember a moving target
                    out.append(digest)
                    continue
            with self._lock:
                self._memory[key] = (ident, digest)
            if disk.get(key) != [ident, digest]:
                disk[key] = [ident, digest]
                changed = True
            out.append(digest)
        if changed and memo is not None:
            write_memo(memo, disk)
        return out


def read_memo(path: Path) -> dict:
    """A JSON object massviz wrote as a memory (digests, file identities) with ``write_memo``, read as untrusted
    (``massviz.io.untrusted.load_json``); {} when missing, unreadable, hostile or not an object (it is rewritten)."""
    from massviz.io.untrusted import load_json

    try:
        data = load_json(path, "memo", max_bytes=64 << 20)
    except MassvizError:
        return {}
    return data if isinstance(data, dict) else {}


def write_memo(path: Path, doc: dict) -> None:
    """Write the memory ``doc`` (JSON) at ``path`` atomically; a failure is ignored (a memory is an optimisation:
    what it would have saved is done again next time; ``atomic_path`` leaves nothing behind)."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp:
            tmp.write_text(json.dumps(doc))
    except (OSError, MassvizError):
        pass


__all__ = ["DIGEST_SIZE", "file_digest", "bytes_digest", "identity", "FileHasher", "read_memo", "write_memo"]
