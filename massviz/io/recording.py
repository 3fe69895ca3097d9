"""Reading RGB-D recordings, one frame at a time.

Three kinds of recording are read:

* **CCM** (CORSMAL Containers Manipulation), addressed by the video path::

      ROOT/view{1..4}/rgb/NNNNNN.mp4
      ROOT/view{n}/depth/NNNNNN/*.png        16-bit mm, aligned to RGB, sorted by name
      ROOT/view{n}/calib/NNNNNN.pickle       optional calibration (intrinsics of 'rgb')

* **massviz folders**::

      REC/rgb.mp4  or  REC/rgb/*.png|*.jpg
      REC/depth/*.png                        16-bit mm, aligned to RGB, sorted by name
      REC/intrinsics.json                    optional {"fx","fy","cx","cy","width","height"}
      REC/meta.json                          optional annotations / ground truth

* **RealSense files** ``X.db3`` (ROS2, librealsense >= 2.56) and ``X.bag`` (ROS1), through ``pyrealsense2``
  (optional extra ``massviz[realsense]``): see ``massviz.io.realsense``.

Frames are streamed (``Recording.frames``): nothing is accumulated, so memory does not grow with the recording's
length. Problems are reported as ``RecordingError`` naming the file, checked up front where that is cheap (so a
long run does not fail half-way) and again per frame.

Every file is untrusted (``massviz.io.untrusted``): calibration pickles go through a restricted unpickler, every
number is checked where it is read (finite, in range, integral where it must be), ids are text without control
characters, image sizes are bounded from their headers before anything is decoded, and a path pattern in meta.json
must stay inside the recording.

A video that decodes fewer frames than its header declares (a file cut short) is an error naming both counts, unless
``open_recording(..., allow_partial=True)`` (CLI ``--allow-partial``): then the decoded frames are used and the
shortfall is said on stderr and kept in ``Recording.notes`` (the pipeline puts them in the trace's events, so they
show in Rerun's ``/log``).
"""
from __future__ import annotations

import hashlib
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from massviz.errors import RecordingError
from massviz.io.untrusted import MAX_IMAGE_SIDE, MAX_INDEX, check_image_size, load_calibration_pickle, load_json, number, text_id
from massviz.core.types import Frame, Intrinsics, RecordingInfo
from massviz.io.meta import check_meta

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


