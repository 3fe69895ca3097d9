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
"""
from __future__ import annotations

import hashlib
import json
import pickle
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from massviz.errors import RecordingError
from massviz.core.types import Frame, Intrinsics, RecordingInfo

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

    # -- identity --------------------------------------------------------------------------------------------------
    @property
    def config_id(self) -> str:
        """The id written in the challenge CSV's 'Configuration ID' column (CCM: the integer recording number)."""
        if self.kind == "ccm" and self.id.isdigit():
            return str(int(self.id))
        return str(self.meta.get("config_id", self.id))

    def fingerprint(self) -> str:
        """A cheap content key (paths, sizes and modification times of every input file)."""
        h = hashlib.sha1()
        files = [self.rgb_video] if self.rgb_video else list(self.rgb_files or [])
        for p in [*files, *self.depth_files]:
            st = p.stat()
            h.update(f"{p.resolve()}|{st.st_size}|{st.st_mtime_ns}\n".encode())
        return h.hexdigest()

    def info(self) -> RecordingInfo:
        """What a trace keeps of this recording."""
        return RecordingInfo(id=self.id, config_id=self.config_id, path=str(self.path), kind=self.kind,
                             width=self.width, height=self.height, num_frames=self.num_frames, fps=self.fps,
                             rgb=str(self.rgb_video) if self.rgb_video else "frames", intrinsics=self.intrinsics,
                             meta=self.meta)

    # -- frames ----------------------------------------------------------------------------------------------------
    def read_depth(self, index: int) -> np.ndarray:
        """Depth of frame ``index`` (H×W uint16, mm), checked."""
        if index >= len(self.depth_files):
            raise RecordingError(f"no depth image for frame {index} ({len(self.depth_files)} depth frames)",
                                 self.depth_files[0].parent if self.depth_files else self.path)
        return _read_depth(self.depth_files[index], self.width, self.height)

    def frames(self, stride: int = 1, indices=None) -> Iterator[Frame]:
        """Yield every ``stride``-th frame (or only ``indices``, ascending) as ``Frame`` objects, streamed."""
        if stride < 1:
            raise ValueError("stride must be >= 1")
        wanted = None if indices is None else sorted({int(i) for i in indices})
        keep = (lambda i: i % stride == 0) if wanted is None else (lambda i: i in wanted_set)
        wanted_set = set(wanted or [])
        last = self.num_frames - 1 if wanted is None else (wanted[-1] if wanted else -1)
        for index, rgb in self._rgb_stream(keep, last):
            yield Frame(index=index, rgb=rgb, depth=self.read_depth(index))

    def read_frame(self, index: int) -> Frame:
        """One frame by index (decodes a video up to it)."""
        for frame in self.frames(indices=[index]):
            return frame
        raise RecordingError(f"frame {index} is past the end ({self.num_frames} frames)", self.path)

    def _rgb_stream(self, keep, last: int) -> Iterator[tuple[int, np.ndarray]]:
        if self.rgb_files is not None:
            for i, p in enumerate(self.rgb_files[: last + 1]):
                if keep(i):
                    yield i, _read_rgb(p, self.width, self.height)
            return
        cap = cv2.VideoCapture(str(self.rgb_video))
        try:
            i = 0
            while i <= last:
                if not cap.grab():
                    break
                if keep(i):
                    ok, bgr = cap.retrieve()
                    if not ok or bgr is None:
                        raise RecordingError(f"cannot decode frame {i} of the video", self.rgb_video)
                    yield i, cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
                i += 1
        finally:
            cap.release()


# ---------------------------------------------------------------------------------------------------------------
def _read_rgb(path: Path, width: int | None = None, height: int | None = None) -> np.ndarray:
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise RecordingError("cannot read image (missing, empty or not an image)", path)
    if width is not None and (bgr.shape[1], bgr.shape[0]) != (width, height):
        raise RecordingError(f"frame is {bgr.shape[1]}x{bgr.shape[0]} but the recording is {width}x{height}", path)
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def _read_depth(path: Path, width: int, height: int) -> np.ndarray:
    depth = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
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
    return depth


def _sorted_images(folder: Path, suffixes=IMAGE_SUFFIXES) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in suffixes)


def _probe_video(path: Path) -> tuple[int, int, int, float]:
    """(width, height, frame count, fps) of a video, checking that its first frame decodes."""
    if path.stat().st_size == 0:
        raise RecordingError("cannot decode video: the file is empty", path)
    cap = cv2.VideoCapture(str(path))
    try:
        ok, bgr = cap.read() if cap.isOpened() else (False, None)
        if not ok or bgr is None:
            raise RecordingError("cannot decode video (not a readable video file)", path)
        count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        fps = float(cap.get(cv2.CAP_PROP_FPS)) or 30.0
        return bgr.shape[1], bgr.shape[0], max(count, 1), fps
    finally:
        cap.release()


