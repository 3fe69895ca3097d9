"""Hostile inputs, outputs: what massviz writes is whole or absent, and never more than its own.

* Replacing an output (``--force``, a regenerated sample): only what massviz wrote under OUT is removed, and never
  through a symlink planted in it; anything else there is one error line, nothing touched.
* Every CSV massviz writes neutralises a formula-looking text cell (one rule, ``massviz.io.untrusted.tables``).
* A signal at the moment an output is committed (the renames that put it in place) or while a temporary one is
  removed: the output is whole or absent.
* A full disk during ``log --rrd``: one line naming the file and saying "No space", nothing left.

Cases are generated per class; each runs ``massviz.cli.main`` in-process (no interpreter start) unless it needs a
process of its own.
"""
from __future__ import annotations

import json
import os
import re
import signal
import stat
from pathlib import Path

import pytest

from fakes import Base, copy_sample
from hostile_runs import Case, check_promise, folder_state, pipeline_argv, run_massviz
from massviz import cli

ROOT = Path(__file__).resolve().parents[1]


def tree(folder: Path) -> dict[str, tuple]:
    """Every entry under ``folder`` (links not followed): (kind, size, content hash of small files)."""
    out = {}
    for p in sorted(folder.rglob("*")):
        st = p.lstat()
        data = p.read_bytes() if stat.S_ISREG(st.st_mode) and st.st_size < (1 << 20) else b""
        out[str(p.relative_to(folder))] = (stat.S_IFMT(st.st_mode), st.st_size, hash(data))
    return out


def run_cli(argv, capsys) -> tuple[int, list[str]]:
    capsys.readouterr()
    code = cli.main([str(a) for a in argv])
    err = capsys.readouterr().err
    return code, [line for line in err.splitlines() if line.strip()]


def pipeline(b: Base, work: Path, command: str, *extra) -> list:
    return [command, *extra, "--detector", "replay", "--replay", b.replay, "--weights", b.weights,
            "--cache", work / "cache", "--quiet"]


def with_id(rec: Path, rec_id: str) -> Path:
    meta = json.loads((rec / "meta.json").read_text())
    meta["id"] = rec_id
    meta.pop("config_id", None)
    (rec / "meta.json").write_text(json.dumps(meta))
    return rec


# ===================================================================================== replacing only what is ours
def _patch_set(work: Path, b: Base, capsys) -> Path:
    out = work / "out"
    code, err = run_cli(pipeline(b, work, "extract", copy_sample(work / "rec"), "--out", out), capsys)
    assert code == 0, err
    return out


def _elsewhere(work: Path) -> Path:
    other = work / "elsewhere"
    other.mkdir()
    (other / "keep.png").write_bytes(b"not massviz's")
    (other / "keep.jpg").write_bytes(b"not massviz's either")
    return other


def _extract_link(work, b, capsys):
    out = _patch_set(work, b, capsys)
    _elsewhere(work)
    os.rename(out / "images", work / "old_images")
    (out / "images").symlink_to("../elsewhere")
    return pipeline(b, work, "extract", work / "rec", "--out", out, "--force"), out, "symlink images"


def _extract_foreign(work, b, capsys):
    out = _patch_set(work, b, capsys)
    (out / "notes.txt").write_text("the user's")
    return pipeline(b, work, "extract", work / "rec", "--out", out, "--force"), out, "notes.txt"


def _extract_linked_png(work, b, capsys):
    out = _patch_set(work, b, capsys)
    other = _elsewhere(work)
    png = sorted((out / "images").iterdir())[0]
    png.unlink()
    png.symlink_to(other / "keep.png")
    return pipeline(b, work, "extract", work / "rec", "--out", out, "--force"), out, "symlink images/"


def _run_folder(work: Path) -> Path:
    run = work / "run"
    run.mkdir()
    for name in ("metrics.csv", "split.csv"):
        (run / name).write_text("epoch\n")
    return run


def _train_foreign(work, b, capsys):
    patches = _patch_set(work, b, capsys)
    run = _run_folder(work)
    (run / "notes.txt").write_text("the user's")
    return ["train", patches, "--out", run, "--force", "--epochs", "1", "--quiet"], run, "notes.txt"


def _train_link(work, b, capsys):
    patches = _patch_set(work, b, capsys)
    run = _run_folder(work)
    other = _elsewhere(work)
    (run / "best.torch").symlink_to(other / "keep.png")
    return ["train", patches, "--out", run, "--force", "--epochs", "1", "--quiet"], run, "symlink best.torch"


