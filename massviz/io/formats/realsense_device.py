"""Reading an ``rs.device`` (a file's playback device, a camera or a ``software_device``): ``DeviceReader`` pairs
colour and depth frames from sensor callbacks; ``FileFrames`` iterates every pair of a file in non-real-time
playback."""
from __future__ import annotations

import queue
import threading
from pathlib import Path

from massviz.core.types import Frame
from massviz.errors import RecordingError
from massviz.io.formats.realsense_decode import FrameDecoder, _reason, import_rs, stream_info

#: seconds without a frame, before the end of a file, after which its non-real-time playback counts as stalled.
FILE_TIMEOUT_S = 10.0


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


def playback_device(path: Path, real_time: bool):
    rs = import_rs()
    try:
        # an absolute path: librealsense is given the file's own name, nothing it could read as relative or a URI
        device = rs.context().load_device(str(Path(path).resolve()))
    except RuntimeError as err:
        raise RecordingError(f"not a readable RealSense recording ({_reason(err)})", path) from None
    playback = device.as_playback()
    playback.set_real_time(real_time)
    profiles = [p for s in device.query_sensors() for p in s.get_stream_profiles()]
    return rs, device, playback, profiles


class FileFrames:
    """Every colour+depth pair of a file, in order (non-real-time playback, bounded queue)."""

    def __init__(self, path: Path):
        rs, device, self.playback, profiles = playback_device(path, real_time=False)
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
                                         "the end of the file)", self.path) from None
                continue
            idle = 0.0
            yield item

    def close(self) -> None:
        self.closing = True
        self.reader.stop()

