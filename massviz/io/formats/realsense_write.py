"""Writing RealSense ``.db3`` files (librealsense 2.59 records only ROS2 .db3; .bag files can be read, not written)
through a ``software_device`` and librealsense's ``recorder``."""
from __future__ import annotations

import contextlib
from pathlib import Path

import numpy as np

from massviz.core.recording_protocol import Recording
from massviz.core.types import Frame, Intrinsics
from massviz.errors import MassvizError, RecordingError
from massviz.io.formats.realsense_decode import import_rs


def _rs_intrinsics(rs, intr: Intrinsics):
    ri = rs.intrinsics()
    ri.width, ri.height = int(intr.width), int(intr.height)
    ri.fx, ri.fy, ri.ppx, ri.ppy = float(intr.fx), float(intr.fy), float(intr.cx), float(intr.cy)
    ri.model = rs.distortion.none
    ri.coeffs = [0.0] * 5
    return ri


class SoftwareRig:
    """A ``software_device`` with a depth (z16, depth units option) and a colour (rgb8) sensor whose stream
    profiles carry the intrinsics. By default depth is registered to colour (the colour intrinsics, identity
    extrinsics); ``depth_intrinsics`` and ``translation_m`` (depth-to-colour, metres) describe a depth camera
    beside the colour one instead (as on a real D400: then readers align with librealsense's align); ``rotation``
    (9 numbers, column-major) is the depth-to-colour rotation (tests write degenerate ones)."""

    def __init__(self, rs, intr: Intrinsics, fps: float, depth_units: float = 0.001, serial: str = "massviz-sw",
                 name: str = "massviz software camera", depth_intrinsics: Intrinsics | None = None,
                 translation_m=(0.0, 0.0, 0.0), rotation=(1, 0, 0, 0, 1, 0, 0, 0, 1)):
        self.rs, self.intr, self.fps, self.depth_units = rs, intr, fps, depth_units
        self.depth_intr = depth_intrinsics or intr
        sd = self.device = rs.software_device()
        sd.register_info(rs.camera_info.name, name)
        sd.register_info(rs.camera_info.serial_number, serial)
        self.depth_sensor, self.colour_sensor = sd.add_sensor("Depth"), sd.add_sensor("Color")
        profiles = []
        streams = ((self.depth_sensor, rs.stream.depth, 0, 2, rs.format.z16, self.depth_intr),
                   (self.colour_sensor, rs.stream.color, 1, 3, rs.format.rgb8, intr))
        for sensor, kind, uid, bpp, fmt, si in streams:
            ri = _rs_intrinsics(rs, si)
            vs = rs.video_stream()
            vs.type, vs.index, vs.uid, vs.fps, vs.bpp, vs.fmt = kind, 0, uid, int(round(fps)), bpp, fmt
            vs.width, vs.height, vs.intrinsics = ri.width, ri.height, ri
            profiles.append(sensor.add_video_stream(vs).as_video_stream_profile())  # (not a plain stream_profile)
        self.depth_profile, self.colour_profile = profiles
        self.depth_sensor.add_read_only_option(rs.option.depth_units, depth_units)
        ex = rs.extrinsics()  # all zeros by default, not the identity
        ex.rotation, ex.translation = [float(r) for r in rotation], [float(t) for t in translation_m]
        self.depth_profile.register_extrinsics_to(self.colour_profile, ex)
        sd.create_matcher(rs.matchers.dlr_c)

    @contextlib.contextmanager
    def record(self, path: str | Path):
        """Record what is pushed inside the block to the ``.db3`` ``path`` (librealsense's ``recorder``; both
        sensors open and started, stopped and closed after it, then the file is finished)."""
        recorder = self.rs.recorder(str(path), self.device)
        sensors = ((self.depth_sensor, self.depth_profile), (self.colour_sensor, self.colour_profile))
        for sensor, profile in sensors:
            sensor.open(profile)
            sensor.start(lambda f: None)
        try:
            yield self
        finally:
            for sensor, _ in sensors:
                sensor.stop()
                sensor.close()
            del recorder

    def push(self, frame: Frame, number: int, timestamp_ms: float, depth: np.ndarray | None = None) -> None:
        """Push ``frame`` (its depth in mm, or ``depth`` in mm at the depth stream's size) as frame ``number``."""
        rs = self.rs
        depth = frame.depth if depth is None else depth
        if (frame.width, frame.height) != (self.intr.width, self.intr.height) or \
                (depth.shape[1], depth.shape[0]) != (self.depth_intr.width, self.depth_intr.height):
            raise MassvizError(f"frame {frame.index} does not have the streams' sizes "
                               f"({self.intr.width}x{self.intr.height} colour, "
                               f"{self.depth_intr.width}x{self.depth_intr.height} depth)")
        z = depth if abs(self.depth_units - 0.001) < 1e-12 else \
            np.clip(np.rint(depth / (self.depth_units * 1000.0)), 0, 65535).astype(np.uint16)
        for sensor, profile, data, bpp in ((self.depth_sensor, self.depth_profile, z, 2),
                                           (self.colour_sensor, self.colour_profile, frame.rgb, 3)):
            f = rs.software_video_frame()
            data = np.ascontiguousarray(data)
            f.pixels, f.stride, f.bpp = data, int(data.shape[1]) * bpp, bpp
            f.timestamp, f.domain, f.frame_number = timestamp_ms, rs.timestamp_domain.hardware_clock, number
            f.profile = profile
            if bpp == 2:
                f.depth_units = self.depth_units
            sensor.on_video_frame(f)