@dataclass
class Recording:
    """An RGB-D recording on disk. Create it with ``open_recording``."""

    path: Path
    kind: str  # "ccm", "folder" or "realsense"
    id: str
    depth_files: list[Path]
    width: int
    height: int
    num_frames: int
    fps: float
    rgb_video: Path | None = None
    rgb_files: list[Path] | None = None
    intrinsics: Intrinsics | None = None
    meta: dict = field(default_factory=dict)
    #: frames the video's header declares when fewer decode (``allow_partial``); None when all decode.
    declared_frames: int | None = None
    #: warnings about the data (e.g. a partial video), one line each; the pipeline adds them to the trace's events.
    notes: list = field(default_factory=list)
    allow_partial: bool = False

    # -- identity --------------------------------------------------------------------------------------------------
    @property
    def config_id(self) -> str:
        """The id written in the challenge CSV's 'Configuration ID' column (CCM: the integer recording number)."""
        if self.kind == "ccm" and self.id.isdigit():
            return str(int(self.id))
        return str(self.meta.get("config_id", self.id))

    def input_files(self) -> list[Path]:
        """Every file the frames are read from (RGB video or images, then depth images)."""
        files = [self.rgb_video] if self.rgb_video else list(self.rgb_files or [])
        return [*files, *self.depth_files]

    def fingerprint(self, hasher=None) -> str:
        """The content key of the recording's frames: a digest of each input file's *bytes* (BLAKE2b), so any edit
        changes it, even one that keeps the size and sets the modification time back. ``hasher``
        (``massviz.io.filehash.FileHasher``, the trace cache's) remembers each file's digest by (path, size, mtime,
        ctime, inode), so a dataset is hashed once, not on every run."""
        from massviz.io.filehash import FileHasher

        hasher = hasher or FileHasher()
        files = self.input_files()
        root = self.path.parent if self.path.is_file() else self.path
        h = hashlib.blake2b(digest_size=16)
        h.update(f"{self.kind}|{self.num_frames}\n".encode())
        for p, digest in zip(files, hasher.digests(files, group=str(Path(self.path).resolve()))):
            try:
                name = str(p.relative_to(root))
            except ValueError:
                name = p.name
            h.update(f"{name}|{digest}\n".encode())
        return h.hexdigest()

    def info(self) -> RecordingInfo:
        """What a trace keeps of this recording."""
        return RecordingInfo(id=self.id, config_id=self.config_id, path=str(self.path), kind=self.kind,
                             width=self.width, height=self.height, num_frames=self.num_frames, fps=self.fps,
                             rgb=str(self.rgb_video) if self.rgb_video else "frames", intrinsics=self.intrinsics,
                             meta=self.meta)

    # -- what sinks ask for (instead of testing the attributes above) ----------------------------------------------
    def video_file(self) -> Path | None:
        """The RGB video a viewer can show as one asset (frames referenced by time), or None when the format has no
        such file (frame images, RealSense files, cameras)."""
        return self.rgb_video

    def source_description(self) -> dict[str, str]:
        """Where the frames come from, for people: {"rgb": ..., "depth": ...}."""
        if self.rgb_video is not None:
            rgb = str(self.rgb_video)
        elif self.rgb_files:
            rgb = f"{len(self.rgb_files)} images in `{Path(self.rgb_files[0]).parent}`"
        else:
            rgb = "(not in files)"
        depth = (f"{len(self.depth_files)} PNGs in `{Path(self.depth_files[0]).parent}`" if self.depth_files
                 else "(not in files)")
        return {"rgb": rgb, "depth": depth}

    # -- frames ----------------------------------------------------------------------------------------------------
    def read_depth(self, index: int) -> np.ndarray:
        """Depth of frame ``index`` (H×W uint16, mm), checked."""
        return self._depth_with_bytes(index)[0]

    def _depth_with_bytes(self, index: int) -> tuple[np.ndarray, bytes]:
        if index >= len(self.depth_files):
            raise RecordingError(f"no depth image for frame {index} ({len(self.depth_files)} depth frames)",
                                 self.depth_files[0].parent if self.depth_files else self.path)
        return _read_depth(self.depth_files[index], self.width, self.height, with_bytes=True)

    def frames(self, stride: int = 1, indices=None) -> Iterator[Frame]:
        """Yield every ``stride``-th frame (or only ``indices``, ascending) as ``Frame`` objects, streamed."""
        if stride < 1:
            raise ValueError("stride must be >= 1")
        wanted = None if indices is None else sorted({int(i) for i in indices})
        keep = (lambda i: i % stride == 0) if wanted is None else (lambda i: i in wanted_set)
        wanted_set = set(wanted or [])
        last = self.num_frames - 1 if wanted is None else (wanted[-1] if wanted else -1)
        for index, rgb, rgb_encoded in self._rgb_stream(keep, last):
            depth, depth_encoded = self._depth_with_bytes(index)
            media = None if rgb_encoded is None else _media_type(self.rgb_files[index])
            yield Frame(index=index, rgb=rgb, depth=depth, rgb_encoded=rgb_encoded, rgb_media_type=media,
                        depth_encoded=depth_encoded)

    def read_frame(self, index: int) -> Frame:
        """One frame by index (decodes a video up to it)."""
        for frame in self.frames(indices=[index]):
            return frame
        raise RecordingError(f"frame {index} is past the end ({self.num_frames} frames)", self.path)

    def _rgb_stream(self, keep, last: int) -> Iterator[tuple[int, np.ndarray]]:
        if self.rgb_files is not None:
            for i, p in enumerate(self.rgb_files[: last + 1]):
                if keep(i):
                    yield i, *_read_rgb(p, self.width, self.height, with_bytes=True)
            return
        cap = cv2.VideoCapture(str(self.rgb_video))
        try:
            i = 0
            while i <= last:
                if not cap.grab():
                    self._video_ended(i)
                    break
                if keep(i):
                    ok, bgr = cap.retrieve()
                    if not ok or bgr is None:
                        raise RecordingError(f"cannot decode frame {i} of the video", self.rgb_video)
                    yield i, cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), None
                i += 1
        finally:
            cap.release()


    def _video_ended(self, decoded: int) -> None:
        """The video stopped decoding at frame ``decoded`` although ``num_frames`` were expected."""
        if decoded >= self.num_frames:
            return
        declared = self.declared_frames or self.num_frames
        if not self.allow_partial:
            raise RecordingError(partial_message(decoded, declared), self.rgb_video)
        note = f"{self.rgb_video}: {partial_message(decoded, declared)}; processed the {decoded} that decode"
        if note not in self.notes:
            self.notes.append(note)
            _warn_once(note)


