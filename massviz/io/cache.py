"""On-disk cache of traces, so another K, a higher threshold or another model never re-runs the detector.

Entries are keyed by the recording's content fingerprint (a BLAKE2b digest of the bytes of every RGB and depth file,
``Recording.fingerprint``; each file's digest is remembered in ``hashes/`` by its path, size, mtime, ctime and inode,
so only new or changed files are read again; a run that found no entry keys its trace by the digests of the bytes it
read, ``watch``/``save(known=)``, so a cold cache reads each frame file once), the detector's name and settings
(except its threshold; a replay source or detector weights by their content too) and the stride. Inside an entry
one file per detection threshold: detections made at threshold t serve every threshold >= t, so a lookup takes the
entry with the largest t <= the threshold asked for.

An entry that cannot be decoded (truncated, garbage, not a file) is dropped and recomputed, never fatal; a cache
that cannot be written is found before any work (``check_writable``).

Location: ``--cache PATH``, else env ``MASSVIZ_CACHE_DIR``, else the user cache directory (platformdirs).
"""
from __future__ import annotations

import contextlib
import functools
import glob
import hashlib
import json
import logging
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from massviz.core.selection import Selection, serves
from massviz.core.trace import Trace
from massviz.core.types import Detections, RecordingInfo
from massviz.errors import MassvizError
from massviz.io.filehash import FileHasher
from massviz.io.recording import Recording
from massviz.io.trace_file import load_trace, save_trace
from massviz.io.untrusted import safe_filename

_LOG = logging.getLogger(__name__)


