"""Recognising a recording already seen, from file listings and ``stat`` alone: no frame decoded, no video probed.

Opening a recording (``open_recording``) checks it: the video is opened and decoded at both ends, the first depth
PNG read, calibration and meta.json parsed (~150 ms for a CCM recording). A recording whose files have not changed
since it was last opened does not need that again to find its trace in the cache: what opening it found (its info,
frame count, notes) and its content fingerprint (``Recording.fingerprint``) are remembered in the trace cache,
under ``located/<sha1(path)>.json``, with the identity (size, mtime, ctime, inode, device:
``massviz.io.filehash.identity``) of every file it depends on and of every folder it lists or lives in:

* the files: its input files (``Recording.input_files``: video or images, depth images) and every file Python
  opened while the recording was opened (meta.json, intrinsics.json, the CCM calibration pickle ...), recorded with
  an audit hook (``sys.addaudithook`` 'open' events) so that no format's reader has to say what it reads;
* the folders: those it listed ('os.listdir'/'os.scandir' events) and the folder of each file above, whose mtime
  changes when a file is added, removed or renamed in it (a new depth frame, a meta.json that appears).

``locate(path)`` stats them all and gives back a :class:`LocatedRecording` only when every identity is unchanged
(any difference, a missing file, an unreadable memo: None, and the caller opens the recording as before).
A user can set a file's mtime back but not its ctime, which every write changes; the fingerprint is still the
files' bytes, hashed once (``massviz.io.filehash``). A command about to process the recording opens it with
``open_remembered(defer=True)``: on a cold cache the fingerprint is then not computed by reading every frame
file up front; :func:`settle` writes the memo after the run, from the digests of the bytes the run read.

The same is done for what a pipeline's options resolve to (the detector's cache settings and the mass CNN's
``weights_id``): ``remember_pipeline`` / ``remembered_pipeline``, keyed by the options and checked against the
identity of every file opened while the pipeline was built (weights, replay source ...), so that a warm command can
find its cached traces without importing torch or loading any weights.
"""
from __future__ import annotations

import hashlib
import json
import os
import sys
import threading
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from massviz.core.types import RecordingInfo
from massviz.io.filehash import identity, read_memo, write_memo

LOCATE_FORMAT = 1
#: files under these are code, not data (module imports while a pipeline is built)
_CODE_SUFFIXES = (".py", ".pyc", ".so", ".pth", ".pyd")

_capture = threading.local()
_hook_installed = False
_hook_lock = threading.Lock()


def _audit(event: str, args) -> None:
    sink = getattr(_capture, "sink", None)
    if sink is None:
        return
    if event == "open":
        path = args[0]
        if isinstance(path, (str, bytes, os.PathLike)) and not isinstance(path, int):
            mode = args[1] if len(args) > 1 else "r"
            if mode is None or "r" in str(mode) or mode == "rb":
                sink["files"].add(os.fsdecode(path))
    elif event in ("os.listdir", "os.scandir"):
        path = args[0] if args else "."
        if isinstance(path, (str, bytes, os.PathLike)) and not isinstance(path, int):
            sink["dirs"].add(os.fsdecode(path) if path is not None else ".")


@contextmanager
def capture_reads():
    """Collect the files Python opens for reading and the folders it lists in this thread, inside the block:
    ``{"files": set, "dirs": set}`` (absolute paths)."""
    global _hook_installed
    with _hook_lock:
        if not _hook_installed:
            sys.addaudithook(_audit)  # an audit hook cannot be removed: it does nothing outside capture_reads
            _hook_installed = True
    outer = getattr(_capture, "sink", None)
    sink = {"files": set(), "dirs": set()}
    _capture.sink = sink
    try:
        yield sink
    finally:
        _capture.sink = outer
        if outer is not None:
            outer["files"] |= sink["files"]
            outer["dirs"] |= sink["dirs"]


def _is_data(path: str, exclude: tuple[str, ...]) -> bool:
    if path.endswith(_CODE_SUFFIXES) or path.startswith(("/proc/", "/sys/", "/dev/")):
        return False
    return not any(path == e or path.startswith(e + os.sep) for e in exclude)


def _code_roots() -> tuple[str, ...]:
    import massviz

    roots = {sys.prefix, sys.base_prefix, sys.exec_prefix, str(Path(massviz.__file__).resolve().parent)}
    return tuple(os.path.abspath(r) for r in roots if r)


def _identities(files, dirs) -> dict | None:
    """{"files": {path: identity}, "dirs": {path: identity}}; None when one is missing (nothing to remember)."""
    try:
        return {"files": {p: identity(os.stat(p)) for p in sorted(files)},
                "dirs": {p: identity(os.stat(p))[1:] for p in sorted(dirs)}}  # a folder's size varies by fs
    except OSError:
        return None


