"""Names and trees, and resources: Unicode names in NFC and NFD, 255-byte names, symlink loops in a dataset, a
dataset of 50,000 recording folders, a recording whose files change while a run reads them; too few file
descriptors, an address-space limit, no $HOME with an unwritable default cache, a read-only dataset, a full temporary
folder. Each case: the command works, or says in one line what is wrong (exit 2), never a traceback, and leaves
nothing behind."""
from __future__ import annotations

import os
import resource
import shutil
import time
import unicodedata
from pathlib import Path

import pytest

import hostile_runs
from fakes import Base, copy_sample
from hostile_runs import run_massviz
from massviz import cli


def run_cli(argv, capsys) -> tuple[int, list[str]]:
    capsys.readouterr()
    code = cli.main([str(a) for a in argv])
    return code, [line for line in capsys.readouterr().err.splitlines() if line.strip()]


def pipeline(b: Base, work: Path, command: str, *extra) -> list:
    return [command, *extra, "--detector", "replay", "--replay", b.replay, "--weights", b.weights,
            "--cache", work / "cache", "--quiet"]


def _two_ids(ds: Path, a: str, b: str) -> list[str]:
    """Two recordings in folders named ``a`` and ``b``, each its name as id (cut to the 200 characters an id may
    have)."""
    import json

    ids = []
    for name in (a, b):
        meta = copy_sample(ds / name) / "meta.json"
        ids.append(name[:200])
        meta.write_text(json.dumps({**json.loads(meta.read_text()), "id": ids[-1]}))
    return ids


def _symlink_loops(ds: Path) -> list[str]:
    import json

    meta = copy_sample(ds / "rec") / "meta.json"
    meta.write_text(json.dumps({**json.loads(meta.read_text()), "id": "rec"}))
    (ds / "loop").symlink_to(".")
    (ds / "self").symlink_to("self")
    (ds / "rec" / "gt" / "loop").symlink_to("..")
    return ["rec"]


CAFE = "caf\u00e9"
TREES = {
    "unicode-nfc-and-nfd-names": lambda ds: _two_ids(ds, unicodedata.normalize("NFC", CAFE),
                                                     unicodedata.normalize("NFD", CAFE)),
    "name-of-255-bytes": lambda ds: _two_ids(ds, "\u00e9" * 127 + "x", "a" * 255),
    "symlink-loops-in-the-dataset": _symlink_loops,
    "names-with-spaces-and-dots": lambda ds: _two_ids(ds, " .rec. ", "rec two"),
}


@pytest.mark.parametrize("command", ["estimate", pytest.param("extract", marks=pytest.mark.slow),
                                     pytest.param("log-rrd-dir", marks=pytest.mark.slow)])
@pytest.mark.parametrize("tree", [pytest.param(t, marks=() if i == 0 else pytest.mark.slow)
                                  for i, t in enumerate(TREES)])
def test_names_and_trees(tree, command, base, tmp_path, capsys):
    ds = tmp_path / "ds"
    ds.mkdir()
    ids = TREES[tree](ds)
    out = tmp_path / "out"
    if command == "estimate":
        argv = pipeline(base, tmp_path, "estimate", ds, "--out", out)
    elif command == "extract":
        argv = pipeline(base, tmp_path, "extract", ds, "--out", out)
    else:
        argv = pipeline(base, tmp_path, "log", ds, "--rrd-dir", out)
    code, err = run_cli(argv, capsys)
    assert "Traceback" not in "\n".join(err) and not [e for e in err if "internal error" in e], err
    if code == 2:  # refused: one line (ids that cannot both be written as file names)
        assert len([e for e in err if ": error:" in e]) == 1 and not out.exists(), err
        return
    assert code == 0, err
    if command == "estimate":
        assert len(out.read_text().splitlines()) == 1 + len(ids)
    elif command == "extract":
        import pandas as pd

        assert sorted(pd.read_csv(out / "index.csv", dtype=str)["recording"].str.lstrip("'")) == sorted(ids)
    else:
        assert len(list(out.glob("*.rrd"))) == len(ids)
    assert not [p for p in tmp_path.rglob(".*")], "hidden temporaries left"


@pytest.mark.slow
def test_listing_50000_recording_folders_takes_seconds_and_little_memory_each(tmp_path):
    import tracemalloc

    from massviz.io.recording import find_recordings

    ds = tmp_path / "ds"
    ds.mkdir()
    n = 50_000
    for i in range(n):
        os.makedirs(ds / f"rec{i:05d}" / "rgb")
    tracemalloc.start()
    t0 = time.perf_counter()
    found = find_recordings(ds)
    seconds = time.perf_counter() - t0
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert len(found) == n
    assert seconds < 20, f"{seconds:.1f} s"
    assert peak / n < 2048, f"{peak / n:.0f} bytes per recording"


# ========================================================================================================= resources
def _limit(kind: int, value: int):
    def apply():
        resource.setrlimit(kind, (value, value))
    return apply


