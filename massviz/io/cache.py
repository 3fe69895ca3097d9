"""On-disk cache of traces, so another K, a higher threshold or another model never re-runs the detector.

Entries are keyed by the recording's content fingerprint (a BLAKE2b digest of the bytes of every RGB and depth file,
``Recording.fingerprint``; each file's digest is remembered in ``hashes/`` by its path, size, mtime, ctime and inode,
so only new or changed files are read again), the detector's name and settings (except its threshold; a replay
source or detector weights by their content too) and the stride. Inside an entry one file per detection threshold: detections made at threshold t serve every
threshold >= t, so a lookup takes the entry with the largest t <= the threshold asked for.

An entry that cannot be decoded (truncated, garbage, not a file) is dropped and recomputed, never fatal; a cache
that cannot be written is found before any work (``check_writable``).

Location: ``--cache PATH``, else env ``MASSVIZ_CACHE_DIR``, else the user cache directory (platformdirs).
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import sys
from pathlib import Path

import platformdirs

from massviz.errors import MassvizError
from massviz.io.filehash import FileHasher
from massviz.io.untrusted import safe_filename
from massviz.io.recording import Recording
from massviz.core.trace import Trace
from massviz.io.trace_file import load_trace, save_trace


def default_cache_dir() -> Path:
    return Path(os.environ.get("MASSVIZ_CACHE_DIR") or platformdirs.user_cache_dir("massviz"))


class TraceCache:
    """Traces under ``root/traces/<recording id>-<key>/t<threshold>.npz``."""

    def __init__(self, root: str | Path | None = None):
        self.root = Path(root) if root else default_cache_dir()
        self.dir = self.root / "traces"
        self.hasher = FileHasher(self.root / "hashes")

    def check_writable(self) -> "TraceCache":
        """``MassvizError`` naming the cache folder when it is not a folder or cannot be written (checked before any
        work starts, so a run never fails at its end for want of a cache)."""
        from massviz.io.atomic import check_output_dir

        try:
            check_output_dir(self.root)
        except MassvizError as err:
            raise MassvizError(f"trace cache: {str(err).removeprefix(f'{self.root}: ')} (use --no-cache or another "
                               "--cache DIR)", self.root) from None
        return self

    def entry(self, recording: Recording, detector_info: dict, stride: int) -> Path:
        key = json.dumps({"recording": recording.fingerprint(self.hasher), "detector": detector_info,
                          "stride": stride}, sort_keys=True, default=str)
        digest = hashlib.sha1(key.encode()).hexdigest()[:16]
        return self.dir / f"{safe_filename(recording.id, 60)}-{digest}"

    def lookup(self, recording: Recording, detector_info: dict, stride: int, threshold: float) -> Path | None:
        """Path of the cached trace made at the largest threshold <= ``threshold``, or None."""
        entry = self.entry(recording, detector_info, stride)
        best = None
        for p in entry.glob("t*.npz") if entry.is_dir() else []:
            try:
                t = float(p.stem[1:])
            except ValueError:
                continue
            if t <= threshold + 1e-9 and (best is None or t > best[0]):
                best = (t, p)
        return best[1] if best else None

    def load(self, recording: Recording, detector_info: dict, stride: int, threshold: float) -> Trace | None:
        path = self.lookup(recording, detector_info, stride, threshold)
        if path is None:
            return None
        try:
            trace = load_trace(path)
        except Exception:  # noqa: BLE001 - whatever is wrong with an entry, it is dropped and recomputed
            _drop(path)
            return None
        return trace if trace.detect_threshold <= threshold else None

    def save(self, trace: Trace, recording: Recording, detector_info: dict) -> Path | None:
        """Write the trace's entry; a file system refusal at this point (the folder was checked writable before
        the work) is a warning, not a failure: the result stands, it is only not cached."""
        entry = self.entry(recording, detector_info, trace.stride)
        path = entry / f"t{float(trace.detect_threshold)!r}.npz"  # exact: t0.4.npz, t0.40005.npz
        try:
            if path.is_dir():
                _drop(path)
            return save_trace(trace, path)
        except (OSError, MassvizError) as err:
            what = getattr(err, "strerror", None) or str(err)
            print(f"massviz: warning: {path}: cannot write the trace cache entry ({what}); the result is not cached",
                  file=sys.stderr)
            return None


def _drop(path: Path) -> None:
    """Remove a cache entry file (or whatever stands in its place) if possible."""
    try:
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        else:
            path.unlink(missing_ok=True)
    except OSError:
        pass