def _unchanged(recorded: dict) -> bool:
    try:
        files, dirs = recorded["files"], recorded["dirs"]
        if not isinstance(files, dict) or not isinstance(dirs, dict):
            return False
        if changed_inputs(files):
            return False
        for p, ident in dirs.items():
            if identity(os.stat(p))[1:] != ident:
                return False
    except (OSError, TypeError, KeyError, ValueError):
        return False
    return True


# -- a run's inputs ---------------------------------------------------------------------------------------------------
def input_identities(recording) -> dict[str, list[int] | None]:
    """{path: identity} of every file ``recording``'s frames are read from (``input_files``; None for one that
    cannot be stat'ed): taken before a run, compared after it by :func:`changed_inputs`."""
    out = {}
    for p in getattr(recording, "input_files", lambda: [])():
        try:
            out[str(p)] = identity(os.stat(p))
        except OSError:
            out[str(p)] = None
    return out


def changed_inputs(before: dict[str, list[int] | None]) -> list[str]:
    """The files of ``before`` (``input_identities``) whose identity (size, times, inode) is not the same now:
    edited, replaced or removed while a run read them."""
    changed = []
    for p, ident in before.items():
        try:
            now = identity(os.stat(p))
        except OSError:
            now = None
        if now != ident:
            changed.append(p)
    return changed


# -- recordings ------------------------------------------------------------------------------------------------------
@dataclass
class LocatedRecording:
    """A recording recognised by :func:`locate`: what ``open_recording`` found last time, without its frames. It
    answers what the trace cache and a command's rows ask of a ``Recording`` (``id``, ``path``, ``config_id``,
    ``kind``, ``num_frames``, ``info()``, ``fingerprint()``, ``notes``); reading frames needs ``open_recording``."""

    path: Path
    id: str
    kind: str
    config_id: str
    num_frames: int
    recording_info: RecordingInfo
    _fingerprint: str
    notes: list = field(default_factory=list)
    meta: dict = field(default_factory=dict)

    def info(self) -> RecordingInfo:
        return self.recording_info

    def fingerprint(self, hasher=None, read: bool = True, known: dict | None = None) -> str:
        return self._fingerprint

    @property
    def intrinsics(self):
        return self.recording_info.intrinsics


def _memo_path(cache_root: Path, path: str | Path, allow_partial: bool) -> Path:
    key = f"{Path(path).resolve()}|{bool(allow_partial)}"
    return Path(cache_root) / "located" / f"{hashlib.sha1(key.encode()).hexdigest()[:24]}.json"


def locate(path: str | Path, cache_root: str | Path, allow_partial: bool = False) -> LocatedRecording | None:
    """The recording at ``path`` as last opened, when none of its files and folders changed since; else None."""
    memo = read_memo(_memo_path(cache_root, path, allow_partial))
    if memo.get("format") != LOCATE_FORMAT or memo.get("path") != str(Path(path).resolve()):
        return None
    if not _unchanged(memo.get("depends", {})):
        return None
    try:
        info = RecordingInfo.from_dict(memo["info"])
        return LocatedRecording(path=Path(memo["recording_path"]), id=str(memo["id"]), kind=str(memo["kind"]),
                                config_id=str(memo["config_id"]), num_frames=int(memo["num_frames"]),
                                recording_info=info, _fingerprint=str(memo["fingerprint"]),
                                notes=[str(n) for n in memo.get("notes", [])], meta=dict(info.meta or {}))
    except (KeyError, TypeError, ValueError, AttributeError):
        return None


def open_remembered(path: str | Path, cache_root: str | Path | None, *, allow_partial: bool = False, hasher=None,
                    defer: bool = False):
    """``locate(path)`` when the recording is unchanged since it was last opened, else ``open_recording(path)``
    (which checks it) and remember what it found. ``cache_root`` None: always ``open_recording``.

    ``defer``: the recording is about to be processed. When its content fingerprint would need its frame files
    read (their digests are not remembered: a cold cache), it is not computed now; :func:`settle` remembers the
    recording after the run, from the digests of the bytes the run read (each frame file read once)."""
    from massviz.io.recording import open_recording

    if cache_root is None:
        return open_recording(path, allow_partial=allow_partial)
    found = locate(path, cache_root, allow_partial)
    if found is not None:
        return found
    with capture_reads() as reads:
        rec = open_recording(path, allow_partial=allow_partial)
    try:
        remember(path, rec, reads, cache_root, allow_partial, hasher, defer=defer)
    except Exception:  # noqa: BLE001 - remembering is an optimisation; the recording is open and checked
        pass
    return rec


