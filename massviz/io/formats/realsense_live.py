"""Live RealSense sources for ``massviz live``: a camera (``open_camera``), a file played back in real time
(``open_file_stream``) or the sensors of any ``rs.device``, e.g. a ``SoftwareCamera`` fed from a thread
(``open_device_stream``), all as a ``LiveStream`` of colour+depth pairs."""
from __future__ import annotations

import threading
import time
from pathlib import Path

from massviz.core.types import Frame, Intrinsics
from massviz.errors import MassvizError
from massviz.io.formats.realsense_decode import StreamInfo, import_rs
from massviz.io.formats.realsense_device import DeviceReader, playback_device
from massviz.io.formats.realsense_file import open_realsense
from massviz.io.formats.realsense_write import SoftwareRig
from massviz.io.untrusted import MAX_ID_CHARS, printable


class LiveStream:
    """A real-time RealSense source for ``massviz live``: a camera, a file played back in real time, or any
    ``rs.device`` (e.g. a ``SoftwareCamera``). ``start(sink)`` hands every colour+depth pair to ``sink(c, d)`` on
    librealsense's threads as it arrives (the sink must not block: it keeps the newest); ``frame(c, d, index)``
    turns a pair into a massviz ``Frame`` (align, copy, mm)."""

    def __init__(self, reader: DeviceReader, description: str, on_stop=None, recording=None, option: str = ""):
        self.reader, self.description, self._on_stop = reader, description, on_stop
        #: the command-line option that chose this source (e.g. ``--camera 123456789012``), named in its errors
        self.option = option
        #: a file's ``RealSenseRecording`` (opened and checked once, before its real-time playback); None otherwise
        self.recording = recording

    @property
    def info(self) -> StreamInfo:
        return self.reader.info

    @property
    def is_file(self) -> bool:
        return self.reader.playback is not None

    def start(self, sink) -> "LiveStream":
        self.reader.sink = sink
        self.reader.start()
        return self

    def frame(self, c, d, index: int) -> Frame:
        return self.reader.frame(c, d, index)

    def finished(self) -> bool:
        return self.reader.finished()

    def stop(self) -> None:
        self.reader.stop()
        if self._on_stop is not None:
            self._on_stop()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()


def open_file_stream(path: str | Path) -> LiveStream:
    """A RealSense file played back in real time (at the pace it was recorded; frames are not waited for)."""
    rec = open_realsense(path)  # every check (and a clear line) up front
    rs, device, playback, profiles = playback_device(rec.path, real_time=True)
    reader = DeviceReader(rs, device, profiles, rec.path, None, playback=playback)
    return LiveStream(reader, f"{rec.path.name} (real-time playback, {rec.num_frames} frames at {rec.fps:g} fps)",
                      recording=rec)


def list_cameras() -> list[dict]:
    """Connected RealSense cameras: name and serial number."""
    rs = import_rs()
    out = []
    for dev in rs.context().query_devices():
        info = {}
        for key, name in (("name", "name"), ("serial", "serial_number")):
            if dev.supports(getattr(rs.camera_info, name)):
                info[key] = printable(dev.get_info(getattr(rs.camera_info, name)), max_chars=MAX_ID_CHARS)
        out.append(info)
    return out


def _pick_profile(sensor, rs, stream, formats, width, height, fps):
    best = None
    for p in sensor.get_stream_profiles():
        if p.stream_type() != stream or p.format() not in formats or p.stream_index() not in (0, 1):
            continue
        v = p.as_video_stream_profile()
        cost = (abs(v.width() - width) + abs(v.height() - height), abs(v.fps() - fps), formats.index(p.format()))
        if best is None or cost < best[0]:
            best = (cost, p)
    return None if best is None else best[1]


def open_camera(serial: str | None = None, width: int = 640, height: int = 480, fps: int = 30) -> LiveStream:
    """The connected camera with this serial (default: the first one) streaming colour (rgb8) and depth (z16) at
    the size and rate nearest to those asked for. Untested without hardware beyond the error paths."""
    rs = import_rs()
    devices = list(rs.context().query_devices())
    if not devices:
        raise MassvizError("no RealSense camera connected (check the USB 3 cable and permissions; or give --file "
                           "X.db3 to play back a recording)")
    serials = [d.get_info(rs.camera_info.serial_number) if d.supports(rs.camera_info.serial_number) else "?"
               for d in devices]
    if serial is None:
        device, serial = devices[0], serials[0]
    elif serial in serials:
        device = devices[serials.index(serial)]
    else:
        raise MassvizError(f"no RealSense camera with serial {printable(serial, max_chars=MAX_ID_CHARS)} (connected: "
                           f"{', '.join(printable(s, max_chars=MAX_ID_CHARS) for s in serials)})")
    serial = printable(serial, max_chars=MAX_ID_CHARS)  # from the device: printed in messages and descriptions
    profiles = []
    for stream, formats in ((rs.stream.color, [rs.format.rgb8, rs.format.bgr8, rs.format.yuyv]),
                            (rs.stream.depth, [rs.format.z16])):
        found = None
        for sensor in device.query_sensors():
            found = found or _pick_profile(sensor, rs, stream, formats, width, height, fps)
        if found is None:
            raise MassvizError(f"camera {serial} has no {'colour' if stream == rs.stream.color else 'depth'} "
                               "stream massviz can read")
        profiles.append(found)
    reader = DeviceReader(rs, device, profiles, f"camera {serial}", None)
    name = reader.info.device.get("name", "RealSense")
    return LiveStream(reader, f"{name} #{serial} ({reader.info.width}x{reader.info.height} at {reader.info.fps:g} fps)")


def open_device_stream(device, description: str = "software device", on_stop=None) -> LiveStream:
    """Any ``rs.device`` with a colour and a depth sensor (e.g. ``SoftwareCamera(...).device``) as a live source."""
    rs = import_rs()
    profiles = [p for s in device.query_sensors() for p in s.get_stream_profiles()]
    return LiveStream(DeviceReader(rs, device, profiles, description, None), description, on_stop=on_stop)



class SoftwareCamera:
    """A stand-in RealSense camera: a ``software_device`` whose frames a thread pushes at ``fps`` (from a list of
    ``Frame``s, looped ``loops`` times), consumable with ``open_device_stream(cam.device)`` like a camera.
    Start the stream first, then ``cam.start()``; ``cam.done`` is set when every frame was pushed."""

    def __init__(self, frames: list[Frame], intrinsics: Intrinsics, fps: float = 30.0, loops: int = 1,
                 serial: str = "massviz-sw", **rig):
        self.rs = import_rs()
        self.frames, self.fps, self.loops = frames, float(fps), int(loops)
        self.rig = SoftwareRig(self.rs, intrinsics, fps, serial=serial, **rig)
        self.device = self.rig.device
        self.done = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.pushed = 0

    def start(self) -> "SoftwareCamera":
        self._thread = threading.Thread(target=self._feed, name="massviz-software-camera", daemon=True)
        self._thread.start()
        return self

    def _feed(self) -> None:
        t0 = time.perf_counter()
        n = 0
        try:
            for _ in range(self.loops):
                for frame in self.frames:
                    if self._stop.is_set():
                        return
                    time.sleep(max(0.0, t0 + n / self.fps - time.perf_counter()))
                    self.rig.push(frame, n, n * 1000.0 / self.fps)
                    n += 1
                    self.pushed = n
        finally:
            self.done.set()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