def _rrd_dir(work: Path, b: Base, capsys) -> Path:
    out = work / "ds"
    code, err = run_cli(pipeline(b, work, "log", copy_sample(work / "rec"), "--rrd-dir", out), capsys)
    assert code == 0, err
    return out


def _log_patches_link(work, b, capsys):
    out = _rrd_dir(work, b, capsys)
    _elsewhere(work)
    (out / "patches").rename(work / "old_patches")
    (out / "patches").symlink_to("../elsewhere")
    return pipeline(b, work, "log", work / "rec", "--rrd-dir", out, "--force"), out, "symlink patches"


def _log_rrd_link(work, b, capsys):
    out = _rrd_dir(work, b, capsys)
    other = _elsewhere(work)
    (other / "x.rrd").write_bytes(b"someone's recording")
    (out / "x.rrd").symlink_to(other / "x.rrd")
    return pipeline(b, work, "log", work / "rec", "--rrd-dir", out, "--force"), out, "symlink x.rrd"


def _log_new_folder_patches_link(work, b, capsys):
    out = work / "ds"
    out.mkdir()
    _elsewhere(work)
    (out / "patches").symlink_to("../elsewhere")
    return pipeline(b, work, "log", copy_sample(work / "rec"), "--rrd-dir", out), out, "symlink patches"


def _samples_link(work, b, capsys):
    out = work / "samples"
    out.mkdir()
    _elsewhere(work)
    (out / "cup_handover").symlink_to("../elsewhere")
    return ["samples", "--out", out, "--only", "cup_handover"], out / "cup_handover", "is a symlink"


def _samples_foreign(work, b, capsys):
    out = work / "samples"
    (out / "cup_handover" / "rgb").mkdir(parents=True)
    (out / "cup_handover" / "meta.json").write_text("{}")
    (out / "cup_handover" / "thesis.pdf").write_text("the user's")
    return ["samples", "--out", out, "--only", "cup_handover"], out / "cup_handover", "thesis.pdf"


REPLACE_CASES = {
    "extract-force-images-linked-out": _extract_link,
    "extract-force-foreign-file": _extract_foreign,
    "extract-force-patch-linked-out": _extract_linked_png,
    "train-force-foreign-file": _train_foreign,
    "train-force-checkpoint-linked-out": _train_link,
    "log-rrd-dir-force-patches-linked-out": _log_patches_link,
    "log-rrd-dir-force-rrd-linked-out": _log_rrd_link,
    "log-rrd-dir-new-patches-linked-out": _log_new_folder_patches_link,
    "samples-recording-linked-out": _samples_link,
    "samples-foreign-file": _samples_foreign,
}


@pytest.mark.parametrize("name", list(REPLACE_CASES))
def test_replacing_an_output_removes_only_what_massviz_wrote(name, base, tmp_path, capsys):
    """Whatever is planted in an output massviz replaces (a symlink out of it, a file of someone else's): one line
    naming the output and the entry, exit 2, and nothing anywhere changed (the folder, where its links point)."""
    work = tmp_path / "w"
    work.mkdir()
    argv, culprit, what = REPLACE_CASES[name](work, base, capsys)
    before = tree(work)
    code, err = run_cli(argv, capsys)
    assert code == 2 and len(err) == 1, err
    assert err[0].startswith(f"massviz {argv[0]}: error: {culprit}: ") and what in err[0], err
    after = {k: v for k, v in tree(work).items() if not k.startswith("cache")}
    assert after == {k: v for k, v in before.items() if not k.startswith("cache")}


def test_replacing_a_patch_set_of_its_own_still_works(base, tmp_path, capsys):
    work = tmp_path / "w"
    work.mkdir()
    out = _patch_set(work, base, capsys)
    stale = out / "images" / "stale_0.png"
    stale.write_bytes((out / "images").joinpath(sorted(os.listdir(out / "images"))[0]).read_bytes())
    code, err = run_cli(pipeline(base, work, "extract", work / "rec", "--out", out, "--force"), capsys)
    assert code == 0, err
    assert not stale.exists() and (out / "index.csv").is_file()
    assert not [p for p in work.iterdir() if p.name.startswith(".")]


# ============================================================================================ one rule for CSVs
CSV_WRITER = re.compile(r"\.to_csv\(|csv\.(writer|DictWriter)\(|\bDictWriter\(")


def csv_writers(text: str) -> list[int]:
    return [n for n, line in enumerate(text.splitlines(), 1) if CSV_WRITER.search(line)]


