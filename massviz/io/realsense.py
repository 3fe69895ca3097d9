"""Intel RealSense recordings and cameras, through ``pyrealsense2`` (the optional extra ``massviz[realsense]``).

* **Files**: ROS2 ``.db3`` (what librealsense >= 2.56 records) and ROS1 ``.bag`` (older SDKs, RealSense Viewer),
  read with librealsense's playback in non-real-time mode (every frame, none dropped). ``open_recording("x.db3")``
  returns a ``RealSenseRecording``; every command that takes a recording takes these files.
* **Frames**: the colour stream (rgb8, bgr8, rgba8, bgra8 or yuyv) and the depth stream (z16) aligned to colour
  with librealsense's ``rs.align(rs.stream.color)``, scaled to millimetres with the device's depth scale
  (``round(z16 * depth_scale * 1000)``). A depth stream that is already registered to colour (same size and
  intrinsics, identity extrinsics, e.g. files written by ``write_realsense``) is used as it is: librealsense's align
  is not the identity there (it leaves ~5 % holes from float round-off of the projected pixel corners and grows
  near objects at edges), so skipping it keeps such files exact. Frame indices are the position in the file
  (0, 1, ...); librealsense's frame numbers and timestamps (ms) are kept in ``meta["realsense"]``.
* **Intrinsics**: the colour stream profile's (fx, fy, ppx, ppy, width, height); lens distortion coefficients are
  not applied (massviz's model is a pinhole; ``meta["realsense"]["distortion"]`` says which model the file has).
* **Live sources** (``massviz live``): a camera (``open_camera``), a file played back in real time
  (``open_file_stream``) or the sensors of any ``rs.device``, e.g. a ``SoftwareCamera`` fed from a thread
  (``open_device_stream``), all as a ``RealSenseStream`` of framesets.
* ``write_realsense`` writes a massviz recording as a ``.db3`` with a ``software_device`` and a ``recorder``
  (librealsense 2.59 records only ROS2 .db3; .bag files can be read but not written).
"""
from __future__ import annotations

import contextlib
import queue
import sqlite3
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from massviz.core.types import Frame, Intrinsics
from massviz.errors import MassvizError, RecordingError
from massviz.io.recording import Recording

SUFFIXES = (".db3", ".bag")
INSTALL_HINT = "RealSense support needs pyrealsense2: pip install 'massviz[realsense]' (or pip install pyrealsense2)"
#: seconds without a frame, before the end of a file, after which its non-real-time playback counts as stalled.
FILE_TIMEOUT_S = 10.0


def import_rs():
    """``pyrealsense2``, or a ``MassvizError`` saying what to install."""
    try:
        import pyrealsense2 as rs
    except ImportError:
        raise MassvizError(INSTALL_HINT) from None
    return rs


def is_realsense_file(path) -> bool:
    return Path(path).suffix.lower() in SUFFIXES


def _reason(err: Exception) -> str:
    """librealsense's message without its 'Failed to resolve request ... Reason:' preamble, on one line."""
    msg = str(err)
    if "Reason:" in msg:
        msg = msg.split("Reason:", 1)[1]
    return " ".join(msg.split()).rstrip(".")


# --------------------------------------------------------------------------------------------- frameset decoding
_COLOUR_CONVERSIONS = {"rgb8": None, "bgr8": cv2.COLOR_BGR2RGB, "rgba8": cv2.COLOR_RGBA2RGB,
                       "bgra8": cv2.COLOR_BGRA2RGB, "yuyv": cv2.COLOR_YUV2RGB_YUYV}


def _f32(value) -> float:
    """librealsense stores intrinsics as float32: the shortest decimal that is that float32 (346.4, not
    346.3999938964844), so intrinsics written from a JSON file read back equal."""
    return float(str(np.float32(value)))


def _intrinsics_of(profile) -> Intrinsics:
    i = profile.as_video_stream_profile().get_intrinsics()
    return Intrinsics(_f32(i.fx), _f32(i.fy), _f32(i.ppx), _f32(i.ppy), int(i.width), int(i.height))


@dataclass
class StreamInfo:
    """What a RealSense source delivers, and how its framesets become massviz ``Frame``s."""

    intrinsics: Intrinsics
    fps: float
    depth_scale: float
    colour_format: str
    registered: bool          # depth already in the colour camera (no align needed)
    distortion: str
    device: dict = field(default_factory=dict)

    @property
    def width(self) -> int:
        return self.intrinsics.width

    @property
    def height(self) -> int:
        return self.intrinsics.height

    def describe(self) -> dict:
        return {"depth_scale": self.depth_scale, "colour_format": self.colour_format, "distortion": self.distortion,
                "depth_to_colour": "registered (used as is)" if self.registered else "librealsense align",
                **self.device}


