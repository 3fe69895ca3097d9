"""What the recording formats share: the fields and identity of a recording (``RecordingBase``), frame-file bytes
(read once, header checked, decoded from memory), the video probe with the partial-video rule, JSON and intrinsics
loading. One copy of each; the formats (``folder``, ``ccm``, ``realsense_file``) build on it."""
from __future__ import annotations

import hashlib
import logging
import math
import os
from collections import OrderedDict
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from massviz.core.types import Frame, Intrinsics, RecordingInfo
from massviz.errors import RecordingError
from massviz.io.untrusted import MAX_IMAGE_PIXELS, MAX_IMAGE_SIDE, MAX_INDEX, decode_image, number
from massviz.io.untrusted import load_json as untrusted_json

_LOG = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


@dataclass
class RecordingBase:
    """The fields every format fills and what follows from them (identity, content key, trace info). A format adds
    its own fields and implements ``frames``, ``read_depth``, ``input_files``, ``video_file`` and
    ``source_description`` (``massviz.core.recording_protocol.Recording``)."""

    path: Path
    kind: str
    id: str
    width: int
    height: int
    num_frames: int
    fps: float
    intrinsics: Intrinsics | None = None
    meta: dict = field(default_factory=dict)
    #: warnings about the data (e.g. a partial video), one line each; the pipeline adds them to the trace's events.
    notes: list = field(default_factory=list)

    @property
    def config_id(self) -> str:
        """The id written in the challenge CSV's 'Configuration ID' column."""
        return str(self.meta.get("config_id", self.id))

    def input_files(self) -> list[Path]:  # pragma: no cover - every format overrides it
        raise NotImplementedError

    def video_file(self) -> Path | None:
        return None

    def fingerprint(self, hasher=None, read: bool = True, known: dict | None = None) -> str | None:
        """The content key of the recording's frames: a digest of each input file's *bytes* (BLAKE2b), so any edit
        changes it, even one that keeps the size and sets the modification time back. ``hasher``
        (``massviz.io.filehash.FileHasher``, the trace cache's) remembers each file's digest by (path, size, mtime,
        ctime, inode), so a dataset is hashed once, not on every run. ``known``: the digests of the bytes a run
        read (``watch_digests``), which the key is then of (each file read once). ``read`` False: None when a file
        would have to be read to know the key; also None when a file changed while the run read it."""
        from massviz.io.filehash import FileHasher

        hasher = hasher or FileHasher()
        files = self.input_files()
        digests = hasher.digests(files, group=str(Path(self.path).resolve()), known=known, read=read)
        if digests is None:
            return None
        root = self.path.parent if self.path.is_file() else self.path
        h = hashlib.blake2b(digest_size=16)
        h.update(f"{self.kind}|{self.num_frames}\n".encode())
        for p, digest in zip(files, digests):
            try:
                name = str(p.relative_to(root))
            except ValueError:
                name = p.name
            h.update(f"{name}|{digest}\n".encode())
        return h.hexdigest()

    @contextmanager
    def watch_digests(self):
        """``with rec.watch_digests() as digests:`` a dict that, inside the block, gets the content digest of each
        frame file this recording reads, from the bytes read (``read_bytes(digests=)``), for
        ``fingerprint(known=)``: the trace cache keys a run it did not find by the bytes the run read, instead of
        reading every file once more to hash it."""
        self.__dict__["_digests"] = digests = {}
        try:
            yield digests
        finally:
            self.__dict__.pop("_digests", None)

    def _watched(self) -> dict | None:
        """The dict ``read_bytes`` fills after ``watch_digests``, else None."""
        return self.__dict__.get("_digests")

    def info(self) -> RecordingInfo:
        """What a trace keeps of this recording."""
        video = self.video_file()
        return RecordingInfo(id=self.id, config_id=self.config_id, path=str(self.path), kind=self.kind,
                             width=self.width, height=self.height, num_frames=self.num_frames, fps=self.fps,
                             rgb=str(video) if video else "frames", intrinsics=self.intrinsics, meta=self.meta)

    def frames(self, stride: int = 1, indices=None) -> Iterator[Frame]:  # pragma: no cover - formats override it
        raise NotImplementedError

    def read_frame(self, index: int) -> Frame:
        """One frame by index (through ``frames``: a video or a RealSense file is decoded up to it)."""
        for frame in self.frames(indices=[index]):
            return frame
        raise RecordingError(f"frame {index} is past the end ({self.num_frames} frames)", self.path)