def partial_message(decoded: int, declared: int) -> str:
    return (f"video is cut short: only {decoded} of the {declared} frames its header declares decode "
            "(a partial download or copy?)")


# ---------------------------------------------------------------------------------------------------------------
def _media_type(path: Path) -> str:
    return "image/png" if Path(path).suffix.lower() == ".png" else "image/jpeg"


#: largest frame file read (a 1280x720 16-bit depth PNG is ~1 MB; this bounds a sparse or hostile file).
MAX_FRAME_FILE_BYTES = 256 << 20


def _read_bytes(path: Path, what: str) -> bytes:
    """A frame file's bytes, read once (its header checked, decoded from memory, and kept for sinks that log them as
    they are)."""
    try:
        with open(path, "rb") as fh:
            data = fh.read(MAX_FRAME_FILE_BYTES + 1)
    except OSError as err:
        raise RecordingError(f"cannot read {what} ({err.strerror or err})", path) from None
    if len(data) > MAX_FRAME_FILE_BYTES:
        raise RecordingError(f"{what} is larger than {MAX_FRAME_FILE_BYTES} bytes; not read", path)
    check_image_size(path, RecordingError, what, data=data)
    return data


def _decode(data: bytes, flags: int):
    return cv2.imdecode(np.frombuffer(data, np.uint8), flags) if data else None


def _read_rgb(path: Path, width: int | None = None, height: int | None = None, *, with_bytes: bool = False):
    """RGB of one frame file (H×W×3 uint8); ``with_bytes``: (rgb, the file's bytes), the file read once."""
    data = _read_bytes(path, "RGB image")
    bgr = _decode(data, cv2.IMREAD_COLOR)
    if bgr is None:
        raise RecordingError("cannot read image (missing, empty or not an image)", path)
    if width is not None and (bgr.shape[1], bgr.shape[0]) != (width, height):
        raise RecordingError(f"frame is {bgr.shape[1]}x{bgr.shape[0]} but the recording is {width}x{height}", path)
    rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    return (rgb, data) if with_bytes else rgb


def _read_depth(path: Path, width: int, height: int, *, with_bytes: bool = False):
    """Depth of one 16-bit PNG (H×W uint16 mm), checked; ``with_bytes``: (depth, the file's bytes), read once."""
    data = _read_bytes(path, "depth image")
    depth = _decode(data, cv2.IMREAD_UNCHANGED)
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


def _sorted_images(folder: Path, suffixes=IMAGE_SUFFIXES) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in suffixes)


def _probe_video(path: Path) -> tuple[int, int, int, float, int]:
    """(width, height, decodable frames, fps, frames the header declares) of a video, checking that its first frame
    decodes and, cheaply, that its last declared frame does (a seek); only when that fails are the frames counted
    by decoding them, so a good file costs two frame decodes."""
    if path.stat().st_size == 0:
        raise RecordingError("cannot decode video: the file is empty", path)
    cap = cv2.VideoCapture(str(path))
    try:
        ok, bgr = cap.read() if cap.isOpened() else (False, None)
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


def _video_frames(path: Path, allow_partial: bool) -> tuple[int, int, int, float, int | None, list[str]]:
    """``_probe_video`` with the partial-video rule applied: (width, height, frames, fps, declared or None, notes)."""
    width, height, decoded, fps, declared = _probe_video(path)
    if decoded >= declared:
        return width, height, decoded, fps, None, []
    if not allow_partial:
        raise RecordingError(f"{partial_message(decoded, declared)}; pass --allow-partial to process the "
                             f"{decoded} that decode", path)
    note = f"{path}: {partial_message(decoded, declared)}; processed the {decoded} that decode"
    _warn_once(note)
    return width, height, decoded, fps, declared, [note]


