"""``--detector auto`` decides from local files only: Mask R-CNN weights given or cached, else the
NanoDet model given or cached, else depth; no connection is ever attempted, it returns at once, and it always says
which detector it chose and why, ``--quiet`` or not."""
from __future__ import annotations

import logging
import socket
import time
from pathlib import Path

import pytest

from massviz.detect import MASKRCNN_COCO_FILE, choose_auto, make_detector

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def no_network(monkeypatch, tmp_path):
    """Empty caches, and every socket connection recorded and refused."""
    attempts = []

    def refuse(self, address, *a, **k):
        attempts.append(address)
        raise OSError("network disabled by the test")

    monkeypatch.setattr(socket.socket, "connect", refuse)
    monkeypatch.setattr(socket.socket, "connect_ex", refuse)
    monkeypatch.setattr(socket, "create_connection", lambda address, *a, **k: refuse(None, address))
    monkeypatch.setattr(socket, "getaddrinfo", lambda host, *a, **k: refuse(None, host))
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    monkeypatch.setenv("MASSVIZ_CACHE_DIR", str(tmp_path / "cache"))
    return attempts


def said(caplog) -> list[str]:
    """The lines massviz logged (its ``logging`` records; the command line prints each on stderr), then forgotten."""
    lines = [r.getMessage() for r in caplog.records if r.name.startswith("massviz")]
    caplog.clear()
    return lines


def test_auto_offline_returns_at_once_without_connecting(no_network, caplog):
    caplog.set_level(logging.INFO, logger="massviz")
    t0 = time.perf_counter()
    det = make_detector("auto", 0.4, quiet=True)
    elapsed = time.perf_counter() - t0
    assert det.name == "depth"
    assert elapsed < 1.0, elapsed
    assert no_network == []  # no connection was even attempted
    err = said(caplog)
    assert len(err) == 1 and err[0].startswith("massviz: --detector auto: using depth: ") and "is cached" in err[0]


def test_auto_prefers_maskrcnn_then_nanodet_then_depth(no_network, tmp_path, shared_dir, caplog):
    caplog.set_level(logging.INFO, logger="massviz")
    onnx = shared_dir / "detectors" / "nanodet" / "object_detection_nanodet_2022nov.onnx"
    assert choose_auto()[0] == "depth"
    cache = tmp_path / "cache" / "weights"
    cache.mkdir(parents=True)
    (cache / onnx.name).write_bytes(onnx.read_bytes())
    name, why = choose_auto()
    assert name == "nanodet" and str(cache / onnx.name) in why
    det = make_detector("auto", 0.45, quiet=True)
    assert det.name == "nanodet" and det.threshold == 0.45
    assert any("using nanodet" in line for line in said(caplog))
    ckpt = tmp_path / "torch" / "hub" / "checkpoints"
    ckpt.mkdir(parents=True)
    (ckpt / MASKRCNN_COCO_FILE).write_bytes(b"x")
    assert choose_auto()[0] == "maskrcnn"
    # given weights decide by kind, whatever is cached
    assert choose_auto(onnx)[0] == "nanodet"
    assert choose_auto(tmp_path / "maskrcnn_state.pth")[0] == "maskrcnn"
    assert no_network == []


def test_maskrcnn_cache_file_name_is_torchvisions():
    from torchvision.models.detection import MaskRCNN_ResNet50_FPN_Weights

    assert MaskRCNN_ResNet50_FPN_Weights.COCO_V1.url.rsplit("/", 1)[1] == MASKRCNN_COCO_FILE


@pytest.mark.slow  # more than ~3 s on 2 idle cores (a massviz subprocess or a pipeline run)
def test_cli_quiet_still_says_which_detector_auto_chose(tmp_path, shared_dir):
    import os
    import subprocess
    import sys

    env = {**os.environ, "PYTHONPATH": str(ROOT), "TORCH_HOME": str(tmp_path / "torch"),
           "MASSVIZ_CACHE_DIR": str(tmp_path / "cache")}
    weights = shared_dir / "weights" / "corsmal_visual" / "Encoder_pool_aug_158.torch"
    out = tmp_path / "o.csv"
    r = subprocess.run([sys.executable, "-m", "massviz", "estimate", str(ROOT / "data_samples" / "cup_handover"),
                        "--out", str(out), "--quiet", "--no-cache", "--stride", "20", "--weights", str(weights)],
                       capture_output=True, text=True, env=env, timeout=600)
    assert r.returncode == 0, r.stderr
    assert "massviz: --detector auto: using depth: " in r.stderr