def stream_info(rs, device, profiles, source) -> StreamInfo:
    """Check that ``profiles`` (stream profiles of ``device``) hold one colour and one depth stream and describe
    them; ``source`` names the file or camera in errors."""
    colour = [p for p in profiles if p.stream_type() == rs.stream.color]
    depth = [p for p in profiles if p.stream_type() == rs.stream.depth]
    have = ", ".join(f"{p.stream_name()} {p.format()}".replace("format.", "") for p in profiles) or "none"
    if not colour:
        raise RecordingError(f"no colour stream (streams: {have}); massviz needs colour and depth", source)
    if not depth:
        raise RecordingError(f"no depth stream (streams: {have}); massviz needs colour and depth", source)
    c, d = colour[0].as_video_stream_profile(), depth[0].as_video_stream_profile()
    fmt = str(c.format()).replace("format.", "")
    if fmt not in _COLOUR_CONVERSIONS:
        raise RecordingError(f"colour stream format {fmt} is not supported ({', '.join(_COLOUR_CONVERSIONS)})",
                             source)
    if str(d.format()).replace("format.", "") != "z16":
        raise RecordingError(f"depth stream format {d.format()} is not supported (z16)", source)
    info = {}
    try:
        scale = float(device.first_depth_sensor().get_depth_scale())
    except RuntimeError:  # no depth-units option recorded: librealsense's default unit, said in the metadata
        scale = 0.001
        info["depth_scale_note"] = "no depth units option in the source: assumed 0.001 m (1 mm)"
    if not scale > 0:
        raise RecordingError(f"depth scale {scale} is not positive", source)
    ci, di = c.get_intrinsics(), d.get_intrinsics()
    same = ((ci.width, ci.height, ci.fx, ci.fy, ci.ppx, ci.ppy, ci.model, list(ci.coeffs))
            == (di.width, di.height, di.fx, di.fy, di.ppx, di.ppy, di.model, list(di.coeffs)))
    try:
        ex = d.get_extrinsics_to(c)
        identity = (np.allclose(np.asarray(ex.rotation, float), np.eye(3).ravel(), atol=1e-7)
                    and np.allclose(np.asarray(ex.translation, float), 0.0, atol=1e-9))
    except RuntimeError:
        identity = False
    for key, name in (("name", "name"), ("serial", "serial_number"), ("firmware", "firmware_version")):
        try:
            if device.supports(getattr(rs.camera_info, name)):
                info[key] = device.get_info(getattr(rs.camera_info, name))
        except (RuntimeError, AttributeError):
            pass
    return StreamInfo(intrinsics=_intrinsics_of(c), fps=float(c.fps()), depth_scale=scale, colour_format=fmt,
                      registered=same and identity, distortion=str(ci.model).replace("distortion.", ""),
                      device=info)


class FrameDecoder:
    """Frameset -> ``Frame`` (copies): colour to RGB, depth aligned to colour (unless registered) and in mm."""

    def __init__(self, rs, info: StreamInfo):
        self.rs, self.info = rs, info
        self.align = None if info.registered else rs.align(rs.stream.color)
        self._conv = _COLOUR_CONVERSIONS[info.colour_format]
        s = info.depth_scale * 1000.0
        self._mm = None if abs(s - 1.0) < 1e-6 else s  # 1 mm units: the z16 values are the millimetres

    def split(self, fs):
        """(colour frame, depth frame) of a frameset, aligned; (None, None) when one of them is missing."""
        if self.align is not None:
            fs = self.align.process(fs)
        c, d = fs.get_color_frame(), fs.get_depth_frame()
        if not c or not d:
            return None, None
        return c, d

    def decode(self, c, d, index: int) -> Frame:
        rgb = np.asanyarray(c.get_data())
        rgb = rgb.copy() if self._conv is None else cv2.cvtColor(rgb, self._conv)
        z = np.asanyarray(d.get_data())
        if self._mm is None:
            depth = z.copy()
        else:
            depth = np.clip(np.rint(z.astype(np.float64) * self._mm), 0, 65535).astype(np.uint16)
        return Frame(index=index, rgb=np.ascontiguousarray(rgb), depth=depth)


