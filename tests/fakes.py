"""Stand-ins the tests share: fake detectors and mass models, recordings and scenes written from numpy arrays, the
hostile-input fixtures' building blocks (a 3-frame copy of the cup sample, CCM layouts, CSVs, PNG headers) and the
in-process command runner.

Importable by any test module (``from fakes import ...``); fixtures built from them live in ``conftest.py``.
"""
from __future__ import annotations

import argparse
import io
import json
import os
import pickle
import shutil
import struct
import subprocess
import sys
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
import pytest

from massviz import cli
from massviz.core.types import COCO_KEEP, Detections

if TYPE_CHECKING:
    from massviz.core.types import Intrinsics
    from massviz.detect.maskrcnn import MaskRCNNDetector

ROOT = Path(__file__).resolve().parents[1]
#: the cup sample, source of the hostile-input copies and the live tests' played frames
SAMPLE = ROOT / "data_samples" / "cup_handover"


# ===================================================================================== fake detectors and models
class ListDetector:
    """Detections given per frame index: {frame: [(xyxy, score, mask-or-None), ...]}; counts its detect() calls."""

    name = "list"

    def __init__(self, per_frame: dict, threshold: float = 0.4, class_id: int = COCO_KEEP["cup"]):
        self.per_frame, self.threshold, self.class_id, self.calls = per_frame, float(threshold), class_id, 0

    def settings(self) -> dict:
        return {"per_frame": repr(sorted(self.per_frame.items(), key=lambda kv: kv[0]))}

    def detect(self, frame) -> Detections:
        self.calls += 1
        rows = [r for r in self.per_frame.get(frame.index, []) if r[1] > self.threshold]
        masks = [np.ones((b[3] - b[1], b[2] - b[0]), bool) if m is None else m for b, _, m in rows]
        return Detections(frame=[frame.index] * len(rows), xyxy=[r[0] for r in rows], score=[r[1] for r in rows],
                          class_id=[self.class_id] * len(rows), masks=masks)


class DistanceModel:
    """Predicts d / 10 grams (so every estimate can be computed by hand); records what it was given."""

    weights_id = "distance-model"

    def __init__(self):
        self.seen = []

    def predict(self, patches, features):
        feats = np.asarray(features, np.float64).reshape(-1, 3)
        self.seen.append((list(patches), feats))
        return (feats[:, 2] / 10).astype(np.float32)


# ================================================================================ recordings from numpy arrays
#: the size of ``rgb_frames``/``depth_frames`` (and so of the broken recordings of ``OPEN_ERRORS``)
W, H = 32, 24


def rgb_frames(n: int, width: int = W, height: int = H) -> list[np.ndarray]:
    """n distinct RGB frames: flat colour per frame plus a gradient, so frames and channels are told apart."""
    out = []
    for i in range(n):
        img = np.zeros((height, width, 3), np.uint8)
        img[..., 0] = (40 * i + 10) % 256
        img[..., 1] = np.arange(width, dtype=np.uint8)[None, :] * 3
        img[..., 2] = 200 - 20 * i
        out.append(img)
    return out


def depth_frames(n: int, width: int = W, height: int = H) -> list[np.ndarray]:
    """n 16-bit depth maps (mm) with values above 255, so an 8-bit read would show."""
    return [np.full((height, width), 1000 + 100 * i, np.uint16) + np.arange(width, dtype=np.uint16)[None, :]
            for i in range(n)]


