"""One ``Recording`` protocol, one module per format: every format implements the protocol of
``massviz.core.recording_protocol``, the folder format's writer writes what its reader reads, ``read_depth`` reads one file
where the format allows, a .db3 is counted from its SQLite table (no playback), a recording is opened once per run,
and a CCM root without the asked view says so."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from fakes import copy_sample, run_cli, snapshot, visible_lines
from massviz.core.recording_protocol import Recording
from massviz.io.recording import open_recording

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "data_samples" / "cup_handover"


def test_folder_and_ccm_implement_the_protocol(shared_dir):
    for path in (SAMPLE, shared_dir / "ccm_real" / "view1" / "rgb" / "000000.mp4"):
        rec = open_recording(path)
        assert isinstance(rec, Recording), type(rec)
        assert rec.info().num_frames == rec.num_frames > 0
    assert not isinstance(object(), Recording)  # the check can fail


def test_protocol_is_pure_typing():
    """core/recording_protocol.py declares exactly what sinks may use (the names the sinks helper relies on)."""
    members = {"frames", "read_frame", "read_depth", "intrinsics", "info", "id", "path", "fps", "num_frames",
               "width", "height", "notes", "input_files", "video_file", "source_description", "kind", "config_id",
               "meta", "fingerprint"}
    declared = {n for n in dir(Recording) if not n.startswith("_")} | set(Recording.__annotations__)
    assert members <= declared, members - declared
    assert declared - members == set(), declared - members


def test_read_depth_reads_one_file(monkeypatch):
    import massviz.io.formats.folder as folder

    rec = open_recording(SAMPLE)
    reads = []
    real = folder.read_depth_png
    monkeypatch.setattr(folder, "read_depth_png", lambda p, *a, **kw: reads.append(Path(p).name) or real(p, *a, **kw))
    depth = rec.read_depth(rec.num_frames - 1)
    assert reads == [f"{rec.num_frames - 1:06d}.png"] and depth.dtype == np.uint16


def test_folder_writer_round_trip(tmp_path):
    """write_folder writes what open_folder reads (frames bit-exact, intrinsics, id, fps); the writer's own
    account of what it wrote equals the reader's (what live --save puts in the trace without re-opening)."""
    from massviz.io.atomic import atomic_dir
    from massviz.io.formats.folder import FolderFrameWriter, write_folder

    src = open_recording(SAMPLE)
    out = write_folder(src, tmp_path / "copy")
    back = open_recording(out)
    assert (back.num_frames, back.intrinsics, back.id, back.fps) == (src.num_frames, src.intrinsics, src.id, src.fps)
    for a, b in zip(src.frames(stride=7), back.frames(stride=7), strict=True):
        assert np.array_equal(a.rgb, b.rgb) and np.array_equal(a.depth, b.depth)

    target = tmp_path / "live"
    with atomic_dir(target) as tmp:
        writer = FolderFrameWriter(tmp, compression=1)
        for f in src.frames(indices=[0, 1, 2]):
            writer.write(f.index, f.rgb, f.depth)
        writer.finish(src.intrinsics, {"id": "live-1", "fps": 15.0, "live": {"source": "x"}})
    assert writer.written(target).info() == open_recording(target).info()


def test_estimate_opens_each_recording_once(tmp_path, monkeypatch):
    import massviz.io.recording as R

    calls = []
    real = R.open_recording
    monkeypatch.setattr(R, "open_recording", lambda p, **kw: calls.append(Path(p).name) or real(p, **kw))
    ds = tmp_path / "ds"
    for name in ("a", "b"):
        rec = copy_sample(ds / name)
        meta = json.loads((rec / "meta.json").read_text())
        (rec / "meta.json").write_text(json.dumps(dict(meta, id=name)))
    weights = _weights(tmp_path)
    code, _, err = run_cli(["estimate", ds, "--out", tmp_path / "p.csv", "--detector", "depth", "--weights", weights,
                            "--no-cache", "--quiet"])
    assert code == 0, err
    assert sorted(calls) == ["a", "b"], calls


def _weights(tmp_path: Path) -> Path:
    import torch

    from massviz.core.model import MassNet
    from massviz.io.checkpoint import published_ranges, save_checkpoint

    torch.manual_seed(0)
    return save_checkpoint(tmp_path / "w.torch", MassNet(), published_ranges("Encoder_pool_aug_158.torch"))