@pytest.mark.slow  # two massviz subprocesses
def test_auto_served_from_the_cache_still_says_which_detector_it_chose(tmp_path, shared_dir):
    """The second run finds every trace in the cache (the warm path: no detector is built) and says the same choice,
    marked as served from the cache."""
    import os
    import subprocess
    import sys

    env = {**os.environ, "PYTHONPATH": str(ROOT), "TORCH_HOME": str(tmp_path / "torch"),
           "MASSVIZ_CACHE_DIR": str(tmp_path / "cache")}
    weights = shared_dir / "weights" / "corsmal_visual" / "Encoder_pool_aug_158.torch"
    lines = []
    for _ in range(2):
        r = subprocess.run([sys.executable, "-m", "massviz", "estimate", str(ROOT / "data_samples" / "cup_handover"),
                            "--out", str(tmp_path / "o.csv"), "--quiet", "--stride", "20", "--weights", str(weights)],
                           capture_output=True, text=True, env=env, timeout=600)
        assert r.returncode == 0, r.stderr
        lines.append([ln for ln in r.stderr.splitlines() if ln.startswith("massviz: --detector auto: using ")])
    assert len(lines[0]) == 1 and lines[0][0].startswith("massviz: --detector auto: using depth: ")
    assert lines[1] == [lines[0][0] + " (traces from the cache)"]


def test_each_detector_has_its_default_cut_and_threshold_overrides_it(shared_dir):
    """Mask R-CNN keeps the paper's 0.4, NanoDet 0.3, depth 0.4 (README "Default score cuts"); --threshold overrides
    any of them, and the trace's estimate event says which cut it used and whether it was the default."""
    from massviz.app import PipelineOptions, build_pipeline
    from massviz.core.detector import DEFAULT_THRESHOLDS, PAPER_THRESHOLD, describe_cut
    from massviz.detect.depth import DepthDetector
    from massviz.detect.maskrcnn import MaskRCNNDetector
    from massviz.detect.nanodet import NanoDetDetector
    from massviz.io.recording import open_recording

    assert DEFAULT_THRESHOLDS == {"maskrcnn": PAPER_THRESHOLD, "nanodet": 0.3, "depth": 0.4} and PAPER_THRESHOLD == 0.4
    assert MaskRCNNDetector(pretrained=False).threshold == 0.4 and NanoDetDetector().threshold == 0.3
    assert DepthDetector().threshold == 0.4
    assert make_detector("depth").threshold == 0.4 and make_detector("depth", 0.55).threshold == 0.55
    assert PipelineOptions().threshold is None
    assert describe_cut("nanodet", 0.3) == "score > 0.3 (nanodet's default)"
    assert describe_cut("nanodet", 0.35) == "score > 0.35 (nanodet's default: 0.3)"
    weights = str(shared_dir / "weights" / "corsmal_visual" / "Encoder_pool_aug_158.torch")
    rec = open_recording(ROOT / "data_samples" / "box_handover")
    for threshold, note in ((None, "(depth's default)"), (0.45, "(depth's default: 0.4)")):
        pipeline = build_pipeline(PipelineOptions(detector="depth", threshold=threshold, stride=12, weights=weights,
                                                  no_cache=True, quiet=True))
        trace = pipeline.process(rec)
        assert trace.threshold == pipeline.threshold == (0.4 if threshold is None else threshold)
        estimate = [e.message for e in trace.events if e.kind == "estimate"]
        assert len(estimate) == 1 and estimate[0].endswith(f"(K=5, score > {trace.threshold:g} {note})"), estimate
        # re-selected (a cached trace served at another cut) the event follows
        again = trace.reselect(threshold=0.5)
        assert [e.message for e in again.events if e.kind == "estimate"][0].endswith("(depth's default: 0.4))")