_WARNED: set[str] = set()


def _warn_once(note: str) -> None:
    """One warning line on stderr per note and process (a recording is opened again by the runner that processes
    it; the user is told once)."""
    if note not in _WARNED:
        _WARNED.add(note)
        print(f"massviz: warning: {note}", file=sys.stderr)


#: largest meta.json / intrinsics.json read (the samples' are a few KB).
MAX_JSON_BYTES = 16 << 20


def _load_json(path: Path) -> dict:
    data = load_json(path, path.name, RecordingError, MAX_JSON_BYTES)
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


def _intrinsics_json(path: Path) -> Intrinsics:
    return check_intrinsics(_load_json(path), path)


def _intrinsics_ccm(path: Path, width: int, height: int) -> Intrinsics:
    """Intrinsics of the RGB camera from a CCM calibration pickle ([0]['rgb'] is the 3×3 camera matrix), read with
    the restricted unpickler (``massviz.io.untrusted.load_calibration_pickle``): nothing in the file runs."""
    calib = load_calibration_pickle(path, RecordingError)
    try:
        k = calib[0]["rgb"]
    except (TypeError, KeyError, IndexError) as err:
        raise RecordingError(f"not a CCM calibration pickle: expected a list whose item 0 is a dict with the 3x3 "
                             f"'rgb' camera matrix ({type(err).__name__}: {err})", path) from None
    if not isinstance(k, np.ndarray) or k.shape != (3, 3) or k.dtype.kind not in "iuf":
        shape = k.shape if isinstance(k, np.ndarray) else type(k).__name__
        raise RecordingError(f"the 'rgb' camera matrix must be a 3x3 array of numbers, got shape {shape}", path)
    k = k.astype(np.float64)
    return check_intrinsics({"fx": k[0, 0], "fy": k[1, 1], "cx": k[0, 2], "cy": k[1, 2]}, path, width, height)


def _check_counts(depth_dir: Path, n_depth: int, n_rgb: int) -> None:
    if n_depth == 0:
        raise RecordingError("no depth frames (*.png) in the depth folder", depth_dir)
    if n_depth < n_rgb:
        raise RecordingError(f"{n_depth} depth frames for {n_rgb} RGB frames: every RGB frame needs its depth",
                             depth_dir)


def open_recording(path: str | Path, *, allow_partial: bool = False) -> Recording:
    """Open and check a recording: a massviz folder, a CCM video path (ROOT/viewN/rgb/NNNNNN.mp4) or a RealSense
    file (.db3 / .bag).

    ``allow_partial``: a video cut short is processed as far as it decodes (a warning on stderr and in
    ``Recording.notes``) instead of being an error."""
    path = Path(path)
    if not path.exists():
        raise RecordingError("no such file or directory", path)
    if path.is_file():
        if path.suffix.lower() in (".db3", ".bag"):
            from massviz.io.realsense import open_realsense

            return open_realsense(path)
        if path.suffix.lower() != ".mp4":
            raise RecordingError("not a recording: give a recording folder, a CCM video (.../viewN/rgb/NNNNNN.mp4) "
                                 "or a RealSense file (.db3, .bag)", path)
        rec = _open_ccm(path, allow_partial)
    else:
        rec = _open_folder(path, allow_partial)
    rec.allow_partial = allow_partial
    return rec


def _open_ccm(video: Path, allow_partial: bool = False) -> Recording:
    view = video.parent.parent
    depth_dir = view / "depth" / video.stem
    text_id(video.stem, "recording id (the video's name)", video, RecordingError)
    if not depth_dir.is_dir():
        raise RecordingError(f"missing depth folder for this CCM video (expected {depth_dir})", video)
    width, height, n_rgb, fps, declared, notes = _video_frames(video, allow_partial)
    depth_files = _sorted_images(depth_dir, (".png",))
    _check_counts(depth_dir, len(depth_files), n_rgb)
    _read_depth(depth_files[0], width, height)
    calib = view / "calib" / f"{video.stem}.pickle"
    intr = _intrinsics_ccm(calib, width, height) if calib.is_file() else None
    return Recording(path=video, kind="ccm", id=video.stem, depth_files=depth_files, width=width, height=height,
                     num_frames=n_rgb, fps=fps, rgb_video=video, intrinsics=intr,
                     meta={"view": view.name, "dataset_root": str(view.parent)}, declared_frames=declared,
                     notes=notes)