def remember(path, rec, reads: dict, cache_root, allow_partial: bool, hasher=None, *, defer: bool = False) -> None:
    """Write ``located/<key>.json`` for ``rec`` (opened from ``path`` while ``reads`` were captured). ``defer``:
    when the fingerprint needs a file read, keep what was found on ``rec`` for :func:`settle` instead."""
    code = _code_roots() + (os.path.abspath(cache_root),)
    files = {os.path.abspath(p) for p in [*map(str, rec.input_files()), *reads["files"]]}
    files = {p for p in files if _is_data(p, code) and os.path.isfile(p)}
    dirs = {os.path.abspath(d) for d in reads["dirs"]} | {os.path.dirname(p) for p in files}
    root = Path(rec.path)
    dirs.add(str(root.resolve() if root.is_dir() else root.resolve().parent))
    dirs = {d for d in dirs if _is_data(d, code) and os.path.isdir(d)}
    before = _identities(files, dirs)
    if before is None:
        return
    pending = {"path": path, "files": files, "dirs": dirs, "before": before, "cache_root": cache_root,
               "allow_partial": allow_partial}
    if not _remember_now(rec, pending, hasher, read=not defer):
        rec.__dict__["_remember_later"] = pending


def settle(rec, hasher=None) -> None:
    """Remember the recording ``open_remembered(defer=True)`` opened, now that a run has read its frame files
    (their digests are remembered by the trace cache): no frame file is read here; nothing is remembered when
    one is still unknown (the run failed) or when a file or folder changed since the recording was opened."""
    pending = getattr(rec, "__dict__", {}).pop("_remember_later", None)
    if pending is not None:
        try:
            _remember_now(rec, pending, hasher, read=False)
        except Exception:  # noqa: BLE001 - remembering is an optimisation
            pass


def _remember_now(rec, pending: dict, hasher, read: bool) -> bool:
    """Write the memo of ``pending`` (what ``remember`` found); False when the fingerprint is not known without
    reading a file (``read`` False). Nothing is written when a file or folder changed since ``before``."""
    from massviz.io.filehash import FileHasher

    fingerprint = rec.fingerprint(hasher or FileHasher(Path(pending["cache_root"]) / "hashes"), read=read)
    if fingerprint is None:
        return False
    if _identities(pending["files"], pending["dirs"]) != pending["before"]:  # changed since opened: remember nothing
        return True
    path, allow_partial = pending["path"], pending["allow_partial"]
    doc = {"format": LOCATE_FORMAT, "path": str(Path(path).resolve()), "recording_path": str(rec.path),
           "id": rec.id, "kind": rec.kind, "config_id": rec.config_id, "num_frames": int(rec.num_frames),
           "info": rec.info().to_dict(), "fingerprint": fingerprint, "notes": [str(n) for n in rec.notes],
           "depends": pending["before"]}
    write_memo(_memo_path(pending["cache_root"], path, allow_partial), json.loads(json.dumps(doc, default=str)))
    return True


# -- pipelines -------------------------------------------------------------------------------------------------------
def _pipeline_memo(cache_root: Path, key: dict) -> Path:
    digest = hashlib.sha1(json.dumps(key, sort_keys=True, default=str).encode()).hexdigest()[:24]
    return Path(cache_root) / "pipelines" / f"{digest}.json"


def remember_pipeline(cache_root, key: dict, resolved: dict, reads: dict) -> None:
    """Remember that the pipeline options ``key`` resolved to ``resolved`` (JSON: detector name, settings,
    threshold-free cache key, ``weights_id``), valid while every data file in ``reads`` is unchanged."""
    code = _code_roots() + (os.path.abspath(cache_root),)
    files = {os.path.abspath(p) for p in reads["files"]}
    files = {p for p in files if _is_data(p, code) and os.path.isfile(p)}
    depends = _identities(files, set())
    if depends is None:
        return
    doc = {"format": LOCATE_FORMAT, "key": key, "resolved": resolved, "depends": depends}
    write_memo(_pipeline_memo(cache_root, key), json.loads(json.dumps(doc, default=str)))


def remembered_pipeline(cache_root, key: dict) -> dict | None:
    """What ``remember_pipeline`` remembered for ``key``, when none of the files it read changed; else None."""
    memo = read_memo(_pipeline_memo(cache_root, key))
    if memo.get("format") != LOCATE_FORMAT or not isinstance(memo.get("resolved"), dict):
        return None
    if json.loads(json.dumps(key, default=str)) != memo.get("key") or not _unchanged(memo.get("depends", {})):
        return None
    return memo["resolved"]


__all__ = ["capture_reads", "LocatedRecording", "locate", "open_remembered", "remember", "settle", "remember_pipeline",
           "remembered_pipeline"]
