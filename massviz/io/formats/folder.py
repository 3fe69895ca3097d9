"""The massviz folder format: reader (``open_folder``, ``FrameFilesRecording``) and writer (``FolderFrameWriter``,
used by ``massviz live --save`` and the sample generator)::

    REC/rgb.mp4  or  REC/rgb/*.png|*.jpg
    REC/depth/*.png                        16-bit mm, aligned to RGB, sorted by name
    REC/intrinsics.json                    optional {"fx","fy","cx","cy","width","height"}
    REC/meta.json                          optional annotations / ground truth

``FrameFilesRecording`` is also the reader of any format made of an RGB video or RGB frame files plus one depth
PNG per frame (CCM, ``massviz.io.formats.ccm``). ``read_depth(i)`` reads one file: O(1).
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from massviz.core.types import Frame, Intrinsics
from massviz.errors import MassvizError, RecordingError
from massviz.io.formats.common import (
    RecordingBase,
    check_intrinsics,
    frame_files,
    load_json,
    media_type,
    partial_message,
    read_depth_png,
    read_rgb,
    video_frames,
    wanted_frames,
    warn_once,
)
from massviz.io.meta import check_meta, write_intrinsics
from massviz.io.untrusted import text_id

KIND = "folder"


@dataclass
class FrameFilesRecording(RecordingBase):
    """A recording made of an RGB video (``rgb_video``) or RGB frame files (``rgb_files``) and one 16-bit depth PNG
    per frame (``depth_files``). Create it with ``open_recording``."""

    depth_files: list[Path] = field(default_factory=list)
    rgb_video: Path | None = None
    rgb_files: list[Path] | None = None
    #: frames the video's header declares when fewer decode (``allow_partial``); None when all decode.
    declared_frames: int | None = None
    allow_partial: bool = False
    #: no depth at all (opened with ``rgb_only=True``): every frame's depth is zeros (no depth), so detectors find
    #: boxes and tracks but no detection has a d and nothing is estimated
    rgb_only: bool = False

    def input_files(self) -> list[Path]:
        """Every file the frames are read from (RGB video or images, then depth images)."""
        files = [self.rgb_video] if self.rgb_video else list(self.rgb_files or [])
        return [*files, *self.depth_files]

    def video_file(self) -> Path | None:
        """The RGB video a viewer can show as one asset (frames referenced by time), or None for frame images."""
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

    def read_depth(self, index: int) -> np.ndarray:
        """Depth of frame ``index`` (H×W uint16, mm), checked: reads that frame's one PNG (O(1))."""
        return self._depth_with_bytes(index)[0]

    def _depth_with_bytes(self, index: int) -> tuple[np.ndarray, bytes | None]:
        if self.rgb_only:
            return np.zeros((self.height, self.width), np.uint16), None
        if not 0 <= index < len(self.depth_files):
            raise RecordingError(f"no depth image for frame {index} ({len(self.depth_files)} depth frames)",
                                 self.depth_files[0].parent if self.depth_files else self.path)
        return read_depth_png(self.depth_files[index], self.width, self.height, with_bytes=True,
                              digests=self._watched())

    def frames(self, stride: int = 1, indices=None, workers: int = 1) -> Iterator[Frame]:
        """Yield every ``stride``-th frame (or only ``indices``, ascending) as ``Frame`` objects, streamed; frame
        files' bytes travel on the Frame (``rgb_encoded``, ``depth_encoded``), each file read once. ``workers`` > 1:
        the depth PNGs are decoded by that many threads, up to twice as many frames ahead (the same frames, in
        order; a GPU consumes frames faster than one thread decodes 1280x720 PNGs)."""
        keep, last = wanted_frames(self.num_frames, stride, indices)

        def frame(index, rgb, rgb_encoded, depth):
            depth, depth_encoded = depth.result() if hasattr(depth, "result") else depth
            media = None if rgb_encoded is None else media_type(self.rgb_files[index])
            return Frame(index=index, rgb=rgb, depth=depth, rgb_encoded=rgb_encoded, rgb_media_type=media,
                         depth_encoded=depth_encoded)

        if workers <= 1:
            for index, rgb, rgb_encoded in self._rgb_stream(keep, last):
                yield frame(index, rgb, rgb_encoded, self._depth_with_bytes(index))
            return
        from collections import deque
        from concurrent.futures import ThreadPoolExecutor

        pool = ThreadPoolExecutor(int(workers), thread_name_prefix="massviz-depth")
        pending: deque = deque()
        try:
            for index, rgb, rgb_encoded in self._rgb_stream(keep, last):
                pending.append((index, rgb, rgb_encoded, pool.submit(self._depth_with_bytes, index)))
                if len(pending) > 2 * workers:
                    yield frame(*pending.popleft())
            while pending:
                yield frame(*pending.popleft())
        finally:
            pool.shutdown(wait=True, cancel_futures=True)

    def _rgb_stream(self, keep, last: int):
        if self.rgb_files is not None:
            for i, p in enumerate(self.rgb_files[: last + 1]):
                if keep(i):
                    yield i, *read_rgb(p, self.width, self.height, with_bytes=True, digests=self._watched())
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
            warn_once(note)