def wanted_frames(num_frames: int, stride: int, indices) -> tuple:
    """(keep(i), last index to read) for ``frames(stride, indices)``; ``stride`` < 1 is a ValueError."""
    if stride < 1:
        raise ValueError("stride must be >= 1")
    if indices is None:
        return (lambda i: i % stride == 0), num_frames - 1
    wanted = {int(i) for i in indices}
    return wanted.__contains__, (max(wanted) if wanted else -1)


def partial_message(decoded: int, declared: int) -> str:
    return (f"video is cut short: only {decoded} of the {declared} frames its header declares decode "
            "(a partial download or copy?)")


# ------------------------------------------------------------------------------------------------ frame files
def media_type(path: Path) -> str:
    return "image/png" if Path(path).suffix.lower() == ".png" else "image/jpeg"


#: largest frame file read (a 1280x720 16-bit depth PNG is ~1 MB; this bounds a sparse or hostile file).
MAX_FRAME_FILE_BYTES = 256 << 20


#: frame files read when a recording was opened (its first frame, checked up front), kept until the frame loop reads
#: them, so that each frame file is opened once; bounded (a dataset opens every recording before the work starts:
#: the first frames of the last few opened are kept, the others are read again). path -> (identity, bytes).
_KEPT: "OrderedDict[str, tuple[list[int], bytes]]" = OrderedDict()
_KEEP_AT_MOST = 4


def _kept(path: Path) -> tuple[bytes, list[int]] | None:
    """The kept bytes of ``path`` and its identity, when the file is unchanged since they were read."""
    from massviz.io.filehash import identity

    entry = _KEPT.pop(str(path), None)
    if entry is None:
        return None
    try:
        ident = identity(os.stat(path))
    except OSError:
        return None
    return (entry[1], ident) if ident == entry[0] else None


def read_bytes(path: Path, what: str, *, keep: bool = False, digests: dict | None = None) -> bytes:
    """A frame file's bytes, read once (checked and decoded from memory by ``massviz.io.untrusted.decode_image``, and
    kept for sinks that log them as they are), with ``massviz.io.untrusted.read_bounded`` (the size checked before reading: a sparse 2 TiB file is
    refused at once). ``keep``: the file is read to check a recording when it is opened; its bytes are kept
    (bounded) for the frame loop's read. ``digests``: a dict that gets ``{absolute path: (identity, BLAKE2b
    digest of the bytes read)}`` (``massviz.io.filehash``), so that the trace cache's content key needs no second
    read of the file; ``{absolute path: None}`` when the file changed while it was read (a mix of two versions)."""
    from massviz.io.filehash import bytes_digest, identity
    from massviz.io.untrusted import read_bounded

    kept = _kept(path)
    if kept is not None:
        data, ident = kept
    else:
        data, before, after = read_bounded(path, MAX_FRAME_FILE_BYTES, what, RecordingError, with_stats=True)
        ident = identity(after) if identity(before) == identity(after) else None  # None: changed while read
        if keep and ident is not None:
            _KEPT[str(path)] = (ident, data)
            while len(_KEPT) > _KEEP_AT_MOST:
                _KEPT.popitem(last=False)
    if digests is not None:  # None: changed while read, the bytes have no key
        digests[os.path.abspath(path)] = (ident, bytes_digest(data)) if ident is not None else None
    return data


def _decode(path: Path, data: bytes, what: str, flags: int, formats: tuple[str, ...], size):
    """The frame decoded by the one image reader: PNG/JPEG by content, the header's size (the recording's ``size``
    when known) checked before decoding."""
    return decode_image(path, what, flags=flags, formats=formats, error=RecordingError, data=data, expected=size)


def read_rgb(path: Path, width: int | None = None, height: int | None = None, *, with_bytes: bool = False,
             keep: bool = False, digests: dict | None = None):
    """RGB of one frame file (H×W×3 uint8); ``with_bytes``: (rgb, the file's bytes), the file read once.

    EXIF orientation is ignored (``cv2.IMREAD_IGNORE_ORIENTATION``): a frame is used as its pixels are stored, so
    it stays aligned with its depth map. ``keep``, ``digests``: see ``read_bytes``."""
    data = read_bytes(path, "RGB image", keep=keep, digests=digests)
    bgr = _decode(path, data, "RGB image", cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION, ("PNG", "JPEG"),
                  None if width is None else (width, height))
    if bgr is None:
        raise RecordingError("cannot read image (missing, empty or not an image)", path)
    if width is not None and (bgr.shape[1], bgr.shape[0]) != (width, height):
        raise RecordingError(f"frame is {bgr.shape[1]}x{bgr.shape[0]} but the recording is {width}x{height}", path)
    rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    return (rgb, data) if with_bytes else rgb


