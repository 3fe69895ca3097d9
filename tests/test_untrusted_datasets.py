"""No recording dropped in silence: in a dataset run, every recording that is not estimated is named on stderr with
its reason and counted in the summary, and ``--on-error stop`` stops on it.

The cases are generated: each way a dataset folder can break one of its recordings (a symlink loop, a dangling
link or a file where ``rgb/`` or ``depth/`` should be, a missing or empty frame folder, an unreadable folder, a
folder among the frames), applied to recording ``b`` of a dataset whose recording ``a`` is sound, for ``estimate``
and ``log --rrd-dir``. An unreadable folder (``chmod 000``) is readable to root: there the recording may be
estimated; it is never left out without a word.
"""
from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

from massviz import cli
from support import small_recording


def _loop(path: Path) -> None:
    shutil.rmtree(path)
    path.symlink_to(path.name)


def _dangling(path: Path) -> None:
    shutil.rmtree(path)
    path.symlink_to("nowhere")


def _file(path: Path) -> None:
    shutil.rmtree(path)
    path.write_bytes(b"not a folder")


def _empty(path: Path) -> None:
    shutil.rmtree(path)
    path.mkdir()


def _unreadable(path: Path) -> None:
    path.chmod(0)


def _folder_among_frames(path: Path) -> None:
    (path / "000001.png").unlink()
    (path / "000001.png").mkdir()


#: case -> (what is broken in recording b, how)
BREAKS = {
    "rgb-symlink-loop": ("rgb", _loop),
    "depth-symlink-loop": ("depth", _loop),
    "rgb-dangling-link": ("rgb", _dangling),
    "rgb-is-a-file": ("rgb", _file),
    "depth-is-a-file": ("depth", _file),
    "missing-rgb": ("rgb", shutil.rmtree),
    "missing-depth": ("depth", shutil.rmtree),
    "empty-rgb": ("rgb", _empty),
    "empty-depth": ("depth", _empty),
    "unreadable-rgb": ("rgb", _unreadable),
    "unreadable-recording": (".", _unreadable),
    "folder-among-the-frames": ("rgb", _folder_among_frames),
}
#: cases that root can still read (the recording may then be estimated)
ROOT_READS = {"unreadable-rgb", "unreadable-recording"}


@pytest.fixture(scope="module")
def options(tmp_path_factory, weights) -> list:
    cache = tmp_path_factory.mktemp("datasets_cache")
    return ["--detector", "depth", "--weights", str(weights), "--cache", str(cache), "--quiet"]


def run(argv, capsys) -> tuple[int, list[str]]:
    code = cli.main([str(a) for a in argv])
    return code, [line for line in capsys.readouterr().err.splitlines() if line.strip()]


def broken_dataset(root: Path, case: str) -> Path:
    ds = root / "ds"
    for name in ("a", "b"):
        small_recording(ds / name, frames=2)
    where, how = BREAKS[case]
    how(ds / "b" / where if where != "." else ds / "b")
    return ds


@pytest.fixture
def restore_modes(tmp_path):
    yield
    for p in [tmp_path, *tmp_path.rglob("*")]:  # chmod 000 folders back, so that pytest can remove them
        if not p.is_symlink():
            os.chmod(p, 0o755)


@pytest.mark.parametrize("command", ["estimate", pytest.param("log-rrd-dir", marks=pytest.mark.slow)])
@pytest.mark.parametrize("case", [pytest.param(c, marks=() if i == 0 else pytest.mark.slow)
                                  for i, c in enumerate(BREAKS)])
def test_a_broken_recording_in_a_dataset_is_named_counted_and_stops_a_stop_run(case, command, options, tmp_path,
                                                                               capsys, restore_modes):
    ds = broken_dataset(tmp_path, case)
    out = tmp_path / ("preds.csv" if command == "estimate" else "out")
    argv = (["estimate", ds, "--out", out] if command == "estimate" else ["log", ds, "--rrd-dir", out]) + options
    code, err = run(argv, capsys)
    assert not [line for line in err if "Traceback" in line or "internal error" in line], err
    named = [line for line in err if "failed:" in line and str(ds / "b") in line]
    if case in ROOT_READS and os.geteuid() == 0 and code == 0:  # root reads it: estimated, like a
        if command == "estimate":
            assert [r.split(",")[0] for r in out.read_text().splitlines()[1:]] == ["a", "b"]
        else:
            assert sorted(p.name for p in out.glob("*.rrd")) == ["a.rrd", "b.rrd"]
        return
    assert code == 3, err
    assert len(named) == 1, err  # named once, with its reason after the path
    assert named[0].split(str(ds / "b"), 1)[1].strip(" /:"), named
    summary = err[-1]
    assert "1 failed" in summary, err
    if command == "estimate":
        assert "2 recordings, 1 estimated, 1 failed" in summary, summary
    else:
        assert sorted(p.name for p in out.glob("*.rrd")) == ["a.rrd"]
    stop_out = tmp_path / ("stop.csv" if command == "estimate" else "stop")
    argv[argv.index(out)] = stop_out
    code, err = run([*argv, "--on-error", "stop"], capsys)
    errors = [line for line in err if ": error:" in line]
    assert code == 2 and len(errors) == 1 and str(ds / "b") in errors[0], err
    assert not stop_out.exists()
