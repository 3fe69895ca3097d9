"""The RealSense file format (ROS2 ``.db3``, librealsense >= 2.56; ROS1 ``.bag``, older SDKs): reader
(``open_realsense``, ``RealSenseRecording``); the writer is ``massviz.io.formats.realsense_write.write_realsense``.
"""
from __future__ import annotations

import math
import re
import sqlite3
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar, Iterator

import numpy as np

from massviz.core.types import Frame
from massviz.errors import RecordingError
from massviz.io.formats.common import RecordingBase, wanted_frames
from massviz.io.formats.realsense_decode import StreamInfo, import_rs, stream_info
from massviz.io.formats.realsense_device import FileFrames, playback_device
from massviz.io.untrusted import text_id

KIND = "realsense"


def _connect_ro(path: Path) -> sqlite3.Connection:
    """The .db3 opened read-only. The path goes into SQLite's URI percent-encoded (``Path.as_uri``): a file name
    that looks like a URI itself (``%2E%2E%2F...#.db3``) names that file, never another one, and ``#`` cannot cut
    ``mode=ro`` off (which would let SQLite create a database elsewhere)."""
    return sqlite3.connect(f"{Path(path).resolve().as_uri()}?mode=ro", uri=True)


def db3_check(path: Path) -> None:
    """A quick integrity check of a ROS2 bag (SQLite), so a truncated file is one clear line up front."""
    if path.stat().st_size == 0:
        raise RecordingError("not a readable RealSense recording (the file is empty)", path)
    try:
        con = _connect_ro(path)
        try:
            ok = con.execute("PRAGMA quick_check").fetchone()[0]
            con.execute("SELECT count(*) FROM messages").fetchone()
        finally:
            con.close()
    except sqlite3.DatabaseError as err:
        raise RecordingError(f"not a readable RealSense recording (.db3: {err}; truncated or not a ROS2 bag?)",
                             path) from None
    if ok != "ok":
        raise RecordingError(f"corrupt RealSense recording (.db3 integrity check: {ok})", path)


#: metadata topics of the colour and depth images in a librealsense .db3 (frame number and time of each image)
_METADATA_TOPIC = re.compile(r"^/device_\d+/sensor_\d+/(Color|Depth)_\d+/image/metadata$")
_FIELD = re.compile(r"(Frame number|timestamp)=([^;]*);")


def db3_frames(path: Path, fps: float) -> tuple[list[int], list[float]] | None:
    """(frame numbers, timestamps in ms) of the colour+depth pairs a playback of the .db3 ``path`` delivers,
    from its SQLite ``messages`` table (the per-image metadata messages, paired by timestamp within half a frame
    period as ``DeviceReader`` pairs them), without decoding an image; None when the file does not have the
    layout librealsense writes (one colour and one depth metadata topic): then the caller counts by playback."""
    try:
        con = _connect_ro(path)
        try:
            topics = {tid: m.group(1) for tid, name in con.execute("SELECT id, name FROM topics")
                      if isinstance(name, str) and (m := _METADATA_TOPIC.match(name))}
            if sorted(topics.values()) != ["Color", "Depth"]:
                return None
            rows = con.execute(f"SELECT topic_id, data FROM messages WHERE topic_id IN ({','.join('?' * 2)}) "
                               "ORDER BY timestamp, id", list(topics)).fetchall()
        finally:
            con.close()
    except sqlite3.DatabaseError:
        return None
    tolerance = 500.0 / max(fps, 1.0)
    pending: dict[str, tuple[int, float]] = {}
    numbers, stamps = [], []
    for tid, data in rows:
        if not isinstance(data, bytes):
            return None
        fields = dict(_FIELD.findall(data[8:].decode("latin-1")))
        try:
            number, stamp = int(fields["Frame number"]), float(fields["timestamp"])
        except (KeyError, ValueError):
            return None
        if not (0 <= number < 2**63 and math.isfinite(stamp)):
            return None
        kind = "c" if topics[tid] == "Color" else "d"
        pending[kind] = (number, stamp)
        c, d = pending.get("c"), pending.get("d")
        if c is None or d is None:
            continue
        if abs(c[1] - d[1]) > tolerance:
            del pending["c" if c[1] < d[1] else "d"]
            continue
        pending.clear()
        numbers.append(c[0])
        stamps.append(c[1])
    return numbers, stamps