def read_depth_png(path: Path, width: int, height: int, *, with_bytes: bool = False, keep: bool = False,
                   digests: dict | None = None):
    """Depth of one 16-bit PNG (H×W uint16 mm), checked; ``with_bytes``: (depth, the file's bytes), read once.
    ``keep``, ``digests``: see ``read_bytes``."""
    data = read_bytes(path, "depth image", keep=keep, digests=digests)
    depth = _decode(path, data, "depth image", cv2.IMREAD_UNCHANGED | cv2.IMREAD_IGNORE_ORIENTATION, ("PNG",),
                    (width, height))
    if depth is None:
        raise RecordingError("cannot read depth image (missing, empty or not a PNG)", path)
    if depth.ndim != 2:
        raise RecordingError(f"depth must be a single-channel 16-bit PNG (mm); this one has {depth.shape[2]} "
                             "channels", path)
    if depth.dtype != np.uint16:
        bits = depth.dtype.itemsize * 8
        raise RecordingError(f"depth must be a 16-bit PNG in millimetres; this one is {bits}-bit", path)
    if (depth.shape[1], depth.shape[0]) != (width, height):
        raise RecordingError(f"depth is {depth.shape[1]}x{depth.shape[0]} but the RGB frames are {width}x{height}",
                             path)
    return (depth, data) if with_bytes else depth


#: most frame files in one folder (a folder of 100,000 tiny frames is listed and checked in bounded time; a
#: recording this long is an hour at 30 fps).
MAX_FRAME_FILES = 200_000


def frame_files(folder: Path, suffixes=IMAGE_SUFFIXES, what: str = "frames") -> list[Path]:
    """The frame files of ``folder`` (by suffix), sorted by name, checked: every entry is a regular file (a
    directory or a dangling symlink among the frames is an error naming it) of at most ``MAX_FRAME_FILE_BYTES``
    (a sparse 2 TiB file is refused from its size, before the cache would hash it), and numbered names (``NNNNNN.png``)
    step evenly (a gap in the numbering is an error naming the frame after it, not a silently shorter or shifted
    recording). Lists the folder once (``os.scandir``)."""

    entries = []
    try:
        with os.scandir(folder) as it:
            for n, e in enumerate(it):
                if n > MAX_FRAME_FILES:
                    raise RecordingError(f"more than {MAX_FRAME_FILES} entries; not a recording's {what} folder",
                                         folder)
                if Path(e.name).suffix.lower() in suffixes:
                    entries.append(e)
    except OSError as err:
        raise RecordingError(f"cannot list {what} ({err.strerror or err})", folder) from None
    entries.sort(key=lambda e: e.name)
    for e in entries:
        try:
            regular = e.is_file()  # follows symlinks: False for a dangling link or a directory
            size = e.stat().st_size if regular else 0
        except OSError:
            regular, size = False, 0
        if not regular:
            kind = ("a dangling symlink" if e.is_symlink() and not os.path.exists(e.path)
                    else "a directory" if e.is_dir() else "not a regular file")
            raise RecordingError(f"{kind} among the {what}: every frame must be a file", Path(e.path))
        if size > MAX_FRAME_FILE_BYTES:  # before anything reads or hashes it (the cache's content key would)
            raise RecordingError(f"frame file is {size} bytes (at most {MAX_FRAME_FILE_BYTES}); not read",
                                 Path(e.path))
    files = [Path(e.path) for e in entries]
    _check_numbering(files, what)
    return files


def _check_numbering(files: list[Path], what: str) -> None:
    """Numbered frame names (all stems digits) must step evenly: 0,1,2,... or 1,11,21,... (a subsampled export)."""
    if len(files) < 3 or not all(p.stem.isdigit() for p in files):
        return
    numbers = [int(p.stem) for p in files]
    step = numbers[1] - numbers[0]
    for prev, cur, p in zip(numbers[1:], numbers[2:], files[2:]):
        if cur - prev != step:
            raise RecordingError(f"gap in the {what}' numbering: {p.name} follows frame {prev} (step {step}); a "
                                 "frame is missing", p)


