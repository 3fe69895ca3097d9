"""A ``massviz`` command in a process of its own, measured (peak resident memory, wall time, a time bound), and the
promise every hostile case run that way is held to (:func:`check_promise`).

The process is a real ``python -m massviz`` subprocess, or a child forked from a ``tests/forkserver.py`` server that
imported massviz and torch once (:func:`run_forked`: the same ``main``, environment, folder, files and exit).
"""
from __future__ import annotations

import contextlib
import os
import re
import signal
import stat
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from fakes import Base, visible_lines
from forkserver import ForkServer

ROOT = Path(__file__).resolve().parents[1]
#: peak resident memory a hostile case may reach (python + torch + the pipeline on 3 frames: ~0.5-0.7 GB; an
#: unbounded compression bomb reaches 1.9-2.5 GB).
MEM_BOUND_MB = 1200
#: wall time a case may take (a case takes 5-25 s on 2 busy cores; a hang is killed at this bound).
TIME_BOUND_S = 150
#: a non-finite number as text: what must never appear in an output or on the terminal.
NON_FINITE = re.compile(r"(?<![A-Za-z_])(nan|NaN|NAN|-?inf|-?Inf|-?Infinity)(?![A-Za-z_])")
#: characters that may appear raw on the terminal (everything else below 0x20, DEL and C1 must come escaped).
RAW_CONTROL = re.compile(r"[\x00-\x08\x0b\x0c\x0e-\x1f\x7f-\x9f\u202a-\u202e\u2066-\u2069]")


# ============================================================================================================ runner
@dataclass
class Run:
    code: int
    stdout: str
    stderr: str
    peak_mb: float
    seconds: float
    killed: bool = False
    signalled: bool = False  # ``send`` was sent while the process still ran


def clean_env() -> dict:
    """This process's environment without the variables that change what a command prints or which weights it
    loads (the case's own are added by the caller)."""
    return {k: v for k, v in os.environ.items() if k not in ("MASSVIZ_DEBUG", "MASSVIZ_WEIGHTS", "RUST_LOG")}


def run_massviz(argv, case_dir: Path, *, preexec: Callable | None = None, when: Callable[[], bool] | None = None,
                send: int | None = None, timeout: float = TIME_BOUND_S, forked: ForkServer | None = None) -> Run:
    """``python -m massviz ARGV`` in a subprocess with TMPDIR inside ``case_dir`` (checked empty after) and HOME too;
    its peak RSS (its VmHWM, sampled every 20 ms while it runs) and wall time are measured. With ``send``, the signal
    is sent as soon as ``when()`` holds (polled), i.e. while the command is writing. With ``forked`` (and no signal
    or ``preexec``) the process is forked from that server instead (``tests/forkserver.py``: the same ``main``,
    environment, folder and files, without the imports)."""
    env = clean_env()
    tmpdir = case_dir / "tmpdir"
    tmpdir.mkdir(exist_ok=True)
    # torch's own compile cache (``torch._dynamo``, which torchvision imports: Mask R-CNN, training) goes to
    # $TMPDIR/torchinductor_$USER unless TORCHINDUCTOR_CACHE_DIR says where; it is torch's, not a massviz temporary,
    # so it goes with the other caches (and is not inherited from this process, whose imports would decide it)
    env.update(TMPDIR=str(tmpdir), HOME=str(case_dir / "home"), PYTHONPATH=str(ROOT),
               MASSVIZ_CACHE_DIR=str(case_dir / "usercache"), XDG_CACHE_HOME=str(case_dir / "xdg"),
               TORCHINDUCTOR_CACHE_DIR=str(case_dir / "xdg" / "torchinductor"))
    logs = case_dir.parent / f"{case_dir.name}.logs"
    logs.mkdir(exist_ok=True)
    if forked is not None and preexec is None and send is None:
        return run_forked(forked, argv, case_dir, env, logs, timeout)
    with open(logs / "out", "wb") as fo, open(logs / "err", "wb") as fe:
        t0 = time.monotonic()
        proc = subprocess.Popen([sys.executable, "-m", "massviz", *map(str, argv)], stdout=fo, stderr=fe,
                                stdin=subprocess.DEVNULL, cwd=case_dir, env=env, preexec_fn=preexec)
        watch = Watch(proc.pid, t0, timeout)
        sent = []
        if send is not None:
            def signal_when_ready():
                while proc.returncode is None and time.monotonic() - t0 < timeout:
                    if when is None or (when(proc.pid) if getattr(when, "takes_pid", False) else when()):
                        proc.send_signal(send)
                        sent.append(1)
                        return
                    time.sleep(0.05)
            sender = threading.Thread(target=signal_when_ready, daemon=True)
            sender.start()
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
        seconds = time.monotonic() - t0
        watch.stop()
    return Run(proc.returncode, (logs / "out").read_text(errors="replace"), (logs / "err").read_text(errors="replace"),
               (watch.peak_kb or usage.ru_maxrss) / 1024, seconds, watch.killed, bool(sent))


def run_forked(server: ForkServer, argv, case_dir: Path, env: dict, logs: Path, timeout: float) -> Run:
    t0 = time.monotonic()
    watch = Watch(server.start(argv, env, case_dir, logs / "out", logs / "err"), t0, timeout)
    code = server.wait()
    watch.stop()
    return Run(code, (logs / "out").read_text(errors="replace"), (logs / "err").read_text(errors="replace"),
               watch.peak_kb / 1024, time.monotonic() - t0, watch.killed)