@dataclass
class RealSenseRecording(RecordingBase):
    """A RealSense ``.db3``/``.bag`` file as a massviz recording: no frame files (the frames are in the one file),
    no video asset. Frames are decoded by a non-real-time playback of the file (see ``massviz.io.formats.
    realsense_decode`` for how colour and depth become a ``Frame``)."""

    stream: StreamInfo | None = None
    frame_numbers: list = field(default_factory=list)
    timestamps_ms: list = field(default_factory=list)
    #: depth maps of the last frames asked for with ``read_depth`` (index -> depth), at most ``DEPTH_CACHE``.
    _depth_cache: dict = field(default_factory=dict, repr=False, compare=False)

    DEPTH_CACHE: ClassVar[int] = 4

    def input_files(self) -> list[Path]:
        """The RealSense file itself: the content key (``fingerprint``) hashes its bytes."""
        return [self.path]

    def source_description(self) -> dict[str, str]:
        name = self.path.name
        return {"rgb": f"colour stream of `{name}`", "depth": f"depth stream of `{name}` (aligned to colour)"}

    def read_depth(self, index: int) -> np.ndarray:
        """Depth of frame ``index`` (mm, aligned to colour). Cost: a playback of the file from its start up to that
        frame (frames after it are not read), then kept: the last ``DEPTH_CACHE`` depth maps asked for are
        answered from memory."""
        if index in self._depth_cache:
            return self._depth_cache[index]
        depth = self.read_frame(index).depth
        self._depth_cache[index] = depth
        while len(self._depth_cache) > self.DEPTH_CACHE:
            del self._depth_cache[next(iter(self._depth_cache))]
        return depth

    def frames(self, stride: int = 1, indices=None) -> Iterator[Frame]:
        """Every ``stride``-th frame (or only ``indices``): one playback of the file up to the last frame wanted."""
        keep, last = wanted_frames(self.num_frames, stride, indices)
        if last < 0:
            return
        frames = FileFrames(self.path)
        i = -1
        try:
            for i, (c, d) in enumerate(frames):
                if i > last:
                    break
                if keep(i):
                    yield frames.reader.frame(c, d, i)
        finally:
            frames.close()
        if i < last:  # the file changed since it was opened, or librealsense skipped frames: never a silent gap
            raise RecordingError(f"the RealSense recording ended after {i + 1} of {self.num_frames} frames", self.path)


def _check_timing(stamps: list[float], path: Path) -> None:
    """Every frame's time is a finite number of ms, never earlier than the frame before: the recording's duration
    (what ``massviz live --file`` plays in real time, and every frame's time in a trace) is a number."""
    for i, stamp in enumerate(stamps):
        if not math.isfinite(stamp):
            raise RecordingError(f"frame {i}'s timestamp is {stamp} ms, so the recording's duration is not a number; "
                                 "not a playable RealSense recording", path)
        if i and stamp < stamps[i - 1]:
            raise RecordingError(f"frame {i}'s timestamp ({stamp:g} ms) is before frame {i - 1}'s "
                                 f"({stamps[i - 1]:g} ms); not a playable RealSense recording", path)


def open_realsense(path: str | Path) -> RealSenseRecording:
    """Open and check a RealSense file: streams, depth scale, intrinsics, extrinsics, and every frame's number and
    time (a .db3: from its ``messages`` table, no playback; a .bag: by playing it back without decoding)."""
    path = Path(path)
    if not path.is_file():
        raise RecordingError("no such file", path)
    text_id(path.stem, "recording id (the file's name)", path, RecordingError)  # as folders' and CCM videos' names
    rs = import_rs()
    counted = None
    if path.suffix.lower() == ".db3":
        db3_check(path)
        rs_, device, playback, profiles = playback_device(path, real_time=False)
        info = stream_info(rs, device, profiles, path)
        counted = db3_frames(path, info.fps)
        del rs_, device, playback, profiles
    if counted is None:
        frames = FileFrames(path)
        numbers, stamps = [], []
        try:
            for c, _ in frames:
                numbers.append(int(c.get_frame_number()))
                stamps.append(float(c.get_timestamp()))
        finally:
            frames.close()
        info = frames.reader.info
    else:
        numbers, stamps = counted
    if not numbers:
        raise RecordingError("the RealSense recording has no frame with both colour and depth", path)
    _check_timing(stamps, path)
    meta = {"id": path.stem, "fps": info.fps,
            "realsense": {"file": path.name, **info.describe(), "frame_numbers": numbers, "timestamps_ms": stamps}}
    return RealSenseRecording(path=path, kind=KIND, id=path.stem, width=info.width, height=info.height,
                              num_frames=len(numbers), fps=info.fps, intrinsics=info.intrinsics, meta=meta,
                              stream=info, frame_numbers=numbers, timestamps_ms=stamps)