def _load_json(path: Path) -> dict:
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise RecordingError(f"not valid JSON ({err})", path) from None
    if not isinstance(data, dict):
        raise RecordingError("expected a JSON object", path)
    return data


def _intrinsics_json(path: Path) -> Intrinsics:
    data = _load_json(path)
    try:
        intr = Intrinsics.from_dict(data)
    except (KeyError, TypeError, ValueError) as err:
        raise RecordingError(f"intrinsics need numeric fx, fy, cx, cy, width, height ({err!s} is wrong)",
                             path) from None
    if intr.fx <= 0 or intr.fy <= 0:
        raise RecordingError("intrinsics fx and fy must be positive", path)
    return intr


def _intrinsics_ccm(path: Path, width: int, height: int) -> Intrinsics:
    """Intrinsics of the RGB camera from a CCM calibration pickle ([0]['rgb'] is the 3×3 camera matrix)."""
    try:
        with open(path, "rb") as fh:
            calib = pickle.load(fh, encoding="latin1")
        k = np.asarray(calib[0]["rgb"], dtype=np.float64)
        if k.shape != (3, 3):
            raise ValueError(f"rgb camera matrix has shape {k.shape}")
    except Exception as err:  # noqa: BLE001 - any unpickling problem is a malformed file
        raise RecordingError(f"not a CCM calibration pickle ({type(err).__name__}: {err})", path) from None
    return Intrinsics(float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]), width, height)


def _check_counts(depth_dir: Path, n_depth: int, n_rgb: int) -> None:
    if n_depth == 0:
        raise RecordingError("no depth frames (*.png) in the depth folder", depth_dir)
    if n_depth < n_rgb:
        raise RecordingError(f"{n_depth} depth frames for {n_rgb} RGB frames: every RGB frame needs its depth",
                             depth_dir)


def open_recording(path: str | Path) -> Recording:
    """Open and check a recording: a massviz folder, a CCM video path (ROOT/viewN/rgb/NNNNNN.mp4) or a RealSense
    file (.db3 / .bag)."""
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
        return _open_ccm(path)
    return _open_folder(path)


def _open_ccm(video: Path) -> Recording:
    view = video.parent.parent
    depth_dir = view / "depth" / video.stem
    if not depth_dir.is_dir():
        raise RecordingError(f"missing depth folder for this CCM video (expected {depth_dir})", video)
    width, height, n_rgb, fps = _probe_video(video)
    depth_files = _sorted_images(depth_dir, (".png",))
    _check_counts(depth_dir, len(depth_files), n_rgb)
    _read_depth(depth_files[0], width, height)
    calib = view / "calib" / f"{video.stem}.pickle"
    intr = _intrinsics_ccm(calib, width, height) if calib.is_file() else None
    return Recording(path=video, kind="ccm", id=video.stem, depth_files=depth_files, width=width, height=height,
                     num_frames=n_rgb, fps=fps, rgb_video=video, intrinsics=intr,
                     meta={"view": view.name, "dataset_root": str(view.parent)})


def _open_folder(folder: Path) -> Recording:
    video = folder / "rgb.mp4"
    rgb_dir = folder / "rgb"
    rgb_files = None
    if video.is_file():
        width, height, n_rgb, fps = _probe_video(video)
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
    meta = _load_json(folder / "meta.json") if (folder / "meta.json").is_file() else {}
    try:
        fps = float(meta.get("fps", fps))
    except (TypeError, ValueError):
        raise RecordingError(f"'fps' must be a number, got {meta['fps']!r}", folder / "meta.json") from None
    intr = _intrinsics_json(folder / "intrinsics.json") if (folder / "intrinsics.json").is_file() else None
    if intr is not None and (intr.width, intr.height) != (width, height):
        raise RecordingError(f"intrinsics are for {intr.width}x{intr.height} but the frames are {width}x{height}",
                             folder / "intrinsics.json")
    return Recording(path=folder, kind="folder", id=str(meta.get("id", folder.name)), depth_files=depth_files,
                     width=width, height=height, num_frames=n_rgb, fps=fps, rgb_video=video, rgb_files=rgb_files,
                     intrinsics=intr, meta=meta)


def collect_recordings(paths, view: int = 3) -> list[Recording]:
    """Expand dataset roots (``find_recordings``) and open (check) every recording before any work starts."""
    found = [p for path in paths for p in find_recordings(path, view=view)]
    return [open_recording(p) for p in found]


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