def _read_only_dataset(work: Path, b: Base):
    rec = copy_sample(work / "rec")
    for p in [rec, *rec.rglob("*")]:
        p.chmod(0o555 if p.is_dir() else 0o444)
    return rec, {}, None


def _no_home(work: Path, b: Base):
    return copy_sample(work / "rec"), {"HOME": "/nonexistent", "MASSVIZ_CACHE_DIR": "/proc/massviz-cache",
                                      "XDG_CACHE_HOME": "/proc"}, None


def _full_tmp(work: Path, b: Base):
    return copy_sample(work / "rec"), {"TMPDIR": "/proc"}, None


RESOURCES = {
    "file-descriptors-64": (lambda w, b: (copy_sample(w / "rec"), {}, _limit(resource.RLIMIT_NOFILE, 64))),
    "address-space-3GB": (lambda w, b: (copy_sample(w / "rec"), {}, _limit(resource.RLIMIT_AS, 3 << 30))),
    "no-home-unwritable-default-cache": _no_home,
    "read-only-dataset": _read_only_dataset,
    "unwritable-temporary-folder": _full_tmp,
}


@pytest.mark.slow  # a massviz process with its own resource limits
@pytest.mark.parametrize("name", list(RESOURCES))
def test_scarce_resources_are_one_line_or_work(name, base, tmp_path):
    """``estimate`` (default cache) under each limit: it works, or one line says what is missing; nothing left."""
    work = tmp_path / "w"
    work.mkdir()
    (work / "home").mkdir()
    rec, env, preexec = RESOURCES[name](work, base)
    out = work / "p.csv"
    argv = ["estimate", rec, "--out", out, "--detector", "replay", "--replay", base.replay, "--weights", base.weights,
            "--quiet"]
    if env:
        saved = hostile_runs.clean_env
        hostile_runs.clean_env = lambda: {**saved(), **env}
        try:
            run = run_massviz(argv, work, preexec=preexec)
        finally:
            hostile_runs.clean_env = saved
    else:
        run = run_massviz(argv, work, preexec=preexec)
    both = run.stdout + run.stderr
    assert "Traceback" not in both and "internal error" not in both, both[-2000:]
    errors = [line for line in run.stderr.splitlines() if ": error:" in line]
    if run.code == 0:
        assert out.is_file() and len(out.read_text().splitlines()) == 2
    else:
        assert run.code == 2 and len(errors) == 1 and not out.exists(), run.stderr
    assert not [p for p in work.rglob(".*") if "usercache" not in p.parts and "xdg" not in p.parts]
    if name == "read-only-dataset":
        shutil.rmtree(rec, onerror=lambda f, p, e: (os.chmod(os.path.dirname(p), 0o755), f(p)))


#: how a recording's file changes while a run reads it (after the first frame's step: the file was already read)
CHANGES = {
    "depth-frame-rewritten": lambda rec: (rec / "depth" / "000000.png").write_bytes(
        (rec / "depth" / "000001.png").read_bytes()),
    "rgb-frame-rewritten": lambda rec: (rec / "rgb" / "000000.png").write_bytes(
        (rec / "rgb" / "000001.png").read_bytes()),
    "frame-replaced-by-a-copy": lambda rec: os.replace(
        shutil.copy(rec / "depth" / "000000.png", rec / "depth" / "x.png"), rec / "depth" / "000000.png"),
    "rgb-frame-touched": lambda rec: os.utime(rec / "rgb" / "000000.png", ns=(1, 1)),
}


@pytest.mark.parametrize("command", ["estimate", pytest.param("log", marks=pytest.mark.slow),
                                     pytest.param("cloud", marks=pytest.mark.slow)])
@pytest.mark.parametrize("change", [pytest.param(c, marks=() if i == 0 else pytest.mark.slow)
                                    for i, c in enumerate(CHANGES)])
def test_a_recording_whose_files_change_during_the_run_is_said_and_not_cached(change, command, base, tmp_path,
                                                                              capsys, monkeypatch):
    from massviz.core import pipeline as core_pipeline

    rec = copy_sample(tmp_path / "rec")
    step, calls = core_pipeline.FramePipeline.step, []

    def step_then_change(self, *args, **kwargs):
        result = step(self, *args, **kwargs)
        calls.append(1)
        if len(calls) == 1:
            CHANGES[change](rec)
        return result

    monkeypatch.setattr(core_pipeline.FramePipeline, "step", step_then_change)
    out = tmp_path / "out"
    target = {"estimate": ["--out", out], "log": ["--rrd", out], "cloud": ["--out", out]}[command]
    code, err = run_cli(pipeline(base, tmp_path, command, rec, *target), capsys)
    assert code == 0 and len(calls) > 1, err
    said = [e for e in err if "changed while the run read it" in e]
    assert len(said) == 1 and str(rec / ("rgb" if "rgb" in change else "depth") / "000000.png") in said[0] \
        and "not cached" in said[0], err
    assert not list((tmp_path / "cache").rglob("*.npz")), "a result read from two versions of a file was cached"
    assert not [p for p in tmp_path.rglob(".*")], "hidden temporaries left"