def write_realsense(recording: Recording, path: str | Path, *, pace: bool = True, depth_units: float = 0.001,
                    progress: bool = False) -> Path:
    """Write ``recording`` as a RealSense ``.db3`` through librealsense's ``recorder`` (depth z16 with the
    ``depth_units`` option, colour rgb8, the recording's intrinsics on both stream profiles, frame numbers
    0..n-1, timestamps index/fps ms). ``pace`` (default): the file plays back like a camera, at the recording's fps
    (``pace_messages``: the recorder stamps each message with the wall clock of writing, so a file written as fast
    as frames can be pushed would play back in a burst: ``massviz live --file`` would process a few frames and drop
    the rest); ``pace=False`` keeps the recorder's stamps. Written to a temporary name and renamed, so nothing is
    left half-written."""
    from massviz.io.atomic import atomic_path

    rs = import_rs()
    path = Path(path)
    if path.suffix.lower() != ".db3":
        raise MassvizError("librealsense writes RealSense recordings only as ROS2 .db3 (.bag can be read, not "
                           "written)", path)
    if recording.intrinsics is None:
        raise RecordingError("the recording has no intrinsics (intrinsics.json): a RealSense stream needs them",
                             recording.path)
    fps = float(recording.fps or 30.0)
    with atomic_path(path) as tmp:
        rig = SoftwareRig(rs, recording.intrinsics, fps, depth_units)
        with rig.record(tmp):
            for i, frame in enumerate(recording.frames()):
                rig.push(frame, i, i * 1000.0 / fps)
        if pace:
            pace_messages(tmp, fps)
    return path


def pace_messages(path: str | Path, fps: float) -> None:
    """Re-stamp the per-frame messages (``.../image/...`` topics) of a ``.db3`` so that frame k is stamped k / fps
    seconds after frame 0 (the messages of one frame keep their order, 1 µs apart: the writer's own delays, which grow
    with the machine's load, are not kept): librealsense's real-time playback waits on these stamps, so the file
    then plays like a camera at ``fps``."""
    import sqlite3

    period_ns = 1e9 / fps
    with contextlib.closing(sqlite3.connect(str(path))) as db:
        topics = [t for (t,) in db.execute("SELECT id FROM topics WHERE name LIKE '%/image/%'")]
        per_topic = [db.execute("SELECT id, timestamp FROM messages WHERE topic_id = ? ORDER BY timestamp, id",
                                (t,)).fetchall() for t in topics]
        n = min((len(m) for m in per_topic), default=0)
        if n == 0:
            return
        t0 = min(m[0][1] for m in per_topic)  # when the recorder got frame 0's first message
        updates = []
        for k in range(n):  # frame k's messages, in the order the recorder got them, 1 µs apart from k / fps
            frame = sorted(((m[k][1], m[k][0]) for m in per_topic))
            updates += [(t0 + round(k * period_ns) + 1000 * j, mid) for j, (_, mid) in enumerate(frame)]
        db.executemany("UPDATE messages SET timestamp = ? WHERE id = ?", updates)
        db.commit()
