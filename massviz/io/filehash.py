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

    @staticmethod
    def _read(memo: Path | None) -> dict:
        if memo is None:
            return {}
        from massviz.errors import MassvizError
        from massviz.io.untrusted import load_json

        try:
            data = load_json(memo, "digest memo")
        except MassvizError:
            return {}  # missing, unreadable or hostile memory: hash again and rewrite it
        return data if isinstance(data, dict) else {}

    def digests(self, paths, group: str) -> list[str]:
        memo = self._memo_path(group)
        disk = self._read(memo)
        out, changed = [], False
        for p in paths:
            key = os.path.abspath(p)
            ident = identity(os.stat(p))
            with self._lock:
                known = self._memory.get(key)
            if known is None and isinstance(disk.get(key), list) and len(disk[key]) == 2:
                known = tuple(disk[key])
            if known is not None and known[0] == ident and isinstance(known[1], str):
                digest = known[1]
            else:
                digest = file_digest(p)
                if identity(os.stat(p)) != ident:  # written while read: do not remember a moving target
                    out.append(digest)
                    continue
                changed = True
            with self._lock:
                self._memory[key] = (ident, digest)
            disk[key] = [ident, digest]
            out.append(digest)
        if changed and memo is not None:
            self._write(memo, disk)
        return out

    @staticmethod
    def _write(memo: Path, disk: dict) -> None:
        try:
            memo.parent.mkdir(parents=True, exist_ok=True)
            with atomic_path(memo) as tmp:
                tmp.write_text(json.dumps(disk))
        except (OSError, MassvizError):
            pass  # the memory is an optimisation: files are hashed again next time (atomic_path left nothing)


__all__ = ["DIGEST_SIZE", "file_digest", "identity", "FileHasher"]
