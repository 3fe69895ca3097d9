"""Outputs whole or not at all: a killed ``log --rrd-dir`` never blocks the next run and leaves what a clean run
leaves; writers of one ``--rrd-dir`` at once leave one writer's whole output; output names of 255 bytes work for
every output option of every command (the hidden temporaries beside them are short).

The runs are children of a fork server (``tests/forkserver.py``) whose ``os.replace`` is wrapped
(``support.KILL_HOOK``): a run is killed (SIGKILL) at its ``n``-th commit, just before or just after it; the kill
points are generated from the number of commits a clean run makes.
"""
from __future__ import annotations

import argparse
import csv
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from forkserver import ForkServer
from support import KILLING_SERVER, ROOT, small_recording

#: seconds a run may take
TIMEOUT_S = 300


@pytest.fixture(scope="module")
def ctx(tmp_path_factory, weights):
    """A dataset of two 2-frame recordings, a shared trace cache, the pipeline options, a clean run's output."""
    root = tmp_path_factory.mktemp("untrusted_outputs")
    for name in ("a", "b"):
        small_recording(root / "ds" / name, frames=2)
    env = {k: v for k, v in os.environ.items() if k not in ("MASSVIZ_DEBUG", "MASSVIZ_WEIGHTS", "RUST_LOG")}
    server = ForkServer({**env, "PYTHONPATH": str(ROOT)}, [sys.executable, "-c", KILLING_SERVER])
    c = argparse.Namespace(root=root, ds=root / "ds", env=env, server=server, weights=weights,
                           options=["--detector", "depth", "--weights", str(weights), "--cache",
                                    str(root / "cache"), "--quiet"])
    clean = root / "clean"
    clean.mkdir()
    code, err = massviz(c, log_argv(c, root / "warm"), clean)  # fills the trace cache: the runs below only read it
    assert code == 0, err
    counts = {}
    for variant in ("fresh", "force"):  # a run into a new OUT, then one replacing it: each one's commits counted
        code, err = massviz(c, log_argv(c, clean / "out", variant == "force"), clean, KILL_COUNT=clean / "n")
        assert code == 0, err
        counts[variant] = int((clean / "n").read_text())
    c.clean, c.counts = result(clean / "out"), counts
    yield c
    server.close()


def massviz(c, argv, work: Path, **env) -> tuple[int, str]:
    """``massviz ARGV`` forked from the server in ``work`` (its TMPDIR and HOME inside it): (exit code, stderr)."""
    for d in ("tmpdir", "home"):
        (work / d).mkdir(exist_ok=True)
    full = {**c.env, "PYTHONPATH": str(ROOT), "TMPDIR": str(work / "tmpdir"), "HOME": str(work / "home"),
            "XDG_CACHE_HOME": str(work / "home" / "xdg"), **{k: str(v) for k, v in env.items()}}
    logs = work.parent / f"{work.name}.logs"
    logs.mkdir(exist_ok=True)
    c.server.start([str(a) for a in argv], full, work, logs / "out", logs / "err")
    code = c.server.wait()
    return code, (logs / "err").read_text(errors="replace")


def log_argv(c, out: Path, force: bool = False) -> list:
    return ["log", c.ds, "--rrd-dir", out, *c.options, *(["--force"] if force else [])]


def result(out: Path):
    """What a ``--rrd-dir`` output holds, without what differs between two clean runs (Rerun's recording ids, hence
    the .rrd sizes): its files, index.csv without ``rrd_bytes``, patches.csv; and the checks that make it one
    run's whole output (every .rrd and thumbnail named by a row, every row's file there)."""
    files = sorted(p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file())
    with open(out / "index.csv", newline="") as fh:
        index = [{k: v for k, v in row.items() if k != "rrd_bytes"} for row in csv.DictReader(fh)]
    with open(out / "patches.csv", newline="") as fh:
        patches = list(csv.DictReader(fh))
    assert sorted(r["rrd"] for r in index) == sorted(f for f in files if f.endswith(".rrd"))
    assert sorted(r["thumb"] for r in patches) == sorted(f for f in files if f.startswith("patches/"))
    return files, index, patches