def default_cache_dir() -> Path:
    env = os.environ.get("MASSVIZ_CACHE_DIR")
    if env:
        return Path(env)
    import platformdirs  # only for the default folder: a CUDA image without it runs with --cache or --no-cache

    return Path(platformdirs.user_cache_dir("massviz"))


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

    def entry(self, recording: Recording, detector_info: dict, stride: int, known: dict | None = None) -> Path | None:
        """The entry folder of this recording's content, detector settings and stride. ``known``: the digests of
        the bytes a run read (:meth:`watch`): the entry of the content that run processed; None when a file
        changed while the run read it."""
        fingerprint = recording.fingerprint(self.hasher, known=known)
        if fingerprint is None:
            return None
        key = json.dumps({"recording": fingerprint, "detector": detector_info,
                          "stride": stride}, sort_keys=True, default=str)
        digest = hashlib.sha1(key.encode()).hexdigest()[:16]
        return self.dir / f"{safe_filename(recording.id, 60)}-{digest}"

    def _may_hold(self, recording: Recording) -> bool:
        """False when no entry of this recording's id exists (``<id>-<16 hex>``): then every lookup misses, whatever
        the recording's content key, which is not computed (reading every frame file to hash it) to find that."""
        pattern = glob.escape(safe_filename(recording.id, 60)) + "-" + "[0-9a-f]" * 16
        return any(True for _ in self.dir.glob(pattern))

    def watch(self, recording: Recording):
        """``with cache.watch(recording) as read:`` around a run of ``recording`` whose trace is not cached: the
        digests of the frame files the run reads, filled as it reads them (``watch_digests``, where the format has
        it; else None), to pass to ``save(known=read)``: the trace is keyed by the bytes it was computed from,
        without reading each frame file again. Files the run does not read (a video, a RealSense file, frames
        skipped by the stride) are hashed by ``save``."""
        watch = getattr(recording, "watch_digests", None)
        return watch() if watch is not None else contextlib.nullcontext()

    def lookup(self, recording: Recording, detector_info: dict, stride: int, threshold: float) -> Path | None:
        """Path of the cached trace made at the largest threshold <= ``threshold``, or None (at once, without the
        content key, when no entry of the recording's id exists)."""
        if not self._may_hold(recording):
            return None
        entry = self.entry(recording, detector_info, stride)
        best = None
        for p in entry.glob("t*.npz") if entry.is_dir() else []:
            try:
                t = float(p.stem[1:])
            except ValueError:
                continue
            if serves(t, threshold) and (best is None or t > best[0]):
                best = (t, p)
        return best[1] if best else None

    def load(self, recording: Recording, detector_info: dict, stride: int, threshold: float) -> Trace | None:
        path = self.lookup(recording, detector_info, stride, threshold)
        if path is None:
            return None
        try:
            trace = load_trace(path)
        except Exception as err:  # noqa: BLE001 - whatever is wrong with an entry, it is dropped and recomputed
            from massviz.io.untrusted import printable

            reason = (str(err).splitlines() or [type(err).__name__])[0][:200]
            _LOG.warning("massviz: warning: %s: damaged trace cache entry (%s); recomputed", path, printable(reason))
            _drop(path)
            return None
        if not index_path(path).is_file():  # an entry written before the index: index it now (cheap)
            try:
                save_index(trace, path)
            except (OSError, MassvizError):
                pass
        return trace if serves(trace.detect_threshold, threshold) else None

    def load_index(self, recording, detector_info: dict, stride: int, threshold: float) -> "TraceIndex | None":
        """The selection index of the cached trace ``load`` would return (see :class:`TraceIndex`), or None when
        the entry is missing; an entry without a usable index (written before indexes, stale, corrupt) is indexed
        from its full trace once. Reads no frame and decodes no patch or mask."""
        path = self.lookup(recording, detector_info, stride, threshold)
        if path is None:
            return None
        index = load_index(path)
        if index is None:  # none, stale (its trace file was replaced or copied) or unreadable: index it again
            trace = self.load(recording, detector_info, stride, threshold)
            if trace is None:
                return None
            try:
                save_index(trace, path)
            except (OSError, MassvizError):
                return None
            index = load_index(path)
        return index if index is not None and serves(index.detect_threshold, threshold) else None

    def save(self, trace: Trace, recording: Recording, detector_info: dict, known: dict | None = None) -> Path | None:
        """Write the trace's entry (``known``: see :meth:`watch`); a file system refusal at this point (the folder
        was checked writable before the work) is a warning, not a failure: the result stands, it is only not
        cached. So is a frame file that changed while the run read it (no content key)."""
        entry = self.entry(recording, detector_info, trace.stride, known)
        if entry is None:
            _LOG.warning("massviz: warning: %s: a frame file changed while it was read; the result is not cached",
                         recording.path)
            return None
        path = entry / f"t{float(trace.detect_threshold)!r}.npz"  # exact: t0.4.npz, t0.40005.npz
        try:
            if path.is_dir():
                _drop(path)
            saved = save_trace(trace, path)
            save_index(trace, saved)
            return saved
        except (OSError, MassvizError) as err:
            what = getattr(err, "strerror", None) or str(err)
            _LOG.warning("massviz: warning: %s: cannot write the trace cache entry (%s); the result is not cached",
                         path, what)
            return None


# -- the selection index ---------------------------------------------------------------------------------------------
#: version of the index files (``i<threshold>.idx`` beside ``t<threshold>.npz``)
INDEX_FORMAT = 2


@functools.lru_cache(maxsize=1)
def _index_dtype() -> np.dtype:
    """One record per detection: every ``Detections`` array (masks and patches apart), in its own dtype."""
    probe = Detections(frame=[0], xyxy=[[0, 0, 1, 1]], score=[0.5], class_id=[0])
    return np.dtype([(name, getattr(probe, name).dtype, getattr(probe, name).shape[1:])
                     for name in Detections._ARRAYS])