def test_ccm_root_without_the_view_says_so(shared_dir, tmp_path):
    """`estimate ROOT --view 2` on a CCM root with view1 and view3 only: "no view2 under ROOT", exit 2, nothing
    written (not an error about view1, not rows for view1/view3)."""
    root = tmp_path / "ccm"
    root.mkdir()
    (root / "view1").symlink_to(shared_dir / "ccm_real" / "view1", target_is_directory=True)
    (root / "view3").symlink_to(shared_dir / "ccm_real" / "view1", target_is_directory=True)
    out = tmp_path / "p.csv"
    before = snapshot(tmp_path)
    code, _, err = run_cli(["estimate", root, "--view", "2", "--out", out, "--detector", "depth", "--quiet"])
    lines = visible_lines(err)
    assert code == 2 and len(lines) == 1 and "Traceback" not in err, err
    assert f"no view2 under {root}" in lines[0], lines[0]
    assert not out.exists() and snapshot(tmp_path) == before
    # the view that exists is found as before
    from massviz.io.recording import find_recordings

    assert [p.name for p in find_recordings(root, view=3)] == ["000000.mp4"]


# ======================================================================================================= RealSense
@pytest.fixture(scope="module")
def cup_db3(tmp_path_factory):
    pytest.importorskip("pyrealsense2")
    from massviz.io.formats.realsense_write import write_realsense

    src = open_recording(SAMPLE)
    short = dataclasses.replace(src, num_frames=6, rgb_files=src.rgb_files[:6], depth_files=src.depth_files[:6])
    return write_realsense(short, tmp_path_factory.mktemp("rs") / "cup.db3")


def test_realsense_recording_is_its_own_format(cup_db3):
    from massviz.io.formats.folder import FrameFilesRecording

    rec = open_recording(cup_db3)
    assert isinstance(rec, Recording) and not isinstance(rec, FrameFilesRecording)
    fields = {f.name for f in dataclasses.fields(rec)}
    assert not fields & {"depth_files", "rgb_video", "rgb_files"}, fields
    assert rec.video_file() is None and rec.input_files() == [cup_db3]
    assert "cup.db3" in rec.source_description()["depth"]


def test_db3_is_counted_without_playback(cup_db3, monkeypatch):
    """Opening a .db3 reads its frame numbers and times from the SQLite table: no playback (FileFrames) at all."""
    import massviz.io.formats.realsense_file as F

    played = []

    class NoPlayback:
        def __init__(self, path):
            played.append(path)
            raise AssertionError("played back to count")

    counted = F.open_realsense(cup_db3)
    monkeypatch.setattr(F, "FileFrames", NoPlayback)
    rec = F.open_realsense(cup_db3)
    assert played == [] and rec.num_frames == 6 and rec.frame_numbers == list(range(6))
    assert np.allclose(rec.timestamps_ms, np.arange(6) * 1000 / 30)
    assert rec.meta == counted.meta


def test_db3_count_equals_playback(cup_db3, monkeypatch):
    """The SQLite count and a playback deliver the same pairs (the fallback used for .bag and unknown layouts)."""
    import massviz.io.formats.realsense_file as F

    fast = F.open_realsense(cup_db3)
    monkeypatch.setattr(F, "db3_frames", lambda path, fps: None)
    slow = F.open_realsense(cup_db3)
    assert (fast.frame_numbers, fast.num_frames) == (slow.frame_numbers, slow.num_frames)
    assert np.allclose(fast.timestamps_ms, slow.timestamps_ms, atol=1e-3)
    assert [f.index for f in fast.frames()] == list(range(6))


def test_realsense_read_depth_stops_at_the_frame_and_caches(cup_db3, monkeypatch):
    import massviz.io.formats.realsense_file as F

    rec = open_recording(cup_db3)
    delivered = []
    real = F.FileFrames

    class Counting(real):
        def __iter__(self):
            for item in super().__iter__():
                delivered.append(1)
                yield item

    monkeypatch.setattr(F, "FileFrames", Counting)
    d2 = rec.read_depth(2)
    assert len(delivered) <= 4  # frames 0..2 (and at most one more before the loop stops), not all 6
    assert np.array_equal(rec.read_depth(2), d2) and len(delivered) <= 4  # from the cache
    assert np.array_equal(d2, open_recording(SAMPLE).read_depth(2))
