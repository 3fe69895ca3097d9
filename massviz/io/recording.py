"""Opening RGB-D recordings: the dispatcher over the formats of ``massviz.io.formats`` (one module per format, each
owning its reader and its writer; the ``Recording`` protocol they implement is ``massviz.core.recording_protocol``):

* **massviz folders** (``formats.folder``)::

      REC/rgb.mp4  or  REC/rgb/*.png|*.jpg
      REC/depth/*.png                        16-bit mm, aligned to RGB, sorted by name
      REC/intrinsics.json                    optional {"fx","fy","cx","cy","width","height"}
      REC/meta.json                          optional annotations / ground truth

* **CCM** (CORSMAL Containers Manipulation, ``formats.ccm``), addressed by the video path::

      ROOT/view{1..4}/rgb/NNNNNN.mp4
      ROOT/view{n}/depth/NNNNNN/*.png        16-bit mm, aligned to RGB, sorted by name
      ROOT/view{n}/calib/NNNNNN.pickle       optional calibration (intrinsics of 'rgb')

* **RealSense files** ``X.db3`` (ROS2, librealsense >= 2.56) and ``X.bag`` (ROS1), through ``pyrealsense2``
  (optional extra ``massviz[realsense]``): ``formats.realsense_file``.

Frames are streamed (``Recording.frames``): nothing is accumulated, so memory does not grow with the recording's
length. Problems are reported as ``RecordingError`` naming the file, checked up front where that is cheap (so a
long run does not fail half-way) and again per frame.

Every file is untrusted (``massviz.io.untrusted``): calibration pickles go through a restricted unpickler, every
number is checked where it is read (finite, in range, integral where it must be), ids are text without control
characters, image sizes are bounded from their headers before anything is decoded, frame folders must hold only
evenly numbered regular files, and a path pattern in meta.json must stay inside the recording.

A video that decodes fewer frames than its header declares (a file cut short) is an error naming both counts, unless
``open_recording(..., allow_partial=True)`` (CLI ``--allow-partial``): then the decoded frames are used and the
shortfall is said on stderr and kept in ``Recording.notes`` (the pipeline puts them in the trace's events, so they
show in Rerun's ``/log``).
"""
from __future__ import annotations

from pathlib import Path

from massviz.core.recording_protocol import Recording
from massviz.errors import RecordingError
from massviz.io.formats.ccm import CCMRecording, ccm_videos, is_ccm_root, open_ccm
from massviz.io.formats.common import (
    IMAGE_SUFFIXES,
    MAX_FRAME_FILE_BYTES,
    MAX_JSON_BYTES,
    RecordingBase,
    check_intrinsics,
    partial_message,
)
from massviz.io.formats.folder import FrameFilesRecording, looks_like_recording, open_folder
from massviz.io.formats.realsense_decode import SUFFIXES as REALSENSE_SUFFIXES


def open_recording(path: str | Path, *, allow_partial: bool = False, rgb_only: bool = False) -> Recording:
    """Open and check a recording: a massviz folder, a CCM video path (ROOT/viewN/rgb/NNNNNN.mp4) or a RealSense
    file (.db3 / .bag).

    ``allow_partial``: a video cut short is processed as far as it decodes (a warning on stderr and in
    ``Recording.notes``) instead of being an error. ``rgb_only``: a folder or CCM video without depth opens as an
    RGB-only recording (``.rgb_only``: every depth frame is zeros, so nothing has a d and nothing is estimated)
    instead of being an error that says what is missing ('massviz log' does: detections and tracks on RGB alone)."""
    path = Path(path)
    if not path.exists():
        raise RecordingError("no such file or directory", path)
    if path.is_file():
        if path.suffix.lower() in REALSENSE_SUFFIXES:
            from massviz.io.formats.realsense_file import open_realsense  # pyrealsense2 only when needed

            return open_realsense(path)
        if path.suffix.lower() != ".mp4":
            raise RecordingError("not a recording: give a recording folder, a CCM video (.../viewN/rgb/NNNNNN.mp4) "
                                 "or a RealSense file (.db3, .bag)", path)
        return open_ccm(path, allow_partial, rgb_only)
    return open_folder(path, allow_partial, rgb_only)


def collect_recordings(paths, view: int = 3, *, allow_partial: bool = False) -> list[Recording]:
    """Expand dataset roots (``find_recordings``) and open (check) every recording before any work starts."""
    found = [p for path in paths for p in find_recordings(path, view=view)]
    return [open_recording(p, allow_partial=allow_partial) for p in found]


def find_recordings(root: str | Path, view: int = 3) -> list[Path]:
    """Recordings under a dataset root: a CCM root (``ROOT/view{view}/rgb/*.mp4``), a CCM view folder, a folder of
    massviz recordings, or a single recording. Sorted by name. A CCM root without ``view{view}`` is an error
    ("no view2 under ROOT"), not the recordings of another view."""
    root = Path(root)
    if not root.exists():
        raise RecordingError("no such file or directory", root)
    if root.is_file():
        return [root]
    videos = ccm_videos(root, view)
    if videos is not None:
        return videos
    if is_ccm_root(root):
        raise RecordingError(f"no view{view} under {root} (a CCM root: view{view}/rgb/*.mp4 is missing or empty)",
                             root)
    if looks_like_recording(root):
        return [root]  # a recording folder, even an incomplete one: open_recording says what is missing
    found = sorted(p for p in root.iterdir() if looks_like_recording(p)
                   or (p.is_file() and p.suffix.lower() in REALSENSE_SUFFIXES))
    if not found:
        raise RecordingError(f"no recordings found (looked for view{view}/rgb/*.mp4, recording folders and RealSense "
                             ".db3/.bag files)", root)
    return found


__all__ = ["Recording", "RecordingBase", "FrameFilesRecording", "CCMRecording", "open_recording",
           "collect_recordings", "find_recordings", "check_intrinsics", "partial_message", "IMAGE_SUFFIXES",
           "MAX_FRAME_FILE_BYTES", "MAX_JSON_BYTES"]
