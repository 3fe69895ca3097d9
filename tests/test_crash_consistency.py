"""Crash consistency and concurrency: a command killed (SIGKILL: no clean-up runs) at any of its commits, then run
again, gives what a clean run gives; what the kill left (a temporary file, a half-made cache entry) is swept or
detected, never used and never accumulated. Two processes writing the same output: one wins whole.

The kill points are generated: the ``n``-th rename by which a command puts a finished file in place (its outputs and
its cache entries alike), just before it or just after it, in a process of its own with ``os.replace`` wrapped (a
real SIGKILL). Each case names its runner: ``subprocess`` (``python -c``, a fresh interpreter; a test's first case)
or ``forked`` (a child of a fork server that installed the wrapper: ``killing_server``, ``tests/forkserver.py``). The
clean runs compared with are ``python -m massviz``. Every case starts massviz processes: the module is ``slow``. The
kill points exist: :data:`COMMITS` (how many commits each command makes) is checked in-process by
``test_each_command_makes_the_commits_its_kill_points_name``, and a killed run that ends on its own fails its case.
"""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from fakes import Base, copy_sample
from forkserver import ForkServer
from hostile_runs import clean_env, run_forked
from support import KILLED_RUN, KILLING_SERVER

pytestmark = pytest.mark.slow  # every case starts massviz processes (a SIGKILL needs a process of its own)

ROOT = Path(__file__).resolve().parents[1]

#: seconds a command may run
TIMEOUT_S = 300


def massviz(argv, work: Path, kill_at: int | None = None, when: str = "before",
            forked: ForkServer | None = None) -> subprocess.CompletedProcess:
    """``massviz ARGV`` in ``work``, killed at its ``kill_at``-th commit when given; a subprocess, or a child of
    ``forked`` (a ``killing_server``)."""
    env = {**clean_env(), "PYTHONPATH": str(ROOT), "TMPDIR": str(work / "tmpdir"), "HOME": str(work / "home"),
           "MASSVIZ_CACHE_DIR": str(work / "usercache"), "XDG_CACHE_HOME": str(work / "xdg"),
           "TORCHINDUCTOR_CACHE_DIR": str(work / "xdg" / "torchinductor")}
    for d in ("tmpdir", "home"):
        (work / d).mkdir(exist_ok=True)
    if kill_at is not None:
        env.update(KILL_AT=str(kill_at), KILL_WHEN=when)
    if forked is not None:
        return _forked_run(forked, argv, work, env)
    if kill_at is None:
        cmd = [sys.executable, "-m", "massviz", *map(str, argv)]
    else:
        cmd = [sys.executable, "-c", KILLED_RUN, *map(str, argv)]
    return subprocess.run(cmd, cwd=work, env=env, capture_output=True, text=True, timeout=TIMEOUT_S)


def _forked_run(server: ForkServer, argv, work: Path, env: dict) -> subprocess.CompletedProcess:
    logs = work.parent / f"{work.name}.logs"  # beside ``work``: its checks see only what the command left
    logs.mkdir(exist_ok=True)
    run = run_forked(server, argv, work, env, logs, TIMEOUT_S)
    assert not run.killed, f"massviz {' '.join(map(str, argv))} ran more than {TIMEOUT_S} s"
    return subprocess.CompletedProcess(argv, run.code, run.stdout, run.stderr)


@pytest.fixture(scope="module")
def killing_server():
    server = ForkServer({**clean_env(), "PYTHONPATH": str(ROOT)}, [sys.executable, "-c", KILLING_SERVER])
    yield server
    server.close()


#: where a case's runs happen: a fresh interpreter each, or children of ``killing_server``
RUNNERS = ("subprocess", "forked")


def server_for(runner: str, request) -> ForkServer | None:
    """The fork server of a ``forked`` case (``killing_server``); none for a ``subprocess`` case."""
    assert runner in RUNNERS, runner
    return request.getfixturevalue("killing_server") if runner == "forked" else None


def pipeline(b: Base, work: Path, command: str, *extra) -> list:
    return [command, *extra, "--detector", "replay", "--replay", b.replay, "--weights", b.weights,
            "--cache", work / "cache", "--quiet"]