#: what a recording without depth is told (after "no depth (...)")
NO_DEPTH = ("massviz estimates mass from RGB-D: it needs one 16-bit depth PNG per RGB frame (millimetres, aligned to "
            "RGB); without depth, 'massviz log REC --rrd OUT.rrd --detector nanodet' shows what a detector finds and "
            "its tracks (no mass)")


def check_counts(depth_dir: Path, n_depth: int, n_rgb: int) -> None:
    if n_depth == 0:
        raise RecordingError("no depth frames (*.png) in the depth folder", depth_dir)
    if n_depth < n_rgb:
        raise RecordingError(f"{n_depth} depth frames for {n_rgb} RGB frames: every RGB frame needs its depth",
                             depth_dir)


#: what a recording folder holds: a folder holding any of them is a recording (opening it says what is wrong)
RECORDING_ENTRIES = ("rgb", "rgb.mp4", "depth", "meta.json", "intrinsics.json")


def looks_like_recording(path: Path) -> bool:
    """``path`` is a folder meant as a recording: it holds any of :data:`RECORDING_ENTRIES` (whatever they are: a
    ``rgb/`` that is a symlink loop or a file is a broken recording, not a folder to skip), or it cannot be read (its
    opening says so). A dataset lists these, so that no broken recording is left out in silence."""
    import os

    if not path.is_dir():
        return False
    if not os.access(path, os.R_OK | os.X_OK):
        return True
    return any(os.path.lexists(path / name) for name in RECORDING_ENTRIES)


def _not_a_folder(path: Path) -> str | None:
    """Why ``path``, which exists, is not a folder (a symlink loop, a dangling symlink, a file); None when it is
    one or is missing."""
    import os

    if path.is_dir() or not os.path.lexists(path):
        return None
    if path.is_symlink():
        try:
            os.stat(path)
        except OSError as err:
            return f"is a symlink that cannot be followed ({err.strerror or err})"
    return "is a file, not a folder"


def open_folder(folder: Path, allow_partial: bool = False, rgb_only: bool = False) -> FrameFilesRecording:
    """Open and check a massviz recording folder (see the module docstring). ``rgb_only``: a folder without depth/
    opens as an RGB-only recording (``FrameFilesRecording.rgb_only``) instead of being an error."""
    video = folder / "rgb.mp4"
    rgb_dir = folder / "rgb"
    rgb_files = None
    declared, notes = None, []
    if video.is_file():
        width, height, n_rgb, fps, declared, notes = video_frames(video, allow_partial)
    elif rgb_dir.is_dir():
        rgb_files = frame_files(rgb_dir, what="RGB frames")
        if not rgb_files:
            raise RecordingError("no RGB frames (*.png, *.jpg) in the rgb folder", rgb_dir)
        first = read_rgb(rgb_files[0], keep=True)
        height, width = first.shape[:2]
        n_rgb, fps = len(rgb_files), 30.0
        video = None
    elif (why := _not_a_folder(rgb_dir)) is not None:
        raise RecordingError(f"{why}; expected a folder of RGB frames (rgb/*.png|*.jpg)", rgb_dir)
    else:
        what = "empty folder" if not any(folder.iterdir()) else "no rgb.mp4 or rgb/ folder"
        raise RecordingError(f"not a recording ({what}): expected rgb.mp4 or rgb/*.png|*.jpg and depth/*.png",
                             folder)
    depth_dir = folder / "depth"
    if (why := _not_a_folder(depth_dir)) is not None:
        raise RecordingError(f"{why}; expected a folder of depth frames (depth/*.png)", depth_dir)
    no_depth = not depth_dir.is_dir()
    if no_depth and not rgb_only:
        raise RecordingError(f"no depth (no depth/ folder): {NO_DEPTH}", folder)
    depth_files = [] if no_depth else frame_files(depth_dir, (".png",), what="depth frames")
    if not no_depth:
        check_counts(depth_dir, len(depth_files), n_rgb)
        read_depth_png(depth_files[0], width, height, keep=True)
    meta = check_meta(load_json(folder / "meta.json"), folder / "meta.json", folder) \
        if (folder / "meta.json").is_file() else {}
    fps = float(meta.get("fps", fps))
    rec_id = str(meta.get("id", folder.name))
    if "id" not in meta:
        text_id(rec_id, "recording id (the folder's name)", folder, RecordingError)
    intr = (check_intrinsics(load_json(folder / "intrinsics.json"), folder / "intrinsics.json")
            if (folder / "intrinsics.json").is_file() else None)
    if intr is not None and (intr.width, intr.height) != (width, height):
        raise RecordingError(f"intrinsics are for {intr.width}x{intr.height} but the frames are {width}x{height}",
                             folder / "intrinsics.json")
    return FrameFilesRecording(path=folder, kind=KIND, id=rec_id, depth_files=depth_files, width=width,
                               height=height, num_frames=n_rgb, fps=fps, rgb_video=video, rgb_files=rgb_files,
                               intrinsics=intr, meta=meta, declared_frames=declared, notes=notes,
                               allow_partial=allow_partial, rgb_only=no_depth)


