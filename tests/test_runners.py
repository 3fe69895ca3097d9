"""Dataset runners (``massviz.runners``): ``--engine ray`` gives the same bytes as ``--engine local``, survives a
worker process that dies, reports a corrupt recording and leaves nothing half-written when interrupted.

Ray is started once for the module (2 CPUs, no dashboard, servers on 127.0.0.1); the CLI runs in this process and
finds it initialised, so each run only creates its actors (a subprocess joins it by address for the SIGINT test).
Datasets are small: the three samples (every 4th frame), and 52 recordings of 2 frames made from them in a
fixture (the byte-identical tests run all 52; the fault and timing tests the first ``N_SMALL``).
"""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from massviz.cli import main
from massviz.runners.dataset import EXIT_SOME_FAILED, FAULT_ENV, REPORT_FORMAT
from support import end_processes, no_other_ray, started_since

SAMPLES = ("box_handover", "cup_handover", "glass_handover")
N_SYNTHETIC = 52
N_SMALL = 12  # the fault, interrupt and execution-time tests: enough recordings for both workers, fewer runs
FRAMES = 2


@pytest.fixture(scope="module")
def ray_address(tmp_path_factory):
    """A local Ray for the whole module: 2 CPUs, no dashboard, bound to 127.0.0.1 (``RAY_ENABLE_WINDOWS_OR_OSX_
    CLUSTER=0`` before the import, as ``massviz.runners.ray_engine`` does for the instances it starts)."""
    from massviz.runners.ray_engine import KEEP_ENV, LOCAL_ONLY_ENV

    os.environ.setdefault(LOCAL_ONLY_ENV, "0")
    os.environ[KEEP_ENV] = "1"  # consecutive runs with the same options reuse their actors (test time)
    if os.environ.get("CI", "").lower() == "true":
        import ray  # the test extra installs it: missing is a failure in CI
    else:
        ray = pytest.importorskip("ray")
    with no_other_ray(tmp_path_factory):  # test_new_user's "auto" address must not find this cluster
        yield from _local_ray(ray)


def _local_ray(ray):
    from massviz.runners.ray_engine import KEEP_ENV

    for attempt in (1, 2):  # Ray gives its raylet a hard-coded 30 s to register: a loaded machine may need two tries
        before = {p.pid for p in started_since(set())}
        try:
            ray.init(num_cpus=2, include_dashboard=False, logging_level="WARNING")
            break
        except Exception:  # noqa: BLE001 - "The current node timed out during startup"
            ray.shutdown()
            end_processes(started_since(before))  # a failed start leaves gcs_server, monitors, a dashboard running
            if attempt == 2:
                raise
    try:
        yield ray.get_runtime_context().gcs_address
    finally:
        from massviz.runners.ray_engine import release_pools

        release_pools()
        os.environ.pop(KEEP_ENV, None)
        ray.shutdown()