# -------------------------------------------------------------------------------------------- reading a device
def _sensors_for(device, profiles) -> list[tuple[object, list]]:
    """(sensor, its profiles among ``profiles``) for every sensor of ``device`` that streams one of them."""
    out = []
    for sensor in device.query_sensors():
        ids = {p.unique_id() for p in sensor.get_stream_profiles()}
        mine = [p for p in profiles if p.unique_id() in ids]
        if mine:
            out.append((sensor, mine))
    return out


class DeviceReader:
    """Colour+depth pairs from the sensors of an ``rs.device`` (a file's playback device, a camera or a
    ``software_device``), in the order they arrive, handed to ``sink(colour_frame, depth_frame)``.

    Sensors are started with callbacks rather than through ``rs.pipeline``: a pipeline starts a file's playback in
    real time before it can be switched to non-real-time, losing the first frames in about half of the runs, and
    ``rs.syncer`` splits the first frames into partial sets. Colour and depth are paired by timestamp (within half a
    frame period); an unpaired frame replaced by a newer one of its stream is counted in ``unpaired``. ``sink`` runs
    on librealsense's threads (in non-real-time playback the file waits for it: back-pressure).
    """

    def __init__(self, rs, device, profiles, source, sink, playback=None):
        self.rs, self.device, self.source, self.sink, self.playback = rs, device, source, sink, playback
        self.info = stream_info(rs, device, profiles, source)
        self.decoder = FrameDecoder(rs, self.info)
        chosen = [next(p for p in profiles if p.stream_type() == kind) for kind in (rs.stream.color, rs.stream.depth)]
        self.sensors = _sensors_for(device, chosen)
        self.tolerance_ms = 500.0 / max(self.info.fps, 1.0)
        self.unpaired = 0
        self.error: BaseException | None = None
        self._lock = threading.Lock()
        self._pending: dict[str, object] = {}
        self._started = False

    def _on_frame(self, f) -> None:
        try:
            kind = "c" if f.get_profile().stream_type() == self.rs.stream.color else "d"
            with self._lock:
                if kind in self._pending:
                    self.unpaired += 1
                self._pending[kind] = f
                c, d = self._pending.get("c"), self._pending.get("d")
                if c is None or d is None:
                    return
                if abs(c.get_timestamp() - d.get_timestamp()) > self.tolerance_ms:
                    older = "c" if c.get_timestamp() < d.get_timestamp() else "d"
                    del self._pending[older]
                    self.unpaired += 1
                    return
                self._pending.clear()
            self.sink(c, d)
        except BaseException as err:  # noqa: BLE001 - reported by the reading thread, never lost in a callback
            self.error = err

    def start(self) -> "DeviceReader":
        for sensor, mine in self.sensors:
            sensor.open(mine if len(mine) > 1 else mine[0])
        if self.playback is not None:
            self.playback.pause()  # else the first frames are read before every sensor listens
        for sensor, _ in self.sensors:
            sensor.start(self._on_frame)
        self._started = True
        if self.playback is not None:
            self.playback.resume()
        return self

    def finished(self) -> bool:
        """A file's playback reached its end (always False for cameras)."""
        return self.playback is not None and self.playback.current_status() == self.rs.playback_status.stopped

    def stop(self) -> None:
        if not self._started:
            return
        self._started = False
        for sensor, _ in self.sensors:
            try:
                sensor.stop()
            except RuntimeError:
                pass
        for sensor, _ in self.sensors:
            try:
                sensor.close()
            except RuntimeError:
                pass

    def frame(self, c, d, index: int) -> Frame:
        """The massviz ``Frame`` of a pair (depth aligned to colour unless registered, in mm)."""
        if self.decoder.align is not None:
            c, d = self.decoder.split(self._frameset(c, d))
        return self.decoder.decode(c, d, index)

    def _frameset(self, c, d):
        holder = [d, c]
        block = self.rs.processing_block(
            lambda f, src: src.frame_ready(src.allocate_composite_frame(holder)))
        out = self.rs.frame_queue(1)
        block.start(out)
        block.invoke(c)
        return out.wait_for_frame().as_frameset()


def _playback_device(path: Path, real_time: bool):
    rs = import_rs()
    try:
        device = rs.context().load_device(str(path))
    except RuntimeError as err:
        raise RecordingError(f"not a readable RealSense recording ({_reason(err)})", path) from None
    playback = device.as_playback()
    playback.set_real_time(real_time)
    profiles = [p for s in device.query_sensors() for p in s.get_stream_profiles()]
    return rs, device, playback, profiles