def hidden_beside(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


# ======================================================================================================= killed
KILLS = [("fresh", "first", "before"), ("fresh", "middle", "after"), ("fresh", "last", "before"),
         ("fresh", "last", "after"), ("force", "middle", "before"), ("force", "last", "after")]


@pytest.mark.slow
@pytest.mark.parametrize("variant,point,when", [pytest.param(*k, id=f"{k[0]}-out-killed-{k[2]}-{k[1]}-commit")
                                                for k in KILLS])
def test_a_killed_rrd_dir_write_never_blocks_the_next_run_which_equals_a_clean_run(variant, point, when, ctx,
                                                                                     tmp_path):
    """SIGKILL at the first, a middle or the last commit of ``log DATASET --rrd-dir OUT`` (a new OUT, or
    ``--force`` over a whole one holding a file of the user's): OUT is the old output or none (a new OUT) or the new
    one, whole, never a part; the same command again succeeds and equals a clean run, leaving no temporary."""
    work = tmp_path / "w"
    work.mkdir()
    out = work / "out"
    if variant == "force":
        code, err = massviz(ctx, log_argv(ctx, out), work)
        assert code == 0, err
        (out / "notes.txt").write_text("mine")
    n = ctx.counts[variant]
    nth = {"first": 1, "middle": max(1, n // 2), "last": n}[point]
    argv = log_argv(ctx, out, variant == "force")
    for _ in range(2 if point == "first" else 1):  # killed twice at the first: what kills leave never accumulates
        code, err = massviz(ctx, argv, work, KILL_AT=nth, KILL_WHEN=when)
        assert code == -9, (code, err)
        if out.exists():  # the old output (--force) or the new one, whole
            files, index, patches = result(out)
            assert [f for f in files if f != "notes.txt"] == ctx.clean[0] and (index, patches) == ctx.clean[1:]
            assert variant == "fresh" or (out / "notes.txt").read_text() == "mine"
        else:
            assert variant == "fresh"
    again_code, again_err = massviz(ctx, argv, work)
    if again_code == 2 and "already holds a dataset" in again_err:  # the kill came once the whole OUT was in place
        assert variant == "fresh" and point == "last" and when == "after", again_err
    else:
        assert again_code == 0, again_err
    assert "Traceback" not in again_err
    files, index, patches = result(out)
    assert [f for f in files if f != "notes.txt"] == ctx.clean[0]
    assert (index, patches) == ctx.clean[1:]
    assert variant == "fresh" or (out / "notes.txt").read_text() == "mine"
    assert hidden_beside(work) == [] and hidden_beside(out) == [], "temporaries of the killed runs were not swept"


# ================================================================================================== concurrency
#: forks N children from one interpreter that imported massviz, each running ``massviz ARGV`` with its stderr in
#: a file of its own, all at once; prints their exit codes
WRITERS = textwrap.dedent("""
    import json, os, sys
    from massviz.cli import _quiet_native_logs
    _quiet_native_logs()
    import cv2, torch, massviz.app
    n, logs, argv = int(sys.argv[1]), sys.argv[2], sys.argv[3:]
    pids = []
    for i in range(n):
        pid = os.fork()
        if pid == 0:
            fd = os.open(os.path.join(logs, f"err{i}"), os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
            os.dup2(fd, 2)
            from massviz.cli import main
            code = main(argv)
            sys.stderr.flush()
            os._exit(code)
        pids.append(pid)
    print(json.dumps([os.waitstatus_to_exitcode(os.waitpid(p, 0)[1]) for p in pids]))
""")


def users_out(c, tmp_path) -> tuple[Path, Path]:
    """(work, OUT): a clean ``log --rrd-dir`` output OUT in the folder work, holding a file of the user's too."""
    work = tmp_path / "w"
    work.mkdir()
    out = work / "out"
    code, err = massviz(c, log_argv(c, out), work)
    assert code == 0, err
    (out / "notes.txt").write_text("mine")
    return work, out


def assert_one_writers_output(c, work: Path, out: Path) -> None:
    """OUT is one clean run's whole output with the user's file kept, and no temporary is left beside or in it."""
    files, index, patches = result(out)
    assert [f for f in files if f != "notes.txt"] == c.clean[0] and (index, patches) == c.clean[1:]
    assert (out / "notes.txt").read_text() == "mine"
    assert hidden_beside(work) == [] and hidden_beside(out) == []


@pytest.mark.slow
@pytest.mark.parametrize("writers", [3])
def test_writers_of_one_rrd_dir_at_once_leave_one_writers_whole_output(writers, ctx, tmp_path):
    """N ``log DATASET --rrd-dir OUT --force`` at once over an existing OUT holding a file of the user's: each
    succeeds or says in one line that another one holds OUT; OUT ends as one writer's whole output (every .rrd and
    thumbnail named by a row), the user's file kept, no temporary left."""
    import json

    work, out = users_out(ctx, tmp_path)
    logs = tmp_path / "logs"
    logs.mkdir()
    run = subprocess.run([sys.executable, "-c", WRITERS, str(writers), str(logs),
                          *map(str, log_argv(ctx, out, force=True))], cwd=work, capture_output=True, text=True,
                         env={**ctx.env, "PYTHONPATH": str(ROOT)}, timeout=TIMEOUT_S)
    assert run.returncode == 0, run.stderr
    codes = json.loads(run.stdout.splitlines()[-1])
    for i, code in enumerate(codes):
        err = (logs / f"err{i}").read_text()
        assert "Traceback" not in err, err
        errors = [line for line in err.splitlines() if ": error:" in line]
        assert code == 0 or (code == 2 and len(errors) == 1 and "another" in errors[0]), (code, err)
    assert 0 in codes
    assert_one_writers_output(ctx, work, out)


@pytest.mark.slow
def test_writers_of_one_rrd_dir_wait_for_the_swap_and_out_is_one_writers_output(ctx, tmp_path):
    """The interleaving forced: while this test holds the lock on OUT's parent folder, three ``--force`` writers
    build their whole outputs beside OUT and then wait (none replaces OUT, which stays the first run's); released,
    they swap one after another, and OUT is one writer's whole output with the user's file kept."""
    import fcntl
    import json
    import time

    work, out = users_out(ctx, tmp_path)
    before = (out / "index.csv").stat().st_ino
    logs = tmp_path / "logs"
    logs.mkdir()
    fd = os.open(work, os.O_RDONLY | os.O_DIRECTORY)
    fcntl.flock(fd, fcntl.LOCK_EX)
    try:
        writers = subprocess.Popen([sys.executable, "-c", WRITERS, "3", str(logs),
                                    *map(str, log_argv(ctx, out, force=True))], cwd=work, stdout=subprocess.PIPE,
                                   text=True, env={**ctx.env, "PYTHONPATH": str(ROOT)})
        deadline = time.monotonic() + TIMEOUT_S
        while len([p for p in work.glob(".mv-*.part") if (p / "index.csv").is_file()]) < 3:
            assert writers.poll() is None, "a writer ended while another held the lock on OUT's folder"
            assert time.monotonic() < deadline, "the writers did not build their outputs"
            time.sleep(0.2)
        time.sleep(1.0)
        assert writers.poll() is None, "a writer replaced OUT without the lock"
        assert (out / "index.csv").stat().st_ino == before  # OUT untouched while they wait
    finally:
        fcntl.flock(fd, fcntl.LOCK_UN)
        os.close(fd)
    stdout, _ = writers.communicate(timeout=TIMEOUT_S)
    assert json.loads(stdout.splitlines()[-1]) == [0, 0, 0], [(logs / f"err{i}").read_text() for i in range(3)]
    assert_one_writers_output(ctx, work, out)


# ============================================================================================ 255-byte names
def long_name(char: str, suffix: str = "", size: int = 255) -> str:
    """A file or folder name of ``size`` bytes ending with ``suffix``."""
    return char * (size - len(suffix)) + suffix


#: every output option of every command, by the runs that write them: (command, options) -> argv builder
#: (ctx, folder for the outputs, {option: output path}) -> argv. A run writes all the options it lists at once.
def _named(folder: Path, **names) -> dict:
    return {f"--{k.replace('_', '-')}": folder / v for k, v in names.items()}


OUTPUT_RUNS = {
    "estimate": (lambda c, o: _named(o, out=long_name("e", ".csv"), report=long_name("r", ".json")),
                 lambda c, outs: ["estimate", c.ds, *c.options, *_flat(outs)]),
    "log": (lambda c, o: _named(o, rrd=long_name("l", ".rrd"), ply=long_name("p")),
            lambda c, outs: ["log", c.ds / "a", *c.options, *_flat(outs)]),
    "log-rrd-dir": (lambda c, o: _named(o, rrd_dir=long_name("d"), report=long_name("r", ".json")),
                    lambda c, outs: ["log", c.ds, *c.options, *_flat(outs)]),
    "extract": (lambda c, o: _named(o, out=long_name("x"), report=long_name("r", ".json")),
                lambda c, outs: ["extract", c.ds, *c.options, *_flat(outs)]),
    "cloud": (lambda c, o: _named(o, out=long_name("c")),
              lambda c, outs: ["cloud", c.ds / "a", *c.options, *_flat(outs)]),
    "render": (lambda c, o: _named(o, out=long_name("i", ".png")),
               lambda c, outs: ["render", c.ds / "a", *c.options, "--size", "64x48", *_flat(outs)]),
    "sweep": (lambda c, o: _named(o, csv=long_name("s", ".csv"), plot=long_name("t", ".png"),
                                  report=long_name("r", ".json")),
              lambda c, outs: ["sweep", c.ds, *c.options, "--threshold", "0.4,0.5", "--k", "5", *_flat(outs)]),
    "compare": (lambda c, o: _named(o, json=long_name("j", ".json"), rrd=long_name("m", ".rrd")),
                lambda c, outs: ["compare", c.ds / "a", *c.options, "--b-k", "3", *_flat(outs)]),
    "compare-runs": (lambda c, o: _named(o, out=long_name("u", ".csv"), rrd_dir=long_name("v")),
                     lambda c, outs: ["compare", c.root / "clean" / "out", c.root / "clean" / "out", "--weights",
                                      c.weights, "--b-weights", c.weights, *_flat(outs)]),
    "baseline": (lambda c, o: _named(o, out=long_name("b", ".csv")),
                 lambda c, outs: ["baseline", "random", "--annotations", annotations(c), *_flat(outs)]),
    "score": (lambda c, o: _named(o, json=long_name("j", ".json"), plot=long_name("g", ".png")),
              lambda c, outs: ["score", predictions(c), "--annotations", annotations(c), *_flat(outs)]),
    "samples": (lambda c, o: _named(o, out=long_name("z")),
                lambda c, outs: ["samples", "--only", "cup_handover", *_flat(outs)]),
    "train": (lambda c, o: _named(o, out=long_name("n")),
              lambda c, outs: ["train", patch_set(c), "--epochs", "1", "--augment", "1", "--quiet", *_flat(outs)]),
}
#: options of the commands that name no file massviz writes (matched by the rule below but not outputs)
NOT_OUTPUTS = {"--on-error", "--exec-time", "--labels", "--exclude", "--annotations", "--video"}
#: commands whose outputs are not tested here, and why
UNTESTED = {"live": "needs a RealSense file (pyrealsense2); its --rrd/--save go through the same atomic writers"}


def _flat(outs: dict) -> list:
    return [x for option, path in outs.items() for x in (option, path)]


def annotations(c) -> Path:
    path = c.root / "ann.csv"
    path.write_text("id,container id,width at the top,width at the bottom,height,depth,container capacity,"
                    "container mass\n0,1,92,60,110,-1,480,9\n1,4,80,60,150,-1,300,120\n")
    return path


def predictions(c) -> Path:
    path = c.root / "pred.csv"
    path.write_text("Configuration ID,Container mass\n0,10\n1,100\n")
    return path


def patch_set(c) -> Path:
    """A patch set of four recordings with different masses (training needs a spread of them)."""
    out = c.root / "patches"
    if not out.exists():
        import json

        recs = []
        for i in range(4):
            rec = small_recording(c.root / "train" / f"r{i}", frames=2)
            meta = json.loads((rec / "meta.json").read_text())
            meta.setdefault("container", {})["mass_g"] = 10.0 + 20 * i
            (rec / "meta.json").write_text(json.dumps(meta))
            recs.append(rec)
        code, err = massviz(c, ["extract", *recs, "--out", out, *c.options], c.root)
        assert code == 0, err
    return out


def output_options() -> set[tuple[str, str]]:
    """(command, option) of every option of every command that names something massviz writes: the options whose
    help says they write or output, or whose value is named OUT…/a folder or file to write."""
    from massviz import cli

    parser = cli.build_parser()
    (sub,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    found = set()
    for command, p in sub.choices.items():
        for a in p._actions:
            text = f"{a.help or ''} {a.metavar or ''}"
            if a.option_strings and a.nargs != 0 and (re.search(r"\b(writes?|written|output|save)\b|OUT", text)
                                                      or a.dest == "out"):
                option = max(a.option_strings, key=len)
                if option not in NOT_OUTPUTS and command not in UNTESTED:
                    found.add((command, option))
    return found


def test_every_output_option_has_a_255_byte_name_case(tmp_path):
    """The cases below cover every output option of every command (a new one fails here until it has a case)."""
    covered = {(name.split("-")[0], option) for name, (names, _) in OUTPUT_RUNS.items()
               for option in names(None, tmp_path)}
    assert output_options() - covered == set()


@pytest.mark.slow  # each case a massviz process
@pytest.mark.parametrize("run", OUTPUT_RUNS)
def test_output_names_of_255_bytes_work_for_every_output_option(run, ctx, tmp_path):
    """Each output named with 255 bytes (the most a Linux file name may have): written, nothing hidden left beside
    it. A temporary beside an output has a short name of its own (``.mv-PID-XXXXXXXX.tmp``)."""
    names, argv = OUTPUT_RUNS[run]
    folder = tmp_path / "outs"
    folder.mkdir()
    outs = names(ctx, folder)
    code, err = massviz(ctx, argv(ctx, outs), tmp_path)
    assert code == 0 and "Traceback" not in err, err
    for option, path in outs.items():
        assert path.exists(), f"{option} {path.name[:20]}… was not written:\n{err}"
    assert hidden_beside(folder) == [], "temporaries left beside the outputs"


@pytest.mark.slow  # each case a massviz process
@pytest.mark.parametrize("run", ["estimate", "log-rrd-dir"])
def test_an_output_name_too_long_is_one_line_naming_it(run, ctx, tmp_path):
    """A name of 256 bytes cannot be written: one line naming the user's path (not a hidden temporary), nothing
    left beside it."""
    names, argv = OUTPUT_RUNS[run]
    folder = tmp_path / "outs"
    folder.mkdir()
    outs = {option: path.with_name(path.name + "x") for option, path in names(ctx, folder).items()
            if option != "--report"}
    code, err = massviz(ctx, argv(ctx, outs), tmp_path)
    errors = [line for line in err.splitlines() if ": error:" in line]
    assert code == 2 and len(errors) == 1 and "Traceback" not in err, err
    (path,) = outs.values()
    assert str(path) in errors[0] and ".mv-" not in errors[0], errors[0]
    assert list(folder.iterdir()) == []