@pytest.fixture(scope="module")
def synthetic(samples_dir, tmp_path_factory) -> Path:
    """52 recordings of 2 frames each, cut from the samples at different offsets (ids syn_000 ...)."""
    root = tmp_path_factory.mktemp("synthetic")
    for i in range(N_SYNTHETIC):
        src = samples_dir / SAMPLES[i % 3]
        offset = (i // 3) % 12 * FRAMES
        dst = root / f"syn_{i:03d}"
        for sub in ("rgb", "depth"):
            (dst / sub).mkdir(parents=True)
            for j in range(FRAMES):
                shutil.copyfile(src / sub / f"{offset + j:06d}.png", dst / sub / f"{j:06d}.png")
        shutil.copyfile(src / "intrinsics.json", dst / "intrinsics.json")
        meta = json.loads((src / "meta.json").read_text())
        meta["id"] = dst.name
        (dst / "meta.json").write_text(json.dumps(meta))
    return root


@pytest.fixture(scope="module")
def replay_json(tmp_path_factory) -> Path:
    """Detections for frames 0-1 (whole-box masks): every recording's d comes from its own depth."""
    path = tmp_path_factory.mktemp("replay") / "detections.json"
    dets = [{"frame": 0, "box": [200, 60, 300, 200], "score": 0.9, "class": "cup"},
            {"frame": 1, "box": [180, 50, 290, 190], "score": 0.8, "class": "cup"},
            {"frame": 1, "box": [20, 20, 120, 120], "score": 0.3, "class": "bottle"},
            {"frame": 0, "box": [210, 70, 320, 210], "score": 0.7, "class": "wine glass"}]
    path.write_text(json.dumps({"detections": dets}))
    return path


def first(synthetic: Path, root: Path, n: int = N_SMALL) -> Path:
    """A dataset of the first ``n`` synthetic recordings (linked)."""
    root.mkdir()
    for i in range(n):
        (root / f"syn_{i:03d}").symlink_to(synthetic / f"syn_{i:03d}")
    return root


def run(*argv) -> int:
    return main([str(a) for a in argv])


def detector_args(detector: str, replay_json: Path) -> list:
    return ["--detector", detector] + (["--replay", replay_json] if detector == "replay" else [])


def both_engines(tmp_path, dataset, weights, args, ray_address, name="run"):
    """estimate (fresh caches, --exec-time none) then extract (from each engine's own cache) on both engines:
    {engine: (csv bytes, index bytes, {image name: bytes})}."""
    out = {}
    for engine in ("local", "ray"):
        d = tmp_path / f"{name}-{engine}"
        d.mkdir()
        common = [dataset, "--weights", weights, "--cache", d / "cache", "--quiet", *args, "--engine", engine]
        assert run("estimate", *common, "--exec-time", "none", "--out", d / "pred.csv") == 0
        assert run("extract", *common, "--out", d / "patches") == 0
        images = {p.name: p.read_bytes() for p in sorted((d / "patches" / "images").iterdir())}
        out[engine] = ((d / "pred.csv").read_bytes(), (d / "patches" / "index.csv").read_bytes(), images)
    return out


def assert_same(out):
    (lc, li, limg), (rc, ri, rimg) = out["local"], out["ray"]
    assert lc == rc
    assert li == ri
    assert limg == rimg
    assert len(lc.splitlines()) > 1 and len(li.splitlines()) > 1 and limg


@pytest.mark.parametrize("detector", ["depth", "replay"])
def test_samples_byte_identical(detector, samples_dir, weights, replay_json, ray_address, tmp_path):
    args = [*detector_args(detector, replay_json), "--stride", "4"]
    out = both_engines(tmp_path, samples_dir, weights, args, ray_address)
    assert_same(out)
    rows = out["local"][0].decode().splitlines()[1:]
    assert [r.split(",")[0] for r in rows] == list(SAMPLES)  # input order
    assert all(r.split(",")[2] != "-1" for r in rows)  # every sample estimated: the comparison is not of -1s


@pytest.mark.parametrize("detector", ["depth", "replay"])
def test_synthetic_dataset_byte_identical(detector, synthetic, weights, replay_json, ray_address, tmp_path):
    stride = ["--stride", "2"] if detector == "depth" else []  # one frame each: the detector is the costly part
    out = both_engines(tmp_path, synthetic, weights, [*detector_args(detector, replay_json), *stride], ray_address)
    assert_same(out)
    rows = out["local"][0].decode().splitlines()[1:]
    assert [r.split(",")[0] for r in rows] == [f"syn_{i:03d}" for i in range(N_SYNTHETIC)]
    assert len({r.split(",")[2] for r in rows}) > 3  # the recordings differ


def test_measured_execution_time_comes_from_the_trace(synthetic, weights, replay_json, ray_address, tmp_path):
    """With the default --exec-time measured, a run on either engine over traces the other engine made writes the
    same bytes: 'Execution time' is the time recorded in the trace, not this run's."""
    args = [first(synthetic, tmp_path / "data"), "--weights", weights, "--cache", tmp_path / "cache", "--quiet",
            *detector_args("replay", replay_json)]
    assert run("estimate", *args, "--engine", "ray", "--out", tmp_path / "ray.csv") == 0
    assert run("estimate", *args, "--out", tmp_path / "local.csv") == 0
    assert (tmp_path / "ray.csv").read_bytes() == (tmp_path / "local.csv").read_bytes()
    times = [float(r.split(",")[-1]) for r in (tmp_path / "ray.csv").read_text().splitlines()[1:]]
    assert all(t > 0 for t in times)


@pytest.fixture(scope="module")
def rigged_maskrcnn(tmp_path_factory) -> Path:
    """A random-weight Mask R-CNN state_dict whose classifier favours 'cup' (some boxes above 0.4)."""
    import torch

    from massviz.core.types import COCO_KEEP
    from massviz.detect.maskrcnn import build_model

    torch.manual_seed(0)
    model = build_model(0.4, pretrained=False)
    with torch.no_grad():
        cls = model.roi_heads.box_predictor.cls_score
        rows = torch.zeros(cls.weight.shape[0], 1)
        rows[COCO_KEEP["cup"]] = 1
        cls.weight.mul_(rows)
        cls.bias.zero_()
        cls.bias[COCO_KEEP["cup"]] = 4.0
    path = tmp_path_factory.mktemp("maskrcnn") / "rigged.pth"
    torch.save(model.state_dict(), path)
    return path


def test_maskrcnn_byte_identical(samples_dir, weights, rigged_maskrcnn, ray_address, tmp_path):
    """The paper's detector (random weights, 1 frame of 1 sample: a Mask R-CNN frame on one CPU thread is most of
    this test's time). Its floats depend on torch's thread count, so the local run uses --threads 1 like each of the
    2 Ray workers."""
    data = tmp_path / "one"
    data.mkdir()
    for name in SAMPLES[1:2]:
        (data / name).symlink_to(samples_dir / name)
    args = ["--detector", "maskrcnn", "--detector-weights", rigged_maskrcnn, "--stride", "36", "--threads", "1"]
    out = both_engines(tmp_path, data, weights, args, ray_address)
    assert_same(out)


def report(path: Path) -> dict:
    doc = json.loads(path.read_text())
    assert doc["format"] == REPORT_FORMAT
    return doc


def test_worker_killed_mid_run(synthetic, weights, replay_json, ray_address, tmp_path, monkeypatch):
    """The worker process that gets syn_010 dies (os._exit) after reading a frame; Ray restarts it and retries the
    recording; every row equals the local run's."""
    args = [first(synthetic, tmp_path / "data"), "--weights", weights, "--quiet", "--exec-time", "none",
            *detector_args("replay", replay_json)]
    assert run("estimate", *args, "--cache", tmp_path / "c-local", "--out", tmp_path / "local.csv") == 0
    monkeypatch.setenv(FAULT_ENV, "syn_010")
    assert run("estimate", *args, "--cache", tmp_path / "c-ray", "--engine", "ray", "--report", tmp_path / "r.json",
               "--out", tmp_path / "ray.csv") == 0
    assert (tmp_path / "ray.csv").read_bytes() == (tmp_path / "local.csv").read_bytes()
    doc = report(tmp_path / "r.json")
    assert doc["counts"] == {"done": N_SMALL, "cached": 0, "failed": 0, "not run": 0}
    workers = [e["worker"] for e in doc["recordings"]]
    killed = workers[10]
    assert len(set(workers)) == 3  # two actors, one of them restarted once (a new process)
    assert workers.count(killed) < N_SMALL


def corrupt_dataset(synthetic: Path, root: Path) -> Path:
    for name in ("syn_000", "syn_001", "syn_002", "syn_003", "syn_004", "syn_005"):
        shutil.copytree(synthetic / name, root / name)
    (root / "syn_003" / "depth" / "000001.png").write_bytes(b"not a png")  # unreadable mid-way (frame 1)
    return root


@pytest.mark.parametrize("engine", ["local", "ray"])
def test_corrupt_recording_in_a_dataset(engine, synthetic, weights, replay_json, ray_address, tmp_path):
    data = corrupt_dataset(synthetic, tmp_path / "data")
    clean = first(synthetic, tmp_path / "clean", 6)  # the same six recordings, none corrupt
    args = ["--weights", weights, "--quiet", "--exec-time", "none", *detector_args("replay", replay_json)]
    assert run("estimate", clean, *args, "--cache", tmp_path / "c0", "--out", tmp_path / "clean.csv") == 0
    rc = run("estimate", data, *args, "--cache", tmp_path / "c1", "--engine", engine, "--report", tmp_path / "r.json",
             "--out", tmp_path / "pred.csv")
    assert rc == EXIT_SOME_FAILED
    got = (tmp_path / "pred.csv").read_text().splitlines()
    want = (tmp_path / "clean.csv").read_text().splitlines()
    assert len(got) == len(want) == 7
    assert [g for i, g in enumerate(got) if i != 4] == [w for i, w in enumerate(want) if i != 4]
    assert got[4].split(",")[0] == "syn_003"
    assert set(got[4].split(",")[1:]) == {"-1"}  # not estimated, nothing measured
    doc = report(tmp_path / "r.json")
    bad = [e for e in doc["recordings"] if e["status"] == "failed"]
    assert [e["id"] for e in bad] == ["syn_003"]
    assert "000001.png" in bad[0]["error"] and "\n" not in bad[0]["error"]
    assert doc["counts"]["failed"] == 1 and doc["counts"]["done"] == 5


def test_on_error_stop_writes_nothing(synthetic, weights, replay_json, tmp_path, capsys):
    data = corrupt_dataset(synthetic, tmp_path / "data")
    rc = run("estimate", data, "--weights", weights, "--quiet", *detector_args("replay", replay_json),
             "--cache", tmp_path / "c", "--on-error", "stop", "--report", tmp_path / "r.json",
             "--out", tmp_path / "pred.csv")
    assert rc == 2
    assert not (tmp_path / "pred.csv").exists()
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("massviz estimate: error: ") and "syn_003" in err[-1] and "000001.png" in err[-1]
    doc = report(tmp_path / "r.json")
    assert [e["status"] for e in doc["recordings"]] == ["done"] * 3 + ["failed", "not run", "not run"]


def test_sigint_leaves_no_csv_and_the_next_run_resumes(synthetic, samples_dir, weights, ray_address, tmp_path):
    """Ctrl-C on a ray run (a driver process joined to the module's Ray): exit 130, no CSV (nor temporary file);
    the next run finds every trace finished before the interrupt in the cache."""
    from massviz.runners.ray_engine import KEEP_ENV, release_pools

    release_pools()  # the other driver needs the CPUs this process's kept actors hold
    # the 2-frame recordings, then three whole samples (36 frames each, last in input order): the run is still busy
    # with those when the interrupt comes, however fast the short ones go
    dataset = tmp_path / "dataset"
    for i in range(N_SMALL):
        shutil.copytree(synthetic / f"syn_{i:03d}", dataset / f"syn_{i:03d}")
    for name in SAMPLES:
        shutil.copytree(samples_dir / name, dataset / f"zz_{name}")
    total = N_SMALL + len(SAMPLES)
    synthetic = dataset
    cache, out = tmp_path / "cache", tmp_path / "out"
    out.mkdir()
    env = {k: v for k, v in os.environ.items() if k != KEEP_ENV}
    argv = [sys.executable, "-m", "massviz", "estimate", str(synthetic), "--detector", "depth", "--weights",
            str(weights), "--cache", str(cache), "--engine", "ray", "--ray-address", ray_address, "--quiet",
            "--out", str(out / "pred.csv")]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    deadline = time.monotonic() + 240
    def traces():  # written ones: a hidden temporary of a write under way is not (yet) a trace
        return [p for p in cache.glob("traces/*/*.npz") if not p.name.startswith(".")]

    while len(traces()) < 4:
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, "no trace written"
        time.sleep(0.2)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "interrupted" in err and "Traceback" not in err
    assert list(out.iterdir()) == []
    finished = {p.parent.name.rsplit("-", 1)[0] for p in traces()}
    assert 4 <= len(finished) < total
    rc = run("estimate", synthetic, "--detector", "depth", "--weights", weights, "--cache", cache, "--quiet",
             "--report", tmp_path / "r.json", "--out", out / "pred.csv")
    assert rc == 0
    status = {e["id"]: e["status"] for e in report(tmp_path / "r.json")["recordings"]}
    assert {i for i, s in status.items() if s == "cached"} >= finished
    assert len(status) == total


def test_engine_options_are_checked(samples_dir, weights, tmp_path, capsys):
    assert run("estimate", samples_dir, "--detector", "depth", "--weights", weights, "--workers", "2",
               "--out", tmp_path / "p.csv") == 2
    assert "--workers and --ray-address need --engine ray" in capsys.readouterr().err
    assert not (tmp_path / "p.csv").exists()