def command_case(command: str, work: Path, b: Base, patches: Path) -> tuple[list, Path]:
    """(argv, output) of one command on a fresh copy of the sample."""
    if command == "train":
        # one epoch: its best checkpoint is written once, whatever the machine's arithmetic (with two, the second
        # epoch's loss decides whether a second best is written: one more commit on some CPUs); --force: a rerun
        # after a kill that came once the run was in place replaces it
        return (["train", patches, "--out", work / "run", "--epochs", "1", "--augment", "1", "--quiet", "--force"],
                work / "run")
    rec = work / "rec"
    if not rec.exists():
        copy_sample(rec)
    outs = {"estimate": ("--out", work / "p.csv", "--exact"), "extract": ("--out", work / "patches", "--force"),
            "cloud": ("--out", work / "clouds"), "log": ("--rrd", work / "o.rrd")}
    extra = outs[command]
    return pipeline(b, work, command, rec, *extra), extra[1]


def result(command: str, out: Path):
    """What a run's output says, without what differs between two clean runs (times, Rerun's recording ids, the
    folder it ran in)."""
    return _result(command, out, str(out.parent))


def _result(command: str, out: Path, work: str):
    if command == "estimate":
        return [line.split(",")[2] for line in out.read_text().splitlines()]
    if command == "log":
        return out.is_file() and out.stat().st_size > 0
    if command == "train":
        return (out / "metrics.csv").read_text(), sorted(os.listdir(out))
    if command == "cloud":
        return (out / "measurements.csv").read_text().replace(work, "W"), sorted(os.listdir(out))
    return (out / "index.csv").read_text().replace(work, "W"), sorted(os.listdir(out / "images"))


def hidden(folder: Path) -> list[str]:
    skip = {"tmpdir", "home", "usercache", "xdg"}
    return sorted(str(p.relative_to(folder)) for p in folder.rglob(".*")
                  if not skip & set(p.relative_to(folder).parts))


@pytest.fixture(scope="module")
def clean_results(base, sample_patch_set, tmp_path_factory) -> dict:
    """Each command's clean result (computed on first use)."""
    out = {}

    def get(command):
        if command not in out:
            work = tmp_path_factory.mktemp(f"clean_{command}")
            argv, target = command_case(command, work, base, sample_patch_set)
            run = massviz(argv, work)
            assert run.returncode == 0, run.stderr
            out[command] = result(command, target)
        return out[command]
    return get


#: the commits (renames into place: outputs and cache entries) each command's case makes on a fresh folder (train:
#: the epoch's best checkpoint inside the run's temporary folder, then the run)
COMMITS = {"estimate": 6, "extract": 5, "cloud": 13, "train": 2, "log": 4}
#: where a command is killed: its first three commits and its last
KILL_POINTS = {c: sorted({n for n in (1, 2, 3) if n <= total} | {total}) for c, total in COMMITS.items()}
KILL_CASES = [(c, n, w) for c in ("estimate", "extract", "cloud", "train", "log") for n in KILL_POINTS[c]
              for w in ("before", "after")]


def test_each_command_makes_the_commits_its_kill_points_name(base, sample_patch_set, tmp_path, monkeypatch):
    """The premise of the kill cases, in-process: each command's case commits (``os.replace``) exactly
    :data:`COMMITS` times, so every kill point of :data:`KILL_POINTS` is reached."""
    from fakes import run_cli

    real, made = os.replace, []

    def replace(src, dst, *args, **kwargs):
        made.append(dst)
        return real(src, dst, *args, **kwargs)

    monkeypatch.setattr(os, "replace", replace)
    counted = {}
    for command in COMMITS:
        work = tmp_path / command
        work.mkdir()
        argv, _ = command_case(command, work, base, sample_patch_set)
        made.clear()
        code, _, err = run_cli(argv)
        assert code == 0, err
        counted[command] = len(made)
    assert counted == COMMITS


@pytest.mark.parametrize("command,nth,when,runner", [
    pytest.param(*case, "subprocess" if i == 0 else "forked", id=f"sigkill-{case[0]}-at-commit-{case[1]}-{case[2]}")
    for i, case in enumerate(KILL_CASES)])