def test_every_csv_massviz_writes_goes_through_the_one_rule():
    """``massviz.io.untrusted.tables`` (``write_csv``, ``csv_writer``) is the only place that writes CSV."""
    rule = ROOT / "massviz" / "io" / "untrusted" / "tables.py"
    offenders = [f"{p.relative_to(ROOT)}:{n}" for p in sorted((ROOT / "massviz").rglob("*.py")) if p != rule
                 for n in csv_writers(p.read_text())]
    assert offenders == []
    assert csv_writers(rule.read_text())  # the scan finds the rule's own writers
    assert csv_writers("table.to_csv(path)\nw = csv.writer(fh)\n") == [1, 2]


@pytest.mark.parametrize("value", ["=1+1", "@SUM(A1)", "+cmd", "-x", "\tx"])
def test_text_cells_of_every_dtype_are_neutralised(value):
    """pandas' ``str`` columns (the default for text) as well as ``object`` ones."""
    import pandas as pd

    from massviz.io.untrusted import csv_safe

    for dtype in (object, "str", "string"):
        frame = pd.DataFrame({"id": pd.Series([value, "plain"], dtype=dtype), "n": [-1, 2]})
        assert csv_safe(frame)["id"].tolist() == ["'" + value, "plain"], dtype
    assert csv_safe(pd.DataFrame({"n": ["-1", "+2.5"]}))["n"].tolist() == ["-1", "+2.5"]


FORMULA_IDS = ["@SUM(1+1)*cmd", "=HYPERLINK(\"http://x\")", "+1+cmd", "-2-cmd"]


def _csv_cells(path: Path) -> list[str]:
    import csv

    with open(path, newline="") as fh:
        return [cell for row in csv.reader(fh) for cell in row]


def _written_csvs(command: str, work: Path, b: Base, rec: Path, capsys) -> list[Path]:
    if command == "extract":
        argv, outs = pipeline(b, work, "extract", rec, "--out", work / "p"), [work / "p" / "index.csv"]
    elif command == "log-rrd-dir":
        argv, outs = (pipeline(b, work, "log", rec, "--rrd-dir", work / "d"),
                      [work / "d" / "index.csv", work / "d" / "patches.csv"])
    elif command == "estimate":
        argv, outs = pipeline(b, work, "estimate", rec, "--out", work / "e.csv"), [work / "e.csv"]
    else:
        argv, outs = pipeline(b, work, "cloud", rec, "--out", work / "c"), [work / "c" / "measurements.csv"]
    code, err = run_cli(argv, capsys)
    assert code == 0, err
    return outs


@pytest.mark.parametrize("command", ["extract", "log-rrd-dir", "estimate", "cloud"])
@pytest.mark.parametrize("rec_id", FORMULA_IDS[:1] + [pytest.param(i, marks=pytest.mark.slow) for i in FORMULA_IDS[1:]])
def test_a_formula_id_reaches_no_csv_as_a_formula(command, rec_id, base, tmp_path, capsys):
    work = tmp_path / "w"
    work.mkdir()
    rec = with_id(copy_sample(work / "rec"), rec_id)
    for out in _written_csvs(command, work, base, rec, capsys):
        cells = _csv_cells(out)
        bad = [c for c in cells if c.startswith(("=", "+", "-", "@")) and not re.fullmatch(r"[-+][0-9.e+-]+", c)]
        assert not bad, (out.name, bad)
        if command != "cloud":
            assert "'" + rec_id in cells, (out.name, cells[:30])


# ============================================================================== a signal while an output is committed
def signal_at_commit(monkeypatch, out: Path, sig: int, nth: int = 1) -> list:
    """Send ``sig`` to this process right after the ``nth`` rename that moves something into or out of ``out`` (the
    renames that put a finished output in place): the worst moment for an interrupt."""
    real, seen = os.replace, []

    def replace(src, dst, *args, **kwargs):
        result = real(src, dst, *args, **kwargs)
        if str(out) in (os.fspath(src), os.fspath(dst)) or Path(os.fspath(dst)).parent == out:
            seen.append(dst)
            if len(seen) == nth:
                os.kill(os.getpid(), sig)
        return result

    monkeypatch.setattr(os, "replace", replace)
    return seen