def _open_folder(folder: Path, allow_partial: bool = False) -> Recording:
    video = folder / "rgb.mp4"
    rgb_dir = folder / "rgb"
    rgb_files = None
    declared, notes = None, []
    if video.is_file():
        width, height, n_rgb, fps, declared, notes = _video_frames(video, allow_partial)
    elif rgb_dir.is_dir():
        rgb_files = _sorted_images(rgb_dir)
        if not rgb_files:
            raise RecordingError("no RGB frames (*.png, *.jpg) in the rgb folder", rgb_dir)
        first = _read_rgb(rgb_files[0])
        height, width = first.shape[:2]
        n_rgb, fps = len(rgb_files), 30.0
        video = None
    else:
        what = "empty folder" if not any(folder.iterdir()) else "no rgb.mp4 or rgb/ folder"
        raise RecordingError(f"not a recording ({what}): expected rgb.mp4 or rgb/*.png|*.jpg and depth/*.png",
                             folder)
    depth_dir = folder / "depth"
    if not depth_dir.is_dir():
        raise RecordingError("missing depth folder (depth/*.png, 16-bit mm)", folder)
    depth_files = _sorted_images(depth_dir, (".png",))
    _check_counts(depth_dir, len(depth_files), n_rgb)
    _read_depth(depth_files[0], width, height)
    meta = check_meta(_load_json(folder / "meta.json"), folder / "meta.json", folder) \
        if (folder / "meta.json").is_file() else {}
    fps = float(meta.get("fps", fps))
    rec_id = str(meta.get("id", folder.name))
    if "id" not in meta:
        text_id(rec_id, "recording id (the folder's name)", folder, RecordingError)
    intr = _intrinsics_json(folder / "intrinsics.json") if (folder / "intrinsics.json").is_file() else None
    if intr is not None and (intr.width, intr.height) != (width, height):
        raise RecordingError(f"intrinsics are for {intr.width}x{intr.height} but the frames are {width}x{height}",
                             folder / "intrinsics.json")
    return Recording(path=folder, kind="folder", id=rec_id, depth_files=depth_files,
                     width=width, height=height, num_frames=n_rgb, fps=fps, rgb_video=video, rgb_files=rgb_files,
                     intrinsics=intr, meta=meta, declared_frames=declared, notes=notes)


def collect_recordings(paths, view: int = 3, *, allow_partial: bool = False) -> list[Recording]:
    """Expand dataset roots (``find_recordings``) and open (check) every recording before any work starts."""
    found = [p for path in paths for p in find_recordings(path, view=view)]
    return [open_recording(p, allow_partial=allow_partial) for p in found]


def find_recordings(root: str | Path, view: int = 3) -> list[Path]:
    """Recordings under a dataset root: a CCM root (``ROOT/view{view}/rgb/*.mp4``), a CCM view folder, a folder of
    massviz recordings, or a single recording. Sorted by name."""
    root = Path(root)
    if not root.exists():
        raise RecordingError("no such file or directory", root)
    if root.is_file():
        return [root]
    for rgb in (root / f"view{view}" / "rgb", root / "rgb"):
        if rgb.is_dir() and any(rgb.glob("*.mp4")):
            return sorted(rgb.glob("*.mp4"))
    if (root / "rgb.mp4").is_file() or (root / "rgb").is_dir():
        return [root]  # a recording folder, even an incomplete one: open_recording says what is missing
    found = sorted(p for p in root.iterdir() if (p.is_dir() and ((p / "rgb.mp4").is_file() or (p / "rgb").is_dir()))
                   or (p.is_file() and p.suffix.lower() in (".db3", ".bag")))
    if not found:
        raise RecordingError(f"no recordings found (looked for view{view}/rgb/*.mp4, recording folders and RealSense "
                             ".db3/.bag files)", root)
    return found
