"""RealSense framesets -> massviz ``Frame``s: ``pyrealsense2`` import, stream checks (``stream_info``: one colour and
one depth stream, depth scale, intrinsics and depth-to-colour extrinsics checked as untrusted data) and the decoder
(colour to RGB, depth aligned to colour unless registered, in millimetres). See ``massviz.io.formats.realsense_file``
for the file format, ``realsense_live`` for cameras."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from massviz.core.types import Frame, Intrinsics
from massviz.errors import MassvizError, RecordingError
from massviz.io.untrusted import MAX_ID_CHARS, MAX_IMAGE_SIDE, printable

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
    if not (math.isfinite(scale) and 0 < scale <= 1.0):
        raise RecordingError(f"depth scale {scale} is not a unit in (0, 1] m", source)
    ci, di = c.get_intrinsics(), d.get_intrinsics()
    _check_intrinsics(ci, "colour", source)
    _check_intrinsics(di, "depth", source)
    same = ((ci.width, ci.height, ci.fx, ci.fy, ci.ppx, ci.ppy, ci.model, list(ci.coeffs))
            == (di.width, di.height, di.fx, di.fy, di.ppx, di.ppy, di.model, list(di.coeffs)))
    try:
        ex = d.get_extrinsics_to(c)
    except RuntimeError:
        ex = None
    identity = False
    if ex is not None:
        rotation, translation = _check_extrinsics(ex, source)
        identity = (np.allclose(rotation, np.eye(3), atol=1e-7) and np.allclose(translation, 0.0, atol=1e-9))
    for key, name in (("name", "name"), ("serial", "serial_number"), ("firmware", "firmware_version")):
        try:
            if device.supports(getattr(rs.camera_info, name)):
                info[key] = printable(device.get_info(getattr(rs.camera_info, name)), max_chars=MAX_ID_CHARS)
        except (RuntimeError, AttributeError):
            pass
    return StreamInfo(intrinsics=_intrinsics_of(c), fps=float(c.fps()), depth_scale=scale, colour_format=fmt,
                      registered=same and identity, distortion=str(ci.model).replace("distortion.", ""),
                      device=info)


#: largest depth-to-colour translation accepted (metres): RealSense baselines are a few centimetres.
MAX_BASELINE_M = 0.5


def _check_intrinsics(i, which: str, source) -> None:
    """A stream's intrinsics from the file: fx, fy finite and > 0, the principal point finite and inside the
    image, the size positive (else ``RecordingError`` naming ``source``: no ZeroDivisionError, no alignment that
    silently maps every pixel away)."""
    w, h = int(i.width), int(i.height)
    if not (0 < w <= MAX_IMAGE_SIDE and 0 < h <= MAX_IMAGE_SIDE):
        raise RecordingError(f"{which} stream is {w}x{h} pixels (1..{MAX_IMAGE_SIDE} per side)", source)
    for key, value in (("fx", i.fx), ("fy", i.fy)):
        if not (math.isfinite(value) and value > 0):
            raise RecordingError(f"{which} intrinsics: {key} = {value} (must be finite and > 0)", source)
    for key, value, hi in (("ppx", i.ppx, w), ("ppy", i.ppy, h)):
        if not (math.isfinite(value) and 0 <= value <= hi):
            raise RecordingError(f"{which} intrinsics: principal point {key} = {value} is outside the image "
                                 f"(0..{hi})", source)


def _check_extrinsics(ex, source) -> tuple[np.ndarray, np.ndarray]:
    """Depth-to-colour extrinsics from the file: a finite rotation (orthonormal, determinant 1) and a finite
    translation of at most ``MAX_BASELINE_M`` (an all-zero or NaN matrix, or a camera metres away, is refused)."""
    rotation = np.asarray(ex.rotation, float).reshape(3, 3).T  # librealsense stores it column-major
    translation = np.asarray(ex.translation, float)
    if not (np.isfinite(rotation).all() and np.isfinite(translation).all()):
        raise RecordingError("depth-to-colour extrinsics are not finite (NaN or infinite values)", source)
    if not (np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-3) and abs(np.linalg.det(rotation) - 1) < 1e-3):
        raise RecordingError("depth-to-colour extrinsics: the rotation is not a rotation matrix (e.g. all zeros)",
                             source)
    if np.linalg.norm(translation) > MAX_BASELINE_M:
        raise RecordingError(f"depth-to-colour extrinsics: the depth camera is {np.linalg.norm(translation):.3g} m "
                             f"from the colour camera (at most {MAX_BASELINE_M} m: metres instead of millimetres?)",
                             source)
    return rotation, translation


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