def test_a_command_killed_at_a_commit_then_run_again_equals_a_clean_run(command, nth, when, runner, base,
                                                                         sample_patch_set, clean_results, tmp_path,
                                                                         request):
    """A case's runs are ``python`` subprocesses or forked from ``killing_server`` (``runner``). The clean runs
    they are compared with are subprocesses."""
    work = tmp_path / "w"
    work.mkdir()
    argv, out = command_case(command, work, base, sample_patch_set)
    forked = server_for(runner, request)
    # killed twice at a command's first commit (what the kills leave must not accumulate), once at a later one
    for _ in range(2 if nth == 1 else 1):
        killed = massviz(argv, work, kill_at=nth, when=when, forked=forked)
        assert killed.returncode != 0, f"{command} ended on its own before its commit {nth}: not killed (see COMMITS)"
        assert killed.returncode == -9, killed.stderr
    again = massviz(argv, work, forked=forked)
    assert again.returncode == 0, again.stderr
    assert "Traceback" not in again.stderr
    assert result(command, out) == clean_results(command)
    assert hidden(work) == [], "temporaries left by the killed runs were not swept"
    assert not any((work / "tmpdir").iterdir())


DAMAGE = {"truncated": lambda data: data[: len(data) // 2], "garbage": lambda data: os.urandom(len(data)),
          "empty": lambda data: b""}


@pytest.mark.parametrize("damage,runner", [pytest.param(d, "subprocess" if i == 0 else "forked", id=d)
                                           for i, d in enumerate(DAMAGE)])
def test_a_damaged_cache_entry_is_detected_recomputed_and_said_once(damage, runner, base, tmp_path, request):
    """A case's runs are subprocesses or forked from ``killing_server`` (``runner``; no kill)."""
    work = tmp_path / "w"
    work.mkdir()
    argv, out = command_case("estimate", work, base, tmp_path)
    forked = server_for(runner, request)
    first = massviz(argv, work, forked=forked)
    assert first.returncode == 0, first.stderr
    clean = result("estimate", out)
    (entry,) = (work / "cache").rglob("t*.npz")
    entry.write_bytes(DAMAGE[damage](entry.read_bytes()))
    again = massviz(argv, work, forked=forked)
    warnings = [line for line in again.stderr.splitlines() if "warning" in line]
    assert again.returncode == 0 and len(warnings) == 1, again.stderr
    assert warnings[0].startswith(f"massviz: warning: {entry}: damaged trace cache entry (")
    assert result("estimate", out) == clean
    third = massviz(argv, work, forked=forked)  # the entry was written again: no warning now
    assert third.returncode == 0 and "warning" not in third.stderr, third.stderr


# ====================================================================================================== concurrency
def _two_at_once(argv_a, argv_b, work: Path):
    env = {**clean_env(), "PYTHONPATH": str(ROOT)}
    procs = [subprocess.Popen([sys.executable, "-m", "massviz", *map(str, a)], cwd=work, env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for a in (argv_a, argv_b)]
    return [(p.wait(timeout=300), p.stderr.read()) for p in procs]


@pytest.mark.parametrize("command", ["extract", "cloud", "train", "log-rrd-dir"])
def test_two_processes_writing_the_same_output_leave_one_whole(command, base, sample_patch_set, clean_results, tmp_path):
    """Both succeed and the output is one run's, whole; or one says in one line why it did not write."""
    work = tmp_path / "w"
    work.mkdir()
    if command == "log-rrd-dir":
        rec = copy_sample(work / "rec")
        argv, out = pipeline(base, work, "log", rec, "--rrd-dir", work / "ds"), work / "ds"
    else:
        argv, out = command_case(command, work, base, sample_patch_set)
    runs = _two_at_once(argv, argv, work)
    for code, err in runs:
        assert "Traceback" not in err and "internal error" not in err, err
        errors = [line for line in err.splitlines() if ": error:" in line]
        assert code == 0 or (code == 2 and len(errors) == 1), (code, err)
    assert any(code == 0 for code, _ in runs), runs
    if command == "log-rrd-dir":
        assert sorted(os.listdir(out)) == ["index.csv", "patches", "patches.csv", "rec.rrd"] or \
            sorted(os.listdir(out))[:1] == ["cup_handover.rrd"] or "index.csv" in os.listdir(out), os.listdir(out)
    else:
        assert result(command, out) == clean_results(command)
    assert hidden(work) == []
