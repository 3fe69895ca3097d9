"""One pass (issue 19): an uncached ``massviz log`` reads each RGB and depth file of the recording exactly once. The
frames are logged as the pipeline processes them (its ``on_frame`` observer), from the bytes the reader read; the
trace-dependent overlays afterwards read no frame. Opens are counted with an audit hook (``open`` events) in a
subprocess; frame files are never read with ``cv2.imread`` (which raises no audit event), checked in the source."""
from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CUP = ROOT / "data_samples" / "cup_handover"

#: runs ``massviz ARGS`` with an audit hook that records every file opened under ROOT_DIR, written to OUT as JSON
COUNTING = """
import collections, json, os, sys
root, out = os.path.realpath(sys.argv[1]), sys.argv[2]
opened = collections.Counter()
def hook(event, args):
    if event == "open" and isinstance(args[0], (str, bytes, os.PathLike)):
        path = os.path.realpath(os.fsdecode(args[0]))
        if path.startswith(root + os.sep):
            opened[os.path.relpath(path, root)] += 1
sys.addaudithook(hook)
sys.argv = ["massviz", *sys.argv[3:]]
from massviz.cli import main
try:
    code = main()
finally:
    json.dump(dict(opened), open(out, "w"))
sys.exit(code)
"""


def count_opens(rec: Path, tmp_path: Path, *args) -> tuple[dict, subprocess.CompletedProcess]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    env.pop("MASSVIZ_DEBUG", None)
    out = tmp_path / "opened.json"
    r = subprocess.run([sys.executable, "-c", COUNTING, str(rec), str(out), *map(str, args)], capture_output=True,
                       text=True, timeout=900, cwd=ROOT, env=env)
    assert r.returncode == 0, r.stderr
    return json.loads(out.read_text()), r


@pytest.fixture
def cold_cup(tmp_path):
    rec = tmp_path / "cup_handover"
    shutil.copytree(CUP, rec)  # a new path: nothing of it is in any cache
    return rec


def frame_files(rec: Path) -> list[str]:
    return sorted(str(p.relative_to(rec)) for sub in ("rgb", "depth") for p in (rec / sub).iterdir())


@pytest.mark.slow
def test_uncached_log_opens_each_frame_file_once(cold_cup, tmp_path, shared_dir):
    weights = shared_dir / "weights" / "corsmal_visual" / "Encoder_pool_aug_158.torch"
    opened, r = count_opens(cold_cup, tmp_path, "log", cold_cup, "--detector", "depth", "--weights", weights,
                            "--no-cache", "--rrd", tmp_path / "cup.rrd", "--quiet")
    files = frame_files(cold_cup)
    assert len(files) == 72
    # open_recording checks the first RGB and depth frame when it opens the folder; the reader keeps those bytes
    # for the frame loop, so they too are opened once
    expected = {f: 1 for f in files}
    assert {f: opened.get(f, 0) for f in files} == expected
    from massviz.views.rerun.rrd_reader import rrd_contents

    contents = rrd_contents(tmp_path / "cup.rrd")
    assert "EncodedImage:blob" in contents["/camera/rgb"] and "EncodedDepthImage:blob" in contents["/camera/depth"]
    assert {"/camera/detections", "/camera/masks", "/patches/0", "/predictions/estimate"} <= set(contents)


def test_no_frame_file_is_read_with_cv2_imread():
    # cv2.imread raises no audit event, so the count above would miss it: frame readers decode bytes instead
    offenders = [str(p.relative_to(ROOT)) for p in (ROOT / "massviz").rglob("*.py")
                 if {"io", "views", "core"} & set(p.relative_to(ROOT / "massviz").parts[:-1])
                 and p.name != "ground_truth.py"  # masks, not frames
                 and re.search(r"cv2\.imread\(", p.read_text())]
    assert offenders == []
