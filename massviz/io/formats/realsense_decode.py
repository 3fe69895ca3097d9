"""RealSense framesets -> massviz ``Frame``s: ``pyrealsense2`` import, stream checks (``stream_info``: one colour and
one depth stream, depth scale, intrinsics and depth-to-colour extrinsics checked as untrusted data) and the decoder
(colour to RGB, depth aligned to colour unless registered, in millimetres). See ``massviz.io.formats.realsense_file``
for the file format, ``realsense_live`` for cameras."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from massviz.core.types import Frame, Intrinsics
from massviz.errors import MassvizError, RecordingError

SUFFIXES = (".db3", ".bag")
INSTALL_HINT = "RealSense support needs pyrealsense2: pip install 'massviz[realsense]' (or pip install pyrealsense2)"


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