class _FileFrames:
    """Every colour+depth pair of a file, in order (non-real-time playback, bounded queue)."""

    def __init__(self, path: Path):
        rs, device, self.playback, profiles = _playback_device(path, real_time=False)
        self.path = path
        self.queue: queue.Queue = queue.Queue(maxsize=2)
        self.closing = False
        self.reader = DeviceReader(rs, device, profiles, path, self._put, playback=self.playback)

    def _put(self, c, d) -> None:
        while not self.closing:
            try:
                self.queue.put((c, d), timeout=0.05)
                return
            except queue.Full:
                continue

    def __iter__(self):
        self.reader.start()
        idle = 0.0
        while True:
            try:
                item = self.queue.get(timeout=0.05)
            except queue.Empty:
                if self.reader.error is not None:
                    raise RecordingError(f"cannot read the RealSense recording ({self.reader.error})",
                                         self.path) from None
                idle += 0.05
                if self.reader.finished() and self.queue.empty():
                    return
                if idle > FILE_TIMEOUT_S:
                    raise RecordingError(f"the RealSense playback stalled (no frame for {FILE_TIMEOUT_S:g} s before "
                                         "the end of the file)", self.path)
                continue
            idle = 0.0
            yield item

    def close(self) -> None:
        self.closing = True
        self.reader.stop()


def _db3_check(path: Path) -> None:
    """A quick integrity check of a ROS2 bag (SQLite), so a truncated file is one clear line up front."""
    if path.stat().st_size == 0:
        raise RecordingError("not a readable RealSense recording (the file is empty)", path)
    try:
        con = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
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


@dataclass
class RealSenseRecording(Recording):
    """A RealSense ``.db3``/``.bag`` file as a massviz recording (see the module docstring)."""

    stream: StreamInfo | None = None
    frame_numbers: list = field(default_factory=list)
    timestamps_ms: list = field(default_factory=list)

    def input_files(self) -> list[Path]:
        """The RealSense file itself: the content key (``Recording.fingerprint``) hashes its bytes."""
        return [self.path]

    def read_depth(self, index: int) -> np.ndarray:
        return self.read_frame(index).depth

    def frames(self, stride: int = 1, indices=None) -> Iterator[Frame]:
        if stride < 1:
            raise ValueError("stride must be >= 1")
        wanted = None if indices is None else {int(i) for i in indices}
        last = self.num_frames - 1 if wanted is None else (max(wanted) if wanted else -1)
        if last < 0:
            return
        frames = _FileFrames(self.path)
        i = -1
        try:
            for i, (c, d) in enumerate(frames):
                if i > last:
                    break
                if (i % stride == 0) if wanted is None else (i in wanted):
                    yield frames.reader.frame(c, d, i)
        finally:
            frames.close()
        if i < last:  # the file changed since it was opened, or librealsense skipped frames: never a silent gap
            raise RecordingError(f"the RealSense recording ended after {i + 1} of {self.num_frames} frames", self.path)


def open_realsense(path: str | Path) -> RealSenseRecording:
    """Open and check a RealSense file: streams, depth scale, intrinsics, and every frame's number and time."""
    path = Path(path)
    if not path.is_file():
        raise RecordingError("no such file", path)
    import_rs()
    if path.suffix.lower() == ".db3":
        _db3_check(path)
    frames = _FileFrames(path)
    numbers, stamps = [], []
    try:
        for c, _ in frames:
            numbers.append(int(c.get_frame_number()))
            stamps.append(float(c.get_timestamp()))
    finally:
        frames.close()
    if not numbers:
        raise RecordingError("the RealSense recording has no frame with both colour and depth", path)
    info = frames.reader.info
    meta = {"id": path.stem, "fps": info.fps,
            "realsense": {"file": path.name, **info.describe(), "frame_numbers": numbers, "timestamps_ms": stamps}}
    return RealSenseRecording(path=path, kind="realsense", id=path.stem, depth_files=[], width=info.width,
                              height=info.height, num_frames=len(numbers), fps=info.fps, rgb_video=None,
                              rgb_files=None, intrinsics=info.intrinsics, meta=meta, stream=info,
                              frame_numbers=numbers, timestamps_ms=stamps)