# ------------------------------------------------------------------------------------------------------ writer
class FolderFrameWriter:
    """Writes a massviz recording folder into ``folder`` (an existing, empty directory; callers make it a
    temporary one renamed into place, ``massviz.io.atomic.atomic_dir``): ``rgb/NNNNNN.png`` (lossless),
    ``depth/NNNNNN.png`` (16-bit mm), optional extra per-frame images (e.g. ``gt/``), then ``finish`` writes
    ``intrinsics.json`` and ``meta.json``. ``compression``: PNG level (1 = fast, for live; 7 = small)."""

    def __init__(self, folder: str | Path, compression: int = 7, extra: tuple[str, ...] = ()):
        self.folder = Path(folder)
        self.params = [cv2.IMWRITE_PNG_COMPRESSION, int(compression)]
        for sub in ("rgb", "depth", *extra):
            (self.folder / sub).mkdir()
        self.names: list[str] = []
        self.size: tuple[int, int] | None = None
        self.intrinsics: Intrinsics | None = None
        self.meta: dict = {}

    def _imwrite(self, path: Path, image: np.ndarray) -> None:
        if not cv2.imwrite(str(path), image, self.params):
            raise MassvizError("could not write image", path)

    def write(self, index: int, rgb: np.ndarray, depth: np.ndarray, **extra: np.ndarray) -> None:
        """Frame ``index``: ``rgb`` H×W×3 uint8 RGB, ``depth`` H×W uint16 mm, ``extra`` sub-folder -> image."""
        name = f"{index:06d}.png"
        self.size = self.size or (int(rgb.shape[1]), int(rgb.shape[0]))
        self._imwrite(self.folder / "rgb" / name, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        self._imwrite(self.folder / "depth" / name, depth)
        for sub, image in extra.items():
            self._imwrite(self.folder / sub / name, image)
        self.names.append(name)

    def finish(self, intrinsics: Intrinsics | None, meta: dict) -> Path:
        if intrinsics is not None:
            write_intrinsics(intrinsics, self.folder / "intrinsics.json")
        text = json.dumps(meta, indent=1) + "\n"
        (self.folder / "meta.json").write_text(text)
        self.intrinsics, self.meta = intrinsics, json.loads(text)
        return self.folder

    def written(self, path: str | Path) -> FrameFilesRecording:
        """The recording this writer wrote, once its folder is at ``path`` (renamed into place), without reading
        it back: what ``open_recording(path)`` returns for it (the frames' files, sizes, intrinsics, meta)."""
        path = Path(path)
        if self.size is None:
            raise MassvizError("no frame was written", path)
        width, height = self.size
        return FrameFilesRecording(path=path, kind=KIND, id=str(self.meta.get("id", path.name)), width=width,
                                   height=height, num_frames=len(self.names),
                                   fps=float(self.meta.get("fps", 30.0)), intrinsics=self.intrinsics,
                                   meta=self.meta, rgb_files=[path / "rgb" / n for n in self.names],
                                   depth_files=[path / "depth" / n for n in self.names])


def write_folder(recording, path: str | Path, compression: int = 7) -> Path:
    """Write any ``Recording`` as a massviz folder at ``path`` (atomically: a temporary folder renamed into place)."""
    from massviz.io.atomic import atomic_dir

    path = Path(path)
    with atomic_dir(path) as tmp:
        writer = FolderFrameWriter(tmp, compression)
        for frame in recording.frames():
            writer.write(frame.index, frame.rgb, frame.depth)
        writer.finish(recording.intrinsics, dict(recording.meta, id=recording.id, fps=recording.fps))
    return path
