"""The CORSMAL Containers Manipulation (CCM) layout, read only (the dataset is published, massviz does not write
it), addressed by the video path::

    ROOT/view{1..4}/rgb/NNNNNN.mp4
    ROOT/view{n}/depth/NNNNNN/*.png        16-bit mm, aligned to RGB, sorted by name
    ROOT/view{n}/calib/NNNNNN.pickle       optional calibration (intrinsics of 'rgb')

A CCM recording is an RGB video plus one depth PNG per frame: ``massviz.io.formats.folder.FrameFilesRecording``
reads it (``read_depth(i)`` reads one file)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from massviz.core.types import Intrinsics
from massviz.errors import RecordingError
from massviz.io.formats.common import check_intrinsics, frame_files, read_depth_png, video_frames
from massviz.io.formats.folder import NO_DEPTH, FrameFilesRecording, check_counts
from massviz.io.untrusted import load_calibration_pickle, text_id

KIND = "ccm"


@dataclass
class CCMRecording(FrameFilesRecording):
    """One CCM recording (its RGB video, its depth folder, its calibration when present)."""

    @property
    def config_id(self) -> str:
        """The challenge CSV's 'Configuration ID': the integer recording number."""
        return str(int(self.id)) if self.id.isdigit() else str(self.meta.get("config_id", self.id))


def is_ccm_video(path: Path) -> bool:
    return path.suffix.lower() == ".mp4"


def ccm_videos(root: Path, view: int) -> list[Path] | None:
    """The recordings (videos) of a CCM root's ``view``, or of a CCM view folder; None when ``root`` is neither."""
    for rgb in (root / f"view{view}" / "rgb", root / "rgb"):
        if rgb.is_dir() and any(rgb.glob("*.mp4")):
            return sorted(rgb.glob("*.mp4"))
    return None


def is_ccm_root(root: Path) -> bool:
    """A CCM dataset root: has viewN/rgb/*.mp4 for some view N."""
    return any((root / f"view{n}" / "rgb").is_dir() and any((root / f"view{n}" / "rgb").glob("*.mp4"))
               for n in range(1, 5))


def intrinsics_ccm(path: Path, width: int, height: int) -> Intrinsics:
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


def open_ccm(video: Path, allow_partial: bool = False, rgb_only: bool = False) -> CCMRecording:
    """Open and check one CCM recording by its video path (``rgb_only``: as ``open_folder``'s)."""
    view = video.parent.parent
    depth_dir = view / "depth" / video.stem
    text_id(video.stem, "recording id (the video's name)", video, RecordingError)
    no_depth = not depth_dir.is_dir()
    if no_depth and not rgb_only:
        raise RecordingError(f"no depth (expected {depth_dir}): {NO_DEPTH}", video)
    width, height, n_rgb, fps, declared, notes = video_frames(video, allow_partial)
    depth_files = [] if no_depth else frame_files(depth_dir, (".png",), what="depth frames")
    if not no_depth:
        check_counts(depth_dir, len(depth_files), n_rgb)
        read_depth_png(depth_files[0], width, height, keep=True)
    calib = view / "calib" / f"{video.stem}.pickle"
    intr = intrinsics_ccm(calib, width, height) if calib.is_file() else None
    return CCMRecording(path=video, kind=KIND, id=video.stem, depth_files=depth_files, width=width, height=height,
                        num_frames=n_rgb, fps=fps, rgb_video=video, intrinsics=intr,
                        meta={"view": view.name, "dataset_root": str(view.parent)}, declared_frames=declared,
                        notes=notes, allow_partial=allow_partial, rgb_only=no_depth)