# ------------------------------------------------------------------------------------------------- live sources
class LiveStream:
    """A real-time RealSense source for ``massviz live``: a camera, a file played back in real time, or any
    ``rs.device`` (e.g. a ``SoftwareCamera``). ``start(sink)`` hands every colour+depth pair to ``sink(c, d)`` on
    librealsense's threads as it arrives (the sink must not block: it keeps the newest); ``frame(c, d, index)``
    turns a pair into a massviz ``Frame`` (align, copy, mm)."""

    def __init__(self, reader: DeviceReader, description: str, on_stop=None):
        self.reader, self.description, self._on_stop = reader, description, on_stop

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
    rs, device, playback, profiles = _playback_device(rec.path, real_time=True)
    reader = DeviceReader(rs, device, profiles, rec.path, None, playback=playback)
    return LiveStream(reader, f"{rec.path.name} (real-time playback, {rec.num_frames} frames at {rec.fps:g} fps)")


def list_cameras() -> list[dict]:
    """Connected RealSense cameras: name and serial number."""
    rs = import_rs()
    out = []
    for dev in rs.context().query_devices():
        info = {}
        for key, name in (("name", "name"), ("serial", "serial_number")):
            if dev.supports(getattr(rs.camera_info, name)):
                info[key] = dev.get_info(getattr(rs.camera_info, name))
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
        raise MassvizError(f"no RealSense camera with serial {serial} (connected: {', '.join(serials)})")
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


# ------------------------------------------------------------------------------------- writing (software_device)
def _rs_intrinsics(rs, intr: Intrinsics):
    ri = rs.intrinsics()
    ri.width, ri.height = int(intr.width), int(intr.height)
    ri.fx, ri.fy, ri.ppx, ri.ppy = float(intr.fx), float(intr.fy), float(intr.cx), float(intr.cy)
    ri.model = rs.distortion.none
    ri.coeffs = [0.0] * 5
    return ri


class _SoftwareRig:
    """A ``software_device`` with a depth (z16, depth units option) and a colour (rgb8) sensor whose stream
    profiles carry the intrinsics. By default depth is registered to colour (the colour intrinsics, identity
    extrinsics); ``depth_intrinsics`` and ``translation_m`` (depth-to-colour, metres) describe a depth camera
    beside the colour one instead (as on a real D400: then readers align with librealsense's align)."""

    def __init__(self, rs, intr: Intrinsics, fps: float, depth_units: float = 0.001, serial: str = "massviz-sw",
                 name: str = "massviz software camera", depth_intrinsics: Intrinsics | None = None,
                 translation_m=(0.0, 0.0, 0.0)):
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
        ex.rotation, ex.translation = [1, 0, 0, 0, 1, 0, 0, 0, 1], [float(t) for t in translation_m]
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


def write_realsense(recording: Recording, path: str | Path, *, pace: bool = False, depth_units: float = 0.001,
                    progress: bool = False) -> Path:
    """Write ``recording`` as a RealSense ``.db3`` through librealsense's ``recorder`` (depth z16 with the
    ``depth_units`` option, colour rgb8, the recording's intrinsics on both stream profiles, frame numbers
    0..n-1, timestamps index/fps ms). ``pace``: push frames at the recording's fps, so that real-time playback
    takes the recording's duration (the file's clock is the wall clock of recording). Written to a temporary name
    and renamed, so nothing is left half-written."""
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
        rig = _SoftwareRig(rs, recording.intrinsics, fps, depth_units)
        with rig.record(tmp):
            t0 = time.perf_counter()
            for i, frame in enumerate(recording.frames()):
                if pace:
                    time.sleep(max(0.0, t0 + i / fps - time.perf_counter()))
                rig.push(frame, i, i * 1000.0 / fps)
    return path


class SoftwareCamera:
    """A stand-in RealSense camera: a ``software_device`` whose frames a thread pushes at ``fps`` (from a list of
    ``Frame``s, looped ``loops`` times), consumable with ``open_device_stream(cam.device)`` like a camera.
    Start the stream first, then ``cam.start()``; ``cam.done`` is set when every frame was pushed."""

    def __init__(self, frames: list[Frame], intrinsics: Intrinsics, fps: float = 30.0, loops: int = 1,
                 serial: str = "massviz-sw", **rig):
        self.rs = import_rs()
        self.frames, self.fps, self.loops = frames, float(fps), int(loops)
        self.rig = _SoftwareRig(self.rs, intrinsics, fps, serial=serial, **rig)
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