@dataclass
class TraceIndex:
    """What re-selection, sweeps, scores and the flags need of a cached trace, without its masks and patches: the
    recording's info, the detector's threshold, the stride, the model's id, the processed frames and every detection's
    columns (``Detections`` with ``masks``/``patches`` None: frame, class, score, box, d, a, b, prediction, track and
    the ground-truth overlaps). A few kilobytes per recording. What the selection stage alone reads
    (``massviz.evaluation.tuning.SelectionSource``: ``detections``, ``detect_threshold``) and a sweep's scores read
    (``recording``, ``excluded``, ``ground_truth``); it is no ``Trace``: ``full_trace`` reads the full trace (patches,
    masks, flags) for the view that needs it."""

    recording: RecordingInfo
    detector: dict
    detect_threshold: float
    stride: int
    weights_id: str
    frames: np.ndarray
    detections: Detections
    trace_path: Path
    excluded: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    @property
    def ground_truth(self):
        return self.recording.ground_truth

    def full_trace(self) -> Trace:
        """The full trace (patches, masks), read now, with this index's recording info (today's, as
        ``massviz.app.process`` gives a cached trace) and the ground-truth overlaps of that recording."""
        import dataclasses

        from massviz.core.trace import analyse_trace
        from massviz.io.ground_truth import with_ground_truth

        return analyse_trace(with_ground_truth(dataclasses.replace(load_trace(self.trace_path),
                                                                   recording=self.recording)))


def index_path(trace_path: Path) -> Path:
    """``.../t0.4.npz`` -> ``.../i0.4.idx`` (an .npz inside; not named .npz, so that every ``*.npz`` of the cache
    is a trace, as ``lookup`` and anyone counting traces expect)."""
    return trace_path.with_name("i" + trace_path.name[1:].removesuffix(".npz") + ".idx")


def _trace_identity(trace_path: Path) -> list[int]:
    from massviz.io.filehash import identity

    return identity(os.stat(trace_path))[:4]


def save_index(trace: Trace, trace_path: Path) -> Path:
    """Write the selection index of ``trace`` (saved at ``trace_path``) beside it, atomically; it names the trace
    file's identity (size, mtime, ctime, inode), so an index whose trace was replaced is not used."""
    from massviz.io.atomic import atomic_path

    dets = trace.detections
    header = {"format": INDEX_FORMAT, "recording": trace.recording.to_dict(), "detector": trace.detector,
              "detect_threshold": float(trace.detect_threshold), "stride": int(trace.stride),
              "weights_id": trace.weights_id, "trace": _trace_identity(trace_path)}
    columns = np.zeros(len(dets), dtype=_index_dtype())
    for name in Detections._ARRAYS:
        columns[name] = getattr(dets, name)
    # two members (header, one structured array of every column): a file is read with two .npy headers parsed
    arrays = {"header": np.frombuffer(json.dumps(header, default=str).encode(), dtype=np.uint8),
              "frames": np.asarray(trace.frames, dtype=np.int64), "columns": columns}
    out = index_path(trace_path)
    with atomic_path(out) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)  # uncompressed: a few kB, read fastest
    return out


def load_index(trace_path: Path) -> TraceIndex | None:
    """The index beside ``trace_path``; None when missing, unreadable, inconsistent or not of this trace file."""
    from massviz.io.untrusted import load_npz_checked

    path = index_path(trace_path)
    try:
        data = load_npz_checked(path, max_bytes=64 << 20)
        header = json.loads(data["header"].tobytes().decode())
        if not isinstance(header, dict) or header.get("format") != INDEX_FORMAT:
            return None
        if header.get("trace") != _trace_identity(trace_path):
            return None  # the trace was rewritten since (another model's predictions ...): index it again
        columns = data["columns"]
        if columns.dtype != _index_dtype() or columns.ndim != 1:
            return None
        n = len(columns)
        dets = Detections(**{name: columns[name] for name in Detections._ARRAYS})
        if n and (np.isinf(dets.d).any() or np.isnan(dets.score).any() or (dets.frame < 0).any()
                  or (dets.score < 0).any() or (dets.score > 1).any()):
            return None
        # checked as every cut and stride are (Selection.check): a ValueError is an unusable index
        threshold = Selection.check("threshold", header["detect_threshold"], "detect_threshold")
        stride = Selection.check("stride", header["stride"])
        return TraceIndex(recording=RecordingInfo.from_dict(header["recording"]), detector=dict(header["detector"]),
                          detect_threshold=threshold, stride=stride, weights_id=str(header["weights_id"]),
                          frames=np.asarray(data["frames"], dtype=np.int64), detections=dets,
                          trace_path=Path(trace_path))
    except Exception:  # noqa: BLE001 - missing, truncated, garbage: the full trace is read instead
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