def hidden(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob(".*"))


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
@pytest.mark.parametrize("nth", [1, 2])
def test_a_signal_while_cloud_moves_its_files_in_leaves_all_or_none(sig, nth, base, tmp_path, capsys, monkeypatch):
    work = tmp_path / "w"
    work.mkdir()
    rec = copy_sample(work / "rec")
    clean = work / "clean"
    code, err = run_cli(pipeline(base, work, "cloud", rec, "--out", clean, "--all-frames"), capsys)
    assert code == 0, err
    whole = sorted(os.listdir(clean))
    out = work / "out"
    out.mkdir()  # the user's folder: cloud writes into it
    seen = signal_at_commit(monkeypatch, out, sig, nth)
    code, err = run_cli(pipeline(base, work, "cloud", rec, "--out", out, "--all-frames"), capsys)
    monkeypatch.undo()
    assert len(seen) >= nth and code == 128 + sig and err[-1].startswith("massviz cloud: interrupted"), (code, err)
    assert sorted(os.listdir(out)) in ([], whole), sorted(os.listdir(out))
    assert hidden(work) == []


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
@pytest.mark.parametrize("nth", [1, 2])
def test_a_signal_while_train_swaps_its_run_folder_leaves_a_whole_run(sig, nth, sample_patch_set, tmp_path, capsys,
                                                                      monkeypatch):
    work = tmp_path / "w"
    work.mkdir()
    run = work / "run"
    argv = ["train", sample_patch_set, "--out", run, "--epochs", "1", "--augment", "1", "--quiet", "--force"]
    code, err = run_cli(argv, capsys)
    assert code == 0, err
    whole = sorted(os.listdir(run))
    seen = signal_at_commit(monkeypatch, run, sig, nth)
    code, err = run_cli(argv, capsys)
    monkeypatch.undo()
    assert len(seen) >= nth and code == 128 + sig and err[-1].startswith("massviz train: interrupted"), (code, err)
    assert run.is_dir() and sorted(os.listdir(run)) == whole
    assert hidden(work) == []


# ================================================================================= a full disk while an .rrd is written
@pytest.fixture
def small_disk(tmp_path):
    """A 2 MiB tmpfs (root, where mounting is allowed); None elsewhere."""
    import subprocess

    mount = tmp_path / "small"
    mount.mkdir()
    if os.geteuid() != 0 or subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(mount)],
                                           capture_output=True).returncode != 0:
        yield None
        return
    yield mount
    subprocess.run(["umount", "-l", str(mount)], capture_output=True)


def _fill(mount: Path, free_kib: int) -> None:
    st = os.statvfs(mount)
    with open(mount / "filler", "wb") as fh:
        fh.write(bytes(max(0, st.f_bavail * st.f_frsize - (free_kib << 10))))


def _fsize(nbytes: int):
    def limit():  # Python ignores SIGXFSZ: a write beyond the limit fails with EFBIG
        import resource

        resource.setrlimit(resource.RLIMIT_FSIZE, (nbytes, nbytes))
    return limit


#: room left on the disk (KiB): more than the first write massviz checks (64 KiB), less than the .rrd (~1 MB).
FULL_DISK_ROOM = [300, 150, 600]


@pytest.mark.slow  # a massviz process (a file-size limit where no small disk can be mounted)
@pytest.mark.parametrize("room", FULL_DISK_ROOM)
def test_log_rrd_onto_a_disk_that_fills_up_ends_with_one_line(room, base, small_disk, tmp_path):
    """Rerun's file writer dies on the first failed write and never answers a flush again (a hang in one run of
    two): massviz notices the file stopped growing, says "No space left on device" (or "File too large" under a
    file-size limit, where no small disk can be mounted), and leaves nothing."""
    work = tmp_path / "w"
    work.mkdir()
    (work / "home").mkdir()
    rec = copy_sample(work / "rec", n=12)
    if small_disk is not None:
        _fill(small_disk, room)
        out, preexec, what = small_disk / "o.rrd", None, r"\(No space left on device\)$"
    else:
        out, preexec, what = work / "o.rrd", _fsize(room << 10), r"\(File too large\)$"
    argv = pipeline_argv(work, base, "log", rec, "--rrd", out, cache=False)
    case = Case("log-rrd-disk-fills-up", argv, out, what, [out], preexec=preexec)
    before = folder_state(work, tuple(work / w for w in ("usercache", "xdg", "home", "tmpdir")))
    run = run_massviz(argv, work, preexec=preexec, timeout=90)
    check_promise(case, run, work, before)
    if small_disk is not None:
        assert sorted(os.listdir(small_disk)) == ["filler"]