class Watch:
    """While a case's process ``pid`` runs: its VmHWM sampled every 20 ms (``peak_kb``: its own high-water mark;
    ru_maxrss after exec keeps the forking parent's, i.e. pytest's, peak: 1.5 GB in the full suite), and SIGKILL
    once ``timeout`` s have passed since ``t0`` (``killed``). ``stop()`` once the process has been waited for."""

    def __init__(self, pid: int, t0: float, timeout: float):
        self.peak_kb, self.killed = 0, False
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(pid, t0, timeout), daemon=True)
        self._thread.start()

    def _run(self, pid: int, t0: float, timeout: float) -> None:
        while not self._done.is_set():
            self.peak_kb = max(self.peak_kb, vm_hwm_kb(pid))
            if not self.killed and time.monotonic() - t0 > timeout:
                self.killed = True
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)
            self._done.wait(0.02)

    def stop(self) -> None:
        self._done.set()
        self._thread.join()


def vm_hwm_kb(pid: int) -> int:
    """Peak resident memory (kB) of the live process ``pid`` so far (/proc/PID/status VmHWM), 0 once it is gone."""
    try:
        m = re.search(r"^VmHWM:\s*(\d+) kB", Path(f"/proc/{pid}/status").read_text(), re.M)
    except OSError:
        return 0
    return int(m.group(1)) if m else 0


def folder_state(folder: Path, skip: tuple[Path, ...] = ()) -> dict[str, tuple[int, int, int]]:
    out = {}
    for p in sorted(folder.rglob("*")):
        if any(p == s or s in p.parents for s in skip):
            continue
        st = p.lstat()
        out[str(p.relative_to(folder))] = (stat.S_IFMT(st.st_mode), st.st_size if stat.S_ISREG(st.st_mode) else -1,
                                           st.st_mtime_ns)
    return out


def text_files(folder: Path):
    for p in folder.rglob("*"):
        if p.is_file() and not p.is_symlink() and p.suffix in (".csv", ".json", ".txt", ".log"):
            yield p


@dataclass
class Case:
    name: str
    argv: list
    culprit: object  # the path (or option) the error line must name first
    what: str  # regex the rest of the line must match
    outputs: list = field(default_factory=list)  # must not exist after
    code: int = 2
    line: str = "error"  # "error" or "interrupted"; "" for a case that must succeed (code 0, ``check`` its outputs)
    writes: tuple = ()  # folders the command may change (the cache)
    preexec: Callable | None = None
    when: Callable | None = None
    send: int | None = None
    check: Callable | None = None  # extra checks on (case, run)


def check_promise(case: Case, run: Run, work: Path, before: dict) -> None:
    """The promise every hostile case is held to (see the module docstring)."""
    both = run.stdout + run.stderr
    where = f"{case.name}: {run.stderr[-2000:]}"
    assert not run.killed and run.seconds < TIME_BOUND_S, f"{case.name}: took {run.seconds:.0f} s (killed)"
    assert run.peak_mb < MEM_BOUND_MB, f"{case.name}: peak memory {run.peak_mb:.0f} MB"
    assert "Traceback" not in both and "internal error" not in both, where
    assert not RAW_CONTROL.search(both), f"{case.name}: raw control character on the terminal: {both[-500:]!r}"
    assert run.code == case.code, f"exit {run.code}: {where}"
    lines = visible_lines(run.stderr)
    marker = ": error:" if case.line == "error" else ": interrupted"
    command = str(case.argv[0])
    if case.line:
        errors = [line for line in lines if marker in line]
        assert len(errors) == 1 and lines[-1] == errors[0], where
        prefix = f"massviz {command}{marker}" + ("" if case.line != "error" else f" {case.culprit}")
        assert errors[0].startswith(prefix), (errors[0], prefix)
        assert re.search(case.what, errors[0][len(prefix):]), (case.name, errors[0])
    else:  # a case that must end well (e.g. a live session ended by a signal): no error or interrupt line
        assert not [line for line in lines if re.match(rf"massviz {command}: (error|interrupted)", line)], where
    assert not NON_FINITE.search(run.stdout) and " nan g" not in both, where
    for out in case.outputs:
        assert not os.path.lexists(out) or Path(out).is_char_device() or Path(out).is_fifo() \
            or Path(out).is_symlink(), f"{case.name}: {out} was written"
    skip = tuple(work / w for w in ("cache", "usercache", "xdg", "home", "tmpdir")) + tuple(case.writes)
    after = folder_state(work, skip)
    assert after == before, (f"{case.name}: something was written, left or replaced: "
                             f"{sorted(set(after.items()) ^ set(before.items()))[:6]}")
    assert not any((work / "tmpdir").iterdir()), f"{case.name}: left files in TMPDIR"
    for p in text_files(work):
        if not any(s in p.parents for s in skip):
            assert not NON_FINITE.search(p.read_text(errors="replace")), f"{case.name}: non-finite number in {p}"
    if case.check is not None:
        case.check(case, run)


def pipeline_argv(work: Path, b: Base, command: str, rec: Path, *extra, weights=None, replay=None,
                  cache: bool = True) -> list:
    return [command, rec, *extra, "--detector", "replay", "--replay", replay or b.replay,
            "--weights", weights or b.weights, *(["--cache", work / "cache"] if cache else ["--no-cache"]), "--quiet"]