def write_video(path: Path, rgbs, fps: float = 30.0) -> Path:
    h, w = rgbs[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
    assert writer.isOpened()
    for rgb in rgbs:
        writer.write(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    writer.release()
    return path


def write_recording(root: Path, rgbs, depths, *, video: bool = False, intrinsics: dict | None = None,
                    meta: dict | None = None) -> Path:
    """A massviz recording folder: rgb/NNNNNN.png (or rgb.mp4), depth/NNNNNN.png, intrinsics.json, meta.json."""
    root.mkdir(parents=True, exist_ok=True)
    if video:
        write_video(root / "rgb.mp4", rgbs)
    else:
        (root / "rgb").mkdir()
        for i, rgb in enumerate(rgbs):
            assert cv2.imwrite(str(root / "rgb" / f"{i:06d}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    (root / "depth").mkdir()
    for i, depth in enumerate(depths):
        assert cv2.imwrite(str(root / "depth" / f"{i:06d}.png"), depth)
    if intrinsics is not None:
        (root / "intrinsics.json").write_text(json.dumps(intrinsics))
    if meta is not None:
        (root / "meta.json").write_text(json.dumps(meta))
    return root


# ------------------------------------------------------------------------------------------------------- bad inputs
def _png(path: Path, array) -> None:
    assert cv2.imwrite(str(path), array)


def bad_missing_depth(root: Path) -> tuple[Path, Path, str]:
    write_recording(root, rgb_frames(3), [])
    (root / "depth").rmdir()
    return root, root, r"no depth \(no depth/ folder\): massviz estimates mass from RGB-D: .* 'massviz log REC"


def bad_fewer_depth(root: Path):
    write_recording(root, rgb_frames(3), depth_frames(2))
    return root, root / "depth", "2 depth frames for 3 RGB frames"


def bad_depth_8bit(root: Path):
    write_recording(root, rgb_frames(2), depth_frames(2))
    _png(root / "depth" / "000000.png", np.full((H, W), 200, np.uint8))
    return root, root / "depth" / "000000.png", "16-bit.*8-bit"


def bad_depth_size(root: Path):
    write_recording(root, rgb_frames(2), depth_frames(2, W // 2, H // 2))
    return root, root / "depth" / "000000.png", f"depth image declares {W // 2}x{H // 2} pixels but the recording's frames are {W}x{H}; not decoded"


def bad_depth_rgb(root: Path):
    write_recording(root, rgb_frames(2), depth_frames(2))
    _png(root / "depth" / "000000.png", np.zeros((H, W, 3), np.uint16) + 1000)
    return root, root / "depth" / "000000.png", "single-channel.*3 channels"


def bad_video_garbage(root: Path):
    write_recording(root, rgb_frames(1), depth_frames(2), video=True)
    (root / "rgb.mp4").write_bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    return root, root / "rgb.mp4", "cannot decode video"


def bad_video_empty(root: Path):
    write_recording(root, rgb_frames(1), depth_frames(2), video=True)
    (root / "rgb.mp4").write_bytes(b"")
    return root, root / "rgb.mp4", "empty"


def bad_empty_folder(root: Path):
    root.mkdir()
    return root, root, "empty folder"


def bad_missing_path(root: Path):
    return root, root, "no such file or directory"


def bad_intrinsics_json(root: Path):
    write_recording(root, rgb_frames(2), depth_frames(2))
    (root / "intrinsics.json").write_text('{"fx": 30, "fy": ')
    return root, root / "intrinsics.json", "not valid JSON"


def bad_intrinsics_keys(root: Path):
    write_recording(root, rgb_frames(2), depth_frames(2), intrinsics={"fx": 30.0, "fy": 31.0})
    return root, root / "intrinsics.json", "intrinsics need"


def bad_meta_json(root: Path):
    write_recording(root, rgb_frames(2), depth_frames(2))
    (root / "meta.json").write_text("[1, 2")
    return root, root / "meta.json", "not valid JSON"


def bad_meta_fps(root: Path):
    write_recording(root, rgb_frames(2), depth_frames(2))
    (root / "meta.json").write_text('{"fps": "thirty"}')
    return root, root / "meta.json", "'fps' must be a number"


#: each builder writes a broken recording under a root and returns (path to open, file the error must name, what).
OPEN_ERRORS = [bad_missing_depth, bad_fewer_depth, bad_depth_8bit, bad_depth_size, bad_depth_rgb, bad_video_garbage,
               bad_video_empty, bad_empty_folder, bad_missing_path, bad_intrinsics_json, bad_intrinsics_keys,
               bad_meta_json, bad_meta_fps]


def corrupt_middle_depth(root: Path):
    """Opens fine (only the first depth frame is checked up front); frame 2's depth is not a PNG."""
    write_recording(root, rgb_frames(4), depth_frames(4))
    (root / "depth" / "000002.png").write_bytes(b"\x89PNG\r\n\x1a\n truncated")
    return root, root / "depth" / "000002.png", "cannot read depth image"


# ================================================================================================ the scene
#: the scene's frame size and length
SCENE_W, SCENE_H, SCENE_N = 64, 48, 6


def scene():
    """Frames with a textured background; depth 2000 mm except a block per frame at a known distance."""
    rng = np.random.default_rng(3)
    rgbs = [rng.integers(0, 256, (SCENE_H, SCENE_W, 3), dtype=np.uint8) for _ in range(SCENE_N)]
    depths = []
    for i in range(SCENE_N):
        depth = np.full((SCENE_H, SCENE_W), 2000, np.uint16)
        depth[10:40, 5:30] = 1500 - 70 * i  # the detection at (5, 10, 30, 40) gets nearer every frame
        depth[5:25, 40:60] = 900 + 50 * i  # the one at (40, 5, 60, 25) gets further
        depths.append(depth)
    return rgbs, depths


# frame -> [(box, score, mask)]: two detections per frame with different scores, one frame with none
DETECTIONS = {i: [((5, 10, 30, 40), 0.5 + 0.08 * i, None), ((40, 5, 60, 25), 0.9 - 0.1 * i, None)]
              for i in range(SCENE_N) if i != 4}


# =============================================================================================== RealSense files
def need_realsense():
    try:
        import pyrealsense2 as rs
    except ImportError:
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail("pyrealsense2 is missing (the test extra installs it)")
        pytest.skip("pyrealsense2 is not installed")
    return rs


def write_streams(rs, path: Path, frames, intr: Intrinsics, streams=("depth", "color")) -> Path:
    """A .db3 with only some streams, written with pyrealsense2 directly (software_device + recorder)."""
    ri = rs.intrinsics()
    ri.width, ri.height, ri.fx, ri.fy, ri.ppx, ri.ppy = intr.width, intr.height, intr.fx, intr.fy, intr.cx, intr.cy
    ri.model, ri.coeffs = rs.distortion.none, [0.0] * 5
    sd = rs.software_device()
    sensors = {}
    for uid, (name, kind, fmt, bpp) in enumerate([("depth", rs.stream.depth, rs.format.z16, 2),
                                                  ("color", rs.stream.color, rs.format.rgb8, 3)]):
        if name not in streams:
            continue
        sensor = sd.add_sensor(name.title())
        vs = rs.video_stream()
        vs.type, vs.index, vs.uid, vs.width, vs.height, vs.fps, vs.bpp, vs.fmt, vs.intrinsics = \
            kind, 0, uid, intr.width, intr.height, 30, bpp, fmt, ri
        profile = sensor.add_video_stream(vs).as_video_stream_profile()
        if name == "depth":
            sensor.add_read_only_option(rs.option.depth_units, 0.001)
        sensors[name] = (sensor, profile, bpp)
    recorder = rs.recorder(str(path), sd)
    for sensor, profile, _ in sensors.values():
        sensor.open(profile)
        sensor.start(lambda f: None)
    for i, frame in enumerate(frames):
        for name, (sensor, profile, bpp) in sensors.items():
            data = np.ascontiguousarray(frame.depth if name == "depth" else frame.rgb)
            f = rs.software_video_frame()
            f.pixels, f.stride, f.bpp, f.timestamp, f.frame_number, f.profile = \
                data, intr.width * bpp, bpp, i * 1000 / 30, i, profile
            f.domain = rs.timestamp_domain.hardware_clock
            sensor.on_video_frame(f)
    for sensor, _, _ in sensors.values():
        sensor.stop()
        sensor.close()
    del recorder
    return path


# ----------------------------------------------------------------------------------------------------- bad input
def realsense_bad_files(rs, base: Path, cup_db3: Path, sample) -> dict[str, tuple[Path, str]]:
    data = cup_db3.read_bytes()
    frames = list(sample.frames(indices=[0, 1]))
    cases = {
        "truncated": (base / "truncated.db3", "not a readable RealSense recording"),
        "empty": (base / "empty.db3", "not a readable RealSense recording"),
        "not a bag": (base / "junk.bag", "not a readable RealSense recording"),
        "no depth": (base / "colour_only.db3", "no depth stream"),
        "no colour": (base / "depth_only.db3", "no colour stream"),
    }
    cases["truncated"][0].write_bytes(data[: len(data) * 2 // 3])
    cases["empty"][0].write_bytes(b"")
    cases["not a bag"][0].write_bytes(b"#ROSBAG V2.0\n" + bytes(range(256)) * 8)
    write_streams(rs, cases["no depth"][0], frames, sample.intrinsics, streams=("color",))
    write_streams(rs, cases["no colour"][0], frames, sample.intrinsics, streams=("depth",))
    return cases


# ======================================================================================= a rigged Mask R-CNN
CUP = COCO_KEEP["cup"]
BIAS = 3.9  # cup logit: some boxes score above 0.4, most below
PROPOSALS = (200, 100)


def rig(det: MaskRCNNDetector, width: int, height: int) -> MaskRCNNDetector:
    import torch

    m = rig_sizes(det, width, height).model
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():
        cls = m.roi_heads.box_predictor.cls_score
        cls.weight.mul_(0.01)
        cls.bias.zero_()
        cls.weight[CUP] = torch.randn(cls.weight.shape[1], generator=g) * 0.01
        cls.bias[CUP] = BIAS
        m.rpn.head.bbox_pred.weight.mul_(0.01)
        m.roi_heads.box_predictor.bbox_pred.weight.mul_(0.01)
    return det


def rig_sizes(det, width: int, height: int):
    """torchvision resizes to a third of the sample (160x90) and keeps fewer proposals: a cheap forward."""
    m = det.model
    m.transform.min_size, m.transform.max_size = (height // 3,), width // 3
    m.rpn._pre_nms_top_n["testing"], m.rpn._post_nms_top_n["testing"] = PROPOSALS
    return det


# ============================================================================================= live sessions
#: the frames of cup_handover the live tests play (the container comes nearest in 19..29; 12 frames keep them quick)
PLAYED = list(range(18, 30))


def flagged_session(played_db3, tmp_path) -> Path:
    """``massviz live --file played.db3 --rrd live.rrd`` (in-process) where the nearest chosen patch is flagged: a
    box on the table's front edge at ~0.8 m touching the bottom edge (frame 0 only; the ``border`` cue flags it
    whatever its track), then one at ~1.1 m on every frame (the container's track). Returns the .rrd."""
    from massviz.commands.live import run_session
    from massviz.io.formats.realsense_live import open_file_stream

    per_frame = {i: [((150, 100, 250, 200), 0.9, None)] for i in range(60)}
    per_frame[0] = [((100, 210, 200, 270), 0.9, None), *per_frame[0]]
    p = live_pipeline(ListDetector(per_frame), tmp_path)
    args = session_args(file=str(played_db3), rrd=str(tmp_path / "live.rrd"))
    assert run_session(args, p, open_file_stream(played_db3), "played") == 0
    return tmp_path / "live.rrd"


class FastModel:
    """d / 10 grams: a stand-in for the mass CNN where the test is about live mechanics, not the CNN."""

    weights_id = "fast-model"

    def predict(self, patches, features):
        return (np.asarray(features, np.float64).reshape(-1, 3)[:, 2] / 10).astype(np.float32)


def software_camera_stream(frames, intrinsics: Intrinsics, **camera):
    """A live stream from ``massviz.io.formats.realsense_live.SoftwareCamera(frames, intrinsics, **camera)`` (fps,
    loops) whose frames start to flow once the session listens (``stream.start``), as a camera's do."""
    from massviz.io.formats.realsense_live import SoftwareCamera, open_device_stream

    cam = SoftwareCamera(frames, intrinsics, **camera)
    stream = open_device_stream(cam.device, "software camera", on_stop=cam.stop)
    started = stream.start
    stream.start = lambda sink: (started(sink), cam.start())[0]
    return stream

def live_pipeline(detector, tmp_path: Path, model=None):
    from massviz.app import Pipeline, PipelineOptions
    from massviz.io.cache import TraceCache

    return Pipeline(PipelineOptions(detector="depth"), detector, model or FastModel(), TraceCache(tmp_path / "cache"))


def session_args(**kw) -> argparse.Namespace:
    base = dict(file=None, rrd=None, spawn=False, connect=None, serve_web=False, save=None, duration=None,
                quiet=True, web_port=9090, grpc_port=9876)
    return argparse.Namespace(**{**base, **kw})


# ================================================================================ hostile inputs: the building blocks
#: frames in a hostile case's copy of the cup sample
N_FRAMES = 3


# ============================================================================================================ inputs
def copy_sample(dst: Path, n: int = N_FRAMES, video: bool = False) -> Path:
    """The first ``n`` frames of the cup sample as a massviz recording folder (rgb/ or rgb.mp4, depth/, gt/,
    intrinsics.json, meta.json)."""
    dst.mkdir(parents=True)
    for sub in ("depth", "gt") + (() if video else ("rgb",)):
        (dst / sub).mkdir()
        for i in range(n):
            shutil.copy(SAMPLE / sub / f"{i:06d}.png", dst / sub / f"{i:06d}.png")
    if video:
        write_mp4(dst / "rgb.mp4", [cv2.imread(str(SAMPLE / "rgb" / f"{i:06d}.png")) for i in range(n)])
    shutil.copy(SAMPLE / "intrinsics.json", dst / "intrinsics.json")
    meta = json.loads((SAMPLE / "meta.json").read_text())
    meta["frames"] = meta["frames"][:n]
    (dst / "meta.json").write_text(json.dumps(meta))
    return dst


def write_mp4(path: Path, bgrs, fps: float = 30.0) -> Path:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (bgrs[0].shape[1], bgrs[0].shape[0]))
    for bgr in bgrs:
        writer.write(bgr)
    writer.release()
    return path


def _atoms(data: bytes, start: int = 0, end: int | None = None):
    end = len(data) if end is None else end
    i = start
    while i + 8 <= end:
        size, kind = struct.unpack(">I4s", data[i:i + 8])
        hdr = 8
        if size == 1:
            size, hdr = struct.unpack(">Q", data[i + 8:i + 16])[0], 16
        elif size == 0:
            size = end - i
        yield kind, i, size, hdr
        i += size


def _shift_chunk_offsets(moov: bytearray, delta: int, start: int = 8, end: int | None = None) -> None:
    for kind, i, size, hdr in list(_atoms(moov, start, len(moov) if end is None else end)):
        if kind in (b"trak", b"mdia", b"minf", b"stbl"):
            _shift_chunk_offsets(moov, delta, i + hdr, i + size)
        elif kind in (b"stco", b"co64"):
            width = 4 if kind == b"stco" else 8
            fmt = ">I" if width == 4 else ">Q"
            for j in range(struct.unpack(">I", moov[i + 12:i + 16])[0]):
                p = i + 16 + width * j
                moov[p:p + width] = struct.pack(fmt, struct.unpack(fmt, moov[p:p + width])[0] + delta)


def faststart(data: bytes) -> bytes:
    """The same mp4 with its index (moov) before the frames (mdat), as ``ffmpeg -movflags +faststart`` writes it:
    cut in half, such a file still opens and promises every frame."""
    top = list(_atoms(data))
    at, size = next((i, s) for k, i, s, _ in top if k == b"moov")
    mdat = next(i for k, i, _, _ in top if k == b"mdat")
    moov = bytearray(data[at:at + size])
    _shift_chunk_offsets(moov, len(moov))
    head = b"".join(data[i:i + s] for k, i, s, _ in top if i < mdat)
    rest = b"".join(data[i:i + s] for k, i, s, _ in top if i >= mdat and k != b"moov")
    return head + bytes(moov) + rest


def png_header_only(width: int, height: int) -> bytes:
    """A 60-byte PNG whose header declares width x height pixels (a decoder would allocate them first)."""
    def chunk(kind, body):
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 16, 0, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(b"")) + chunk(b"IEND", b""))


def cup_box(frame: int = 1) -> list[int]:
    gt = cv2.imread(str(SAMPLE / "gt" / f"{frame:06d}.png"), cv2.IMREAD_UNCHANGED)
    ys, xs = np.nonzero(gt == 1)
    return [int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1]


class Evil:
    """Unpickling this runs ``touch CANARY``."""

    def __init__(self, canary: Path, how: str = "os"):
        self.canary, self.how = canary, how

    def __reduce__(self):
        if self.how == "subprocess":
            return subprocess.call, (["touch", str(self.canary)],)
        if self.how == "eval":
            return eval, (f"open({str(self.canary)!r}, 'w').close()",)
        return os.system, (f"touch {self.canary}",)


def calib(fx: float = 346.4, fy: float = 346.3, cx: float = 243.7, cy: float = 135.4) -> list:
    """The structure of a CCM calibration pickle (shared/ccm_real/README.md) with the sample's intrinsics."""
    k = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=np.float64)
    ext = {"rvec": np.eye(3), "tvec": np.zeros((3, 1)), "projMatrix": np.zeros((3, 4))}
    return [{"rgb": k, "ir1": k.copy(), "ir2": k.copy()}, {n: dict(ext) for n in ("rgb", "ir1", "ir2")},
            np.array([487, 341]), np.array([748, 338])]


def make_ccm(root: Path, calib_bytes: bytes | None = None) -> Path:
    """ROOT/view1/{rgb/000000.mp4, depth/000000/*.png, calib/000000.pickle} from the sample; returns the video."""
    view = root / "view1"
    for sub in ("rgb", "depth/000000", "calib"):
        (view / sub).mkdir(parents=True)
    write_mp4(view / "rgb" / "000000.mp4", [cv2.imread(str(SAMPLE / "rgb" / f"{i:06d}.png")) for i in range(2)])
    for i in range(2):
        shutil.copy(SAMPLE / "depth" / f"{i:06d}.png", view / "depth" / "000000" / f"{i:04d}.png")
    data = pickle.dumps(calib(), protocol=0) if calib_bytes is None else calib_bytes
    (view / "calib" / "000000.pickle").write_bytes(data)
    return view / "rgb" / "000000.mp4"


@dataclass
class Base:
    root: Path
    weights: Path
    replay: Path
    box: list[int]
    trace_npz: Path


def make_base(root: Path) -> Base:
    """The ``base`` fixture's content, written in ``root``."""
    import torch

    from massviz.core.model import MassNet
    from massviz.io.checkpoint import load_checkpoint, published_ranges, save_checkpoint

    torch.manual_seed(0)
    weights = save_checkpoint(root / "w.torch", MassNet(), published_ranges("Encoder_pool_aug_158.torch"))
    box = cup_box(1)
    replay = root / "replay.json"
    replay.write_text(json.dumps({"detections": [{"frame": 1, "box": box, "score": 0.9, "class": "cup"}]}))
    from massviz.core.pipeline import run
    from massviz.detect.saved import ReplayDetector
    from massviz.io.recording import open_recording
    from massviz.io.trace_file import save_trace

    trace = run(open_recording(copy_sample(root / "rec")), ReplayDetector(replay),
                load_checkpoint(weights), k=5)
    assert len(trace.detections) == 1 and trace.estimate >= 0
    return Base(root, weights, replay, box, save_trace(trace, root / "trace.npz"))


# --- annotation and prediction CSVs -----------------------------------------------------------------------------
ANN_HEADER = "id,container id,width at the top,width at the bottom,height,depth,container capacity,container mass"
ANN_ROWS = ["0,1,92,60,110,-1,480,9", "1,4,80,60,150,-1,300,120", "2,7,140,70,200,100,-1,30"]
PRED_HEADER = "Configuration ID,Container mass"
PRED_ROWS = ["0,10", "1,100", "2,31"]


def csv_text(header: str, rows: list[str], row: int | None = None, column: str | None = None, value: str = "") -> str:
    names = header.split(",")
    rows = [r.split(",") for r in rows]
    if row is not None:
        rows[row][names.index(column)] = value
    return "\n".join([header, *(",".join(r) for r in rows)]) + "\n"


# ============================================================================================================ runner
def visible_lines(stderr: str) -> list[str]:
    lines = [line.split("\r")[-1] for line in stderr.split("\n")]
    return [line for line in lines if line.strip()]


def snapshot(folder: Path, skip: Path | None = None) -> dict[str, tuple[int, int]]:
    """Every file (and folder) under ``folder`` with its size and modification time, ``skip`` excluded."""
    out = {}
    for p in sorted(folder.rglob("*")):
        if skip is not None and (p == skip or skip in p.parents):
            continue
        st = p.lstat()
        out[str(p.relative_to(folder))] = (st.st_size if p.is_file() else -1, st.st_mtime_ns)
    return out


def run_cli(argv) -> tuple[int, str, str]:
    """``massviz.cli.main`` in-process; (exit code, stdout, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    real = sys.stdout, sys.stderr
    sys.stdout, sys.stderr = out, err
    try:
        code = cli.main([str(a) for a in argv])
    except SystemExit as exit_:  # argparse
        code = exit_.code
    finally:
        sys.stdout, sys.stderr = real
    return code, out.getvalue(), err.getvalue()


def run_cli_as_user(*args) -> subprocess.CompletedProcess:
    """``massviz ARGS`` in-process (:func:`run_cli`) without the caller's ``MASSVIZ_DEBUG`` and ``MASSVIZ_WEIGHTS``
    (as ``support.run_massviz`` runs it in a subprocess), as a ``CompletedProcess``: returncode, stdout, stderr."""
    saved = {k: os.environ.pop(k) for k in ("MASSVIZ_DEBUG", "MASSVIZ_WEIGHTS") if k in os.environ}
    try:
        code, out, err = run_cli(args)
    finally:
        os.environ.update(saved)
    return subprocess.CompletedProcess(["massviz", *map(str, args)], code, out, err)


def make_patch_set(base: Base, root: Path) -> Path:
    """Patches extracted (``massviz extract``, in-process) from four copies of the cup sample with distinct ids and
    masses, their d, a, b spread (min-max ranges need a span): ROOT/patches."""
    recs = []
    for i in range(4):
        rec = copy_sample(root / f"rec{i}", n=3)
        meta = json.loads((rec / "meta.json").read_text())
        meta["id"] = f"rec{i}"
        meta.setdefault("container", {})["mass_g"] = 10.0 + 5 * i
        (rec / "meta.json").write_text(json.dumps(meta))
        recs.append(rec)
    out = root / "patches"
    code = cli.main(["extract", *map(str, recs), "--out", str(out), "--detector", "replay", "--replay",
                     str(base.replay), "--weights", str(base.weights), "--cache", str(root / "cache"), "--quiet"])
    assert code == 0 and (out / "index.csv").is_file()
    import pandas as pd

    index = pd.read_csv(out / "index.csv")  # copies of one sample: spread d, a, b (min-max ranges need a span)
    for col, step in (("d", 37.0), ("a", 0.01), ("b", 0.01)):
        index[col] = index[col] + step * np.arange(len(index))
    index.to_csv(out / "index.csv", index=False)
    return out
