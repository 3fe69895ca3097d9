"""massviz.views.rerun (through ``massviz.runners.trace_to_rerun.log_trace``, which gives it the measure stage's
clouds): log traces of tiny synthetic recordings to .rrd files and read the files back.

Recordings are drawn in tmp_path in massviz's folder layout (rgb/*.png or rgb.mp4, depth/*.png uint16 mm,
intrinsics.json, meta.json); traces come from ``massviz.core.pipeline.run`` with a fake detector (finds the red square)
and a fake model. The .rrd files are read back with Rerun's own reader (``rrd_contents``) and checked with
``rerun rrd verify``.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import rerun as rr
import rerun.blueprint as rrb

from massviz.core.patches import model_view
from massviz.core.pipeline import run
from massviz.core.types import COCO_KEEP, Detections, Intrinsics
from massviz.errors import MassvizError
from massviz.io.meta import write_intrinsics
from massviz.io.recording import open_recording
from massviz.measure3d.geometry import depth_to_points
from massviz.runners.trace_to_rerun import log_trace
from massviz.views import rerun as RR
from massviz.views.rerun import entities as E
from rrd_reader import rrd_contents, rrd_entities

W, H, N = 64, 48, 4
CONTRACT = {"/camera", "/camera/rgb", "/camera/depth", "/camera/detections", "/camera/masks", "/world",
            "/patches/0", "/predictions/patch_0", "/predictions/estimate", "/log"}
RERUN_CLI = Path(sys.executable).parent / "rerun"


@pytest.fixture(autouse=True)
def strict_rerun():
    """Rerun turns logging mistakes into warnings by default; make them errors here."""
    rr.set_strict_mode(True)
    yield
    rr.set_strict_mode(False)


# ------------------------------------------------------------------------------------------------ fakes, recordings
class SquareDetector:
    """Finds the red square drawn in each frame: one 'cup' with its exact box and mask."""

    name = "square"
    threshold = 0.5

    def settings(self) -> dict:
        return {}

    def detect(self, frame) -> Detections:
        red = (frame.rgb[..., 0] > 200) & (frame.rgb[..., 1] < 60) & (frame.rgb[..., 2] < 60)
        ys, xs = np.nonzero(red)
        if len(xs) == 0:
            return Detections()
        x1, y1, x2, y2 = xs.min(), ys.min(), xs.max() + 1, ys.max() + 1
        return Detections(frame=[frame.index], xyxy=[[x1, y1, x2, y2]], score=[0.9], class_id=[COCO_KEEP["cup"]],
                          masks=[red[y1:y2, x1:x2]])


class NothingDetector(SquareDetector):
    name = "nothing"

    def detect(self, frame) -> Detections:
        return Detections()


class FakeModel:
    weights_id = "fake0"

    def predict(self, patches, features) -> np.ndarray:
        return (100.0 + np.asarray(features)[:, 2] / 10.0).astype(np.float32)


def frames_rgbd(n: int = N):
    """n frames: a red square moving right over grey, at a depth that shrinks frame by frame (600, 550, ... mm)."""
    for i in range(n):
        rgb = np.full((H, W, 3), 90, np.uint8)
        x = 8 + 6 * i
        rgb[12:30, x:x + 16] = (255, 0, 0)
        depth = np.full((H, W), 1500, np.uint16)
        depth[12:30, x:x + 16] = 600 - 50 * i
        yield rgb, depth


def write_folder(root: Path, *, video: str | None = None, intrinsics: bool = True, mass: float | None = 42.0) -> Path:
    """A massviz recording folder: rgb/*.png (or rgb.mp4 written with fourcc ``video``) + depth/*.png."""
    (root / "depth").mkdir(parents=True)
    frames = list(frames_rgbd())
    if video is None:
        (root / "rgb").mkdir()
        for i, (rgb, _) in enumerate(frames):
            cv2.imwrite(str(root / "rgb" / f"{i:04d}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    else:
        writer = cv2.VideoWriter(str(root / "rgb.mp4"), cv2.VideoWriter_fourcc(*video), 10.0, (W, H))
        assert writer.isOpened(), f"cv2 cannot write {video} mp4 here"
        for rgb, _ in frames:
            writer.write(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        writer.release()
    for i, (_, depth) in enumerate(frames):
        cv2.imwrite(str(root / "depth" / f"{i:04d}.png"), depth)
    if intrinsics:
        write_intrinsics(Intrinsics(fx=60.0, fy=60.0, cx=W / 2, cy=H / 2, width=W, height=H), root / "intrinsics.json")
    if mass is not None:
        (root / "meta.json").write_text(json.dumps({"container": {"mass_g": mass}}))
    return root


def traced(root: Path, detector=None, k: int = 2):
    recording = open_recording(root)
    return run(recording, detector or SquareDetector(), FakeModel(), k=k), recording


def components(contents: dict, entity: str) -> set[str]:
    return contents.get(entity, set())


def text_logs(path: Path) -> str:
    """Every /log message in an .rrd, via ``rerun rrd print -vvv`` (the chunks' data as text)."""
    out = subprocess.run([str(RERUN_CLI), "rrd", "print", "-vvv", "--entity", "/log", str(path)],
                         capture_output=True, text=True, check=True)
    return out.stdout


# ------------------------------------------------------------------------------------------------------------ tests
def test_png_folder_logs_the_whole_entity_tree(tmp_path):
    trace, recording = traced(write_folder(tmp_path / "rec"))
    assert len(trace.selection) == 2 and trace.estimate > 0
    out = tmp_path / "out.rrd"
    stats = log_trace(trace, recording, rrd=out)
    assert out.is_file() and stats["rrd"] == str(out)
    assert stats["frames"] == N and stats["chosen"] == 2 and stats["rgb"] == "files" and stats["points"] == 0
    assert stats["log_seconds"] > 0
    assert not stats["notes"]

    entities = rrd_entities(out)
    assert CONTRACT <= entities, CONTRACT - entities
    assert {"/patches/1", "/predictions/patch_1", "/predictions/ground_truth", "/summary", "/timings", "/world",
            "/timings/log", "/timings/detect"} <= entities
    contents = rrd_contents(out)
    assert {"Pinhole:image_from_camera", "AnnotationContext:context"} <= components(contents, "/camera")
    assert "EncodedImage:blob" in components(contents, "/camera/rgb")
    assert "AssetVideo:blob" not in components(contents, "/camera/rgb")
    # the depth PNG goes in as its own bytes; Rerun back-projects it under the Pinhole (no /world/points)
    assert {"EncodedDepthImage:blob", "EncodedDepthImage:meter"} <= components(contents, "/camera/depth")
    assert "DepthImage:buffer" not in components(contents, "/camera/depth")
    assert {"Boxes2D:class_ids", "Boxes2D:labels"} <= components(contents, "/camera/detections")
    assert "SegmentationImage:buffer" in components(contents, "/camera/masks")
    assert "/world/points" not in contents
    assert {"EncodedImage:blob", "pred_g", "d_mm", "a", "b", "frame"} <= components(contents, "/patches/0")
    assert "Scalars:scalars" in components(contents, "/predictions/estimate")
    assert "TextLog:text" in components(contents, "/log")
    assert not list(tmp_path.glob(".out.rrd.*")), "temporary file left behind"


def test_rrd_is_valid_for_the_rerun_cli(tmp_path):
    trace, recording = traced(write_folder(tmp_path / "rec"))
    out = tmp_path / "out.rrd"
    log_trace(trace, recording, rrd=out)
    verify = subprocess.run([str(RERUN_CLI), "rrd", "verify", str(out)], capture_output=True, text=True)
    assert verify.returncode == 0, verify.stderr
    logs = text_logs(out)
    assert "chose patch 0" in logs and "estimate" in logs


def test_mp4_rerun_can_decode_is_one_video_asset(tmp_path):
    """VP9 in mp4: the file is logged once (static AssetVideo) and each processed frame references it."""
    trace, recording = traced(write_folder(tmp_path / "rec", video="vp09"))
    out = tmp_path / "out.rrd"
    stats = log_trace(trace, recording, rrd=out)
    assert stats["rgb"] == "asset"
    rgb = components(rrd_contents(out), "/camera/rgb")
    assert {"AssetVideo:blob", "VideoFrameReference:timestamp"} <= rgb
    assert "EncodedImage:blob" not in rgb
    assert CONTRACT <= rrd_entities(out)


def test_mp4v_video_falls_back_to_jpeg_frames_with_a_warning(tmp_path):
    """cv2's 'mp4v' (MPEG-4 Part 2, the CCM dataset's codec) is not decodable by Rerun's viewer."""
    trace, recording = traced(write_folder(tmp_path / "rec", video="mp4v"))
    out = tmp_path / "auto.rrd"
    stats = log_trace(trace, recording, rrd=out)
    assert stats["rgb"] == "images"
    assert any("cannot decode" in n for n in stats["notes"])
    rgb = components(rrd_contents(out), "/camera/rgb")
    assert "EncodedImage:blob" in rgb and "AssetVideo:blob" not in rgb
    assert "cannot decode" in text_logs(out)

    forced = tmp_path / "asset.rrd"
    stats = log_trace(trace, recording, rrd=forced, video="asset")
    assert stats["rgb"] == "asset"
    rgb = components(rrd_contents(forced), "/camera/rgb")
    assert {"AssetVideo:blob", "VideoFrameReference:timestamp"} <= rgb and "EncodedImage:blob" not in rgb


def test_without_intrinsics_no_pinhole_or_points_and_one_log_line(tmp_path):
    trace, recording = traced(write_folder(tmp_path / "rec", intrinsics=False))
    out = tmp_path / "out.rrd"
    stats = log_trace(trace, recording, rrd=out)
    contents = rrd_contents(out)
    assert "/world/points" not in contents
    assert not any(c.startswith("Pinhole:") for c in components(contents, "/camera"))
    assert {"/camera/rgb", "/camera/depth", "/camera/detections", "/patches/0"} <= set(contents)
    assert stats["points"] == 0
    assert sum("intrinsics" in n for n in stats["notes"]) == 1
    assert "no camera intrinsics" in text_logs(out)


def test_no_detections_still_logs_frames_and_says_not_estimated(tmp_path):
    trace, recording = traced(write_folder(tmp_path / "rec", mass=None), NothingDetector())
    assert trace.estimate == -1
    out = tmp_path / "out.rrd"
    stats = log_trace(trace, recording, rrd=out)
    assert stats["chosen"] == 0 and stats["frames"] == N
    entities = rrd_entities(out)
    assert {"/camera", "/camera/rgb", "/camera/depth", "/camera/detections", "/camera/masks", "/world",
            "/log", "/summary"} <= entities
    assert not any(e.startswith(("/patches", "/predictions")) for e in entities)
    assert "not estimated" in text_logs(out)
    assert "not estimated" in E.summary_markdown(trace)


def test_failure_half_way_leaves_no_file(tmp_path, monkeypatch):
    trace, recording = traced(write_folder(tmp_path / "rec"))
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    previous = out_dir / "old.rrd"
    previous.write_bytes(b"previous run")
    calls = []

    def broken_masks(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise RuntimeError("disk on fire")

    monkeypatch.setattr("massviz.views.rerun.trace_logger.log_masks", broken_masks)
    with pytest.raises(RuntimeError, match="disk on fire"):
        log_trace(trace, recording, rrd=out_dir / "new.rrd")
    with pytest.raises(RuntimeError, match="disk on fire"):
        calls.clear()
        log_trace(trace, recording, rrd=previous)
    assert sorted(p.name for p in out_dir.iterdir()) == ["old.rrd"]
    assert previous.read_bytes() == b"previous run"


def test_missing_output_folder_is_a_clear_error(tmp_path):
    trace, recording = traced(write_folder(tmp_path / "rec"))
    with pytest.raises(MassvizError, match="does not exist"):
        log_trace(trace, recording, rrd=tmp_path / "nope" / "out.rrd")


def test_two_recordings_in_one_process_and_a_caller_stream(tmp_path):
    trace, recording = traced(write_folder(tmp_path / "rec"))
    a = log_trace(trace, recording, rrd=tmp_path / "a.rrd")
    b = log_trace(trace, recording, rrd=tmp_path / "b.rrd")
    assert a["recording_id"] != b["recording_id"]
    assert rrd_entities(tmp_path / "a.rrd") == rrd_entities(tmp_path / "b.rrd")

    stream = rr.RecordingStream("massviz", recording_id="notebook-test")
    stream.save(tmp_path / "stream.rrd")
    stats = log_trace(trace, recording, stream=stream)
    stream.disconnect()
    assert stats["recording_id"] == "notebook-test"
    assert CONTRACT <= rrd_entities(tmp_path / "stream.rrd")


def test_output_arguments_are_checked(tmp_path):
    trace, recording = traced(write_folder(tmp_path / "rec"))
    with pytest.raises(ValueError, match="nothing to log to"):
        log_trace(trace, recording)
    with pytest.raises(ValueError, match="either stream"):
        log_trace(trace, recording, rrd=tmp_path / "x.rrd", stream=rr.RecordingStream("massviz"))


def test_trace_of_another_recording_is_refused(tmp_path):
    trace, _ = traced(write_folder(tmp_path / "rec"))
    other = tmp_path / "small"
    (other / "rgb").mkdir(parents=True)
    (other / "depth").mkdir()
    cv2.imwrite(str(other / "rgb" / "0.png"), np.zeros((10, 10, 3), np.uint8))
    cv2.imwrite(str(other / "depth" / "0.png"), np.zeros((10, 10), np.uint16))
    with pytest.raises(MassvizError, match="64x48"):
        log_trace(trace, open_recording(other), rrd=tmp_path / "x.rrd")


def test_depth_to_points_back_projects_in_metres():
    intr = Intrinsics(fx=100.0, fy=50.0, cx=2.0, cy=1.0, width=4, height=3)
    depth = np.zeros((3, 4), np.uint16)
    depth[1, 2] = 1000  # the principal point, 1 m
    depth[2, 3] = 2000  # one pixel right and down, 2 m
    rgb = np.zeros((3, 4, 3), np.uint8)
    rgb[2, 3] = (1, 2, 3)
    points, colours = depth_to_points(depth, intr, rgb, step=1)
    assert points.dtype == np.float32
    np.testing.assert_allclose(points, [[0, 0, 1], [2 / 100, 2 / 50, 2]], rtol=1e-6)
    np.testing.assert_array_equal(colours, [[0, 0, 0], [1, 2, 3]])
    points, colours = depth_to_points(depth, intr, None, step=2)
    assert colours is None and len(points) == 0  # (1,2) and (2,3) are not on the even grid


def test_point_cloud_is_capped(tmp_path):
    trace, recording = traced(write_folder(tmp_path / "rec"))
    stats = log_trace(trace, recording, rrd=tmp_path / "out.rrd", step=1, max_points=500, points=True)
    assert 0 < stats["points"] <= 500 * N


def test_points_option_logs_rgb_points_and_keeps_them_out_of_the_default(tmp_path):
    trace, recording = traced(write_folder(tmp_path / "rec"))
    stats = log_trace(trace, recording, rrd=tmp_path / "points.rrd", points=True)
    contents = rrd_contents(tmp_path / "points.rrd")
    assert stats["points"] > 0 and {"Points3D:positions", "Points3D:colors"} <= components(contents, "/world/points")
    assert "EncodedDepthImage:blob" in components(contents, "/camera/depth")
    default = tmp_path / "default.rrd"
    log_trace(trace, recording, rrd=default)
    assert "/world/points" not in rrd_contents(default)
    assert default.stat().st_size < (tmp_path / "points.rrd").stat().st_size


def test_depth_without_png_file_is_a_depth_image(tmp_path):
    stream = rr.RecordingStream("massviz-test")
    stream.save(tmp_path / "depth.rrd")
    depth = np.full((4, 5), 800, np.uint16)
    E.log_depth(stream, depth, None)  # e.g. a recording type whose depth is not a PNG file
    stream.disconnect()
    logged = components(rrd_contents(tmp_path / "depth.rrd"), "/camera/depth")
    assert {"DepthImage:buffer", "DepthImage:format", "DepthImage:meter"} <= logged
    assert not any(c.startswith("EncodedDepthImage:") for c in logged), logged


def test_3d_view_starts_oblique_looking_into_the_scene():
    depth = np.zeros((10, 10), np.uint16)
    depth[2:8, 2:8] = 1200
    assert E.scene_depth_m(depth) == pytest.approx(1.2)
    assert E.scene_depth_m(np.zeros((3, 3), np.uint16)) == 1.0
    bp = RR.default_blueprint(2, look_at_m=1.2)
    views = [v for v in _walk(bp.root_container) if isinstance(v, rrb.Spatial3DView)]
    assert len(views) == 1
    eye = views[0].properties["EyeControls3D"]
    # oblique like `massviz render`: tests/test_viewer_layout.py checks the angles
    assert eye.position.as_arrow_array().to_pylist()[0][2] < 0 < eye.position.as_arrow_array().to_pylist()[0][0]
    np.testing.assert_allclose(eye.look_target.as_arrow_array().to_pylist(), [[0, 0, 1.2]], rtol=1e-6)
    np.testing.assert_allclose(eye.eye_up.as_arrow_array().to_pylist(), [[0, -1, 0]])
    assert "/camera/depth" in str(views[0].contents) and "/camera/rgb" not in str(views[0].contents)
    with_points = [v for v in _walk(RR.default_blueprint(2, points=True).root_container)
                   if isinstance(v, rrb.Spatial3DView)][0]
    assert "/camera/depth" not in str(with_points.contents)


def _walk(container):
    for item in getattr(container, "contents", None) or []:
        if hasattr(item, "origin"):
            yield item
        else:
            yield from _walk(item)


def test_patch_is_logged_as_the_model_saw_it():
    patch = np.full((10, 30, 3), 200, np.uint8)
    image = model_view(patch)
    assert image.shape == (112, 112, 3) and image.dtype == np.uint8
    assert image[0, 56].max() == 0 and image[56, 56].min() > 150  # zero padding above, the patch in the middle


def _views(container) -> list:
    out = []
    for part in getattr(container, "contents", None) or []:
        out += [part] if hasattr(part, "class_identifier") else _views(part)
    return out


def test_blueprint_lays_out_every_view(tmp_path):
    views = [(type(v).__name__, str(v.origin)) for v in _views(RR.default_blueprint(2).root_container)]
    assert views.count(("Spatial2DView", "/camera")) == 2  # RGB + detections + masks, and depth
    assert {("Spatial2DView", "/camera"), ("Spatial3DView", "/"), ("Spatial2DView", "/patches/0"),
            ("Spatial2DView", "/patches/1"), ("TimeSeriesView", "/predictions"), ("TextLogView", "/log"),
            ("TextDocumentView", "/summary"), ("TextDocumentView", "/timings")} <= set(views)
    no_3d = {type(v).__name__ for v in _views(RR.default_blueprint(0, has_3d=False).root_container)}
    assert "Spatial3DView" not in no_3d

    # ... and it travels in the .rrd with the recording
    from rerun.chunk import RrdReader

    trace, recording = traced(write_folder(tmp_path / "rec"))
    log_trace(trace, recording, rrd=tmp_path / "out.rrd")
    reader = RrdReader(tmp_path / "out.rrd")
    (blueprint,) = reader.blueprints()
    schema = reader.store(store=blueprint).schema()
    view_entities = {e for e in schema.entity_paths() if e.startswith("/view/") and e.count("/") == 2}
    assert len(view_entities) == len(views)


def test_real_ccm_frames(shared_dir, tmp_path):
    """The two real CCM frames (mp4v video + calibration): Pinhole from the calibration, JPEG frames."""
    video = shared_dir / "ccm_real" / "view1" / "rgb" / "000000.mp4"
    recording = open_recording(video)

    class BoxDetector(SquareDetector):
        def detect(self, frame):
            box = [560, 250, 760, 520]
            mask = np.ones((box[3] - box[1], box[2] - box[0]), bool)
            return Detections(frame=[frame.index], xyxy=[box], score=[0.8], class_id=[COCO_KEEP["book"]],
                              masks=[mask])

    trace = run(recording, BoxDetector(), FakeModel(), k=1)
    out = tmp_path / "ccm.rrd"
    stats = log_trace(trace, recording, rrd=out)
    assert stats["rgb"] == "images" and stats["points"] <= 2 * E.MAX_POINTS
    contents = rrd_contents(out)
    assert CONTRACT <= set(contents)
    assert "Pinhole:image_from_camera" in components(contents, "/camera")


def test_inline_viewer_serves_its_code_locally_unless_the_user_chose(monkeypatch):
    monkeypatch.delitem(sys.modules, "rerun_notebook", raising=False)
    monkeypatch.delenv("RERUN_NOTEBOOK_ASSET", raising=False)
    assert RR.use_local_notebook_assets() == "serve-local"
    assert os.environ["RERUN_NOTEBOOK_ASSET"] == "serve-local"
    monkeypatch.setenv("RERUN_NOTEBOOK_ASSET", "inline")
    assert RR.use_local_notebook_assets() == "inline"
