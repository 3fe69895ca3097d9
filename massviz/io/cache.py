"""On-disk cache of traces, so another K, a higher threshold or another model never re-runs the detector.

Entries are keyed by the recording's content fingerprint, the detector's name and settings (except its threshold)
and the stride. Inside an entry one file per detection threshold: detections made at threshold t serve every
threshold >= t, so a lookup takes the entry with the largest t <= the threshold asked for.

Location: ``--cache PATH``, else env ``MASSVIZ_CACHE_DIR``, else the user cache directory (platformdirs).
"""
from __future__ import annotations

import hashlib
import json
import os
import re
from pathlib import Path

import platformdirs

from massviz.errors import MassvizError
from massviz.io.recording import Recording
from massviz.core.trace import Trace


def default_cache_dir() -> Path:
    return Path(os.environ.get("MASSVIZ_CACHE_DIR") or platformdirs.user_cache_dir("massviz"))


class TraceCache:
    """Traces under ``root/traces/<recording id>-<key>/t<threshold>.npz``."""

    def __init__(self, root: str | Path | None = None):
        self.root = Path(root) if root else default_cache_dir()
        self.dir = self.root / "traces"

    def entry(self, recording: Recording, detector_info: dict, stride: int) -> Path:
        key = json.dumps({"recording": recording.fingerprint(), "detector": detector_info, "stride": stride},
                         sort_keys=True, default=str)
        digest = hashlib.sha1(key.encode()).hexdigest()[:16]
        safe = re.sub(r"[^A-Za-z0-9_.-]+", "_", recording.id)
        return self.dir / f"{safe}-{digest}"

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
            trace = Trace.load(path)
        except MassvizError:
            path.unlink(missing_ok=True)  # a corrupt entry is dropped and recomputed
            return None
        return trace if trace.detect_threshold <= threshold else None

    def save(self, trace: Trace, recording: Recording, detector_info: dict) -> Path:
        entry = self.entry(recording, detector_info, trace.stride)
        return trace.save(entry / f"t{float(trace.detect_threshold)!r}.npz")  # exact: t0.4.npz, t0.40005.npz