# ---------------------------------------------------------------------------------------------------- videos
def probe_video(path: Path) -> tuple[int, int, int, float, int]:
    """(width, height, decodable frames, fps, frames the header declares) of a video, checking that its first frame
    decodes and, cheaply, that its last declared frame does (a seek); only when that fails are the frames counted
    by decoding them, so a good file costs two frame decodes. The frame size is checked from the container's
    header before the first frame is decoded (a video declaring a huge size is refused before any allocation)."""
    if path.stat().st_size == 0:
        raise RecordingError("cannot decode video: the file is empty", path)
    cap = cv2.VideoCapture(str(path))
    try:
        if not cap.isOpened():
            raise RecordingError("cannot decode video (not a readable video file)", path)
        w, h = cap.get(cv2.CAP_PROP_FRAME_WIDTH), cap.get(cv2.CAP_PROP_FRAME_HEIGHT)
        if not (math.isfinite(w) and math.isfinite(h)) or w > MAX_IMAGE_SIDE or h > MAX_IMAGE_SIDE \
                or w * h > MAX_IMAGE_PIXELS:
            raise RecordingError(f"video declares {w:g}x{h:g} frames (at most {MAX_IMAGE_SIDE} per side and "
                                 f"{MAX_IMAGE_PIXELS} pixels); not decoded", path)
        ok, bgr = cap.read()
        if not ok or bgr is None:
            raise RecordingError("cannot decode video (not a readable video file)", path)
        height, width = bgr.shape[:2]
        if width > MAX_IMAGE_SIDE or height > MAX_IMAGE_SIDE:
            raise RecordingError(f"video frames are {width}x{height} (at most {MAX_IMAGE_SIDE} per side)", path)
        count = cap.get(cv2.CAP_PROP_FRAME_COUNT)
        declared = int(count) if math.isfinite(count) and 0 < count <= MAX_INDEX else 0
        fps = float(cap.get(cv2.CAP_PROP_FPS))
        fps = fps if math.isfinite(fps) and 0 < fps <= 1000 else 30.0
        if declared > 1:
            cap.set(cv2.CAP_PROP_POS_FRAMES, declared - 1)
            if cap.grab():
                return width, height, declared, fps, declared
    finally:
        cap.release()
    decoded = _count_frames(path, declared or MAX_INDEX)
    return width, height, decoded, fps, declared or decoded


def _count_frames(path: Path, limit: int) -> int:
    cap = cv2.VideoCapture(str(path))
    try:
        n = 0
        while n < limit and cap.grab():
            n += 1
        return n
    finally:
        cap.release()


def video_frames(path: Path, allow_partial: bool) -> tuple[int, int, int, float, int | None, list[str]]:
    """``probe_video`` with the partial-video rule applied: (width, height, frames, fps, declared or None, notes)."""
    width, height, decoded, fps, declared = probe_video(path)
    if decoded >= declared:
        return width, height, decoded, fps, None, []
    if not allow_partial:
        raise RecordingError(f"{partial_message(decoded, declared)}; pass --allow-partial to process the "
                             f"{decoded} that decode", path)
    note = f"{path}: {partial_message(decoded, declared)}; processed the {decoded} that decode"
    warn_once(note)
    return width, height, decoded, fps, declared, [note]


_WARNED: set[str] = set()


def warn_once(note: str) -> None:
    """One warning (a WARNING record of the ``massviz`` logger: a line on stderr from the command line) per note and
    process (the user is told once)."""
    if note not in _WARNED:
        _WARNED.add(note)
        _LOG.warning("massviz: warning: %s", note)


# ------------------------------------------------------------------------------------------------------- JSON
#: largest meta.json / intrinsics.json read (the samples' are a few KB).
MAX_JSON_BYTES = 16 << 20


def load_json(path: Path) -> dict:
    """A JSON object from ``path`` (bounded size, depth and integer digits: ``massviz.io.untrusted.load_json``, the
    one loader of untrusted JSON), or one ``RecordingError`` naming it."""
    data = untrusted_json(path, path.name, RecordingError, MAX_JSON_BYTES)
    if not isinstance(data, dict):
        raise RecordingError("expected a JSON object", path)
    return data


def check_intrinsics(values: dict, path: Path, width: int | None = None, height: int | None = None) -> Intrinsics:
    """``Intrinsics`` from {fx, fy, cx, cy[, width, height]}, every value checked: fx, fy finite and > 0, width and
    height integers in [1, MAX_IMAGE_SIDE], cx in [0, width], cy in [0, height]. ``RecordingError`` naming ``path``."""
    def num(key, **kw):
        if key not in values:
            raise RecordingError(f"intrinsics need fx, fy, cx, cy, width, height; '{key}' is missing", path)
        return number(values[key], key, path, error=RecordingError, **kw)

    w = width if width is not None else num("width", lo=1, hi=MAX_IMAGE_SIDE, integral=True)
    h = height if height is not None else num("height", lo=1, hi=MAX_IMAGE_SIDE, integral=True)
    return Intrinsics(num("fx", lo=0, lo_open=True), num("fy", lo=0, lo_open=True), num("cx", lo=0, hi=w),
                      num("cy", lo=0, hi=h), w, h)
