"""Every code block of README.md runs. The test reads whatever blocks README has:

* ``python`` blocks are executed, each in a fresh interpreter in a temporary folder holding ``data_samples`` (a link to
  the bundled samples), with ``$MASSVIZ_WEIGHTS`` pointing at the reference weights and the session's trace cache;
* every ``massviz ...`` command of a ``bash``/``console``/``sh`` block (``$ massviz ...`` in console blocks, with ``\\``
  continuations) and of an inline code span must name an existing command and only options that command's
  ``--help`` lists;
* the block commands whose inputs are the bundled samples (and that need no display, camera, server or dataset) are
  run through the CLI in that folder and must exit 0.
"""
from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
from sample_traces import WEIGHTS, sample_cache

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
SHELL = ("bash", "sh", "console", "shell")
#: commands never run here (a window, a camera, a server that runs until stopped, training)
NOT_RUN = {"view3d", "live", "serve", "train"}


def blocks(lang: tuple[str, ...]) -> list[tuple[int, str]]:
    """(line number, code) of README's fenced blocks in one of ``lang``."""
    out, text = [], README.read_text()
    for m in re.finditer(r"^```(\w*)\n(.*?)^```", text, re.S | re.M):
        if m.group(1) in lang:
            out.append((text[:m.start()].count("\n") + 1, m.group(2)))
    return out


def block_commands() -> list[tuple[int, str]]:
    """(line, command) of every ``massviz`` command in README's shell blocks (continuations joined)."""
    out = []
    for line_no, code in blocks(SHELL):
        console = any(line.startswith("$ ") for line in code.splitlines())
        joined = re.sub(r"\\\n\s*", " ", code)
        for k, line in enumerate(joined.splitlines()):
            if console:
                if not line.startswith("$ "):
                    continue  # output
                line = line[2:]
            line = line.split(" #", 1)[0].strip()
            if line.startswith("massviz "):
                out.append((line_no + 1 + k, line))
    return out


def inline_commands() -> list[tuple[int, str]]:
    text = README.read_text()
    out = []
    for m in re.finditer(r"`(massviz [a-z0-9]+[^`]*)`", text):
        out.append((text[:m.start()].count("\n") + 1, m.group(1)))
    return out


def words(command: str) -> list[str]:
    # [optional parts] are still options of the command; "a | b" alternatives and "..." are placeholders
    return [w for w in shlex.split(command.replace("[", " ").replace("]", " ").replace("|", " ")) if w != "..."]


def _subparsers(parser):
    import argparse

    return next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)


def check_options(command: str) -> list[str]:
    """What is wrong with a README command: an unknown command or an option its --help does not list."""
    from massviz.cli import build_parser

    argv = words(command)[1:]
    parser, problems, path = build_parser(), [], ["massviz"]
    while argv and (sub := _subparsers(parser)) is not None and not argv[0].startswith("-"):
        name = argv.pop(0)
        if name not in sub.choices:
            return [f"{' '.join(path)}: no command {name!r}"]
        parser = sub.choices[name]
        path.append(name)
    if len(path) == 1:
        return [f"no command in {command!r}"]
    helptext = parser.format_help()
    for w in argv:
        if w.startswith("--"):
            flag = w.split("=", 1)[0]
            if flag not in parser._option_string_actions or flag not in helptext:
                problems.append(f"`{' '.join(path)}` has no option {flag} (README: {command})")
    return problems


COMMANDS = block_commands()


def test_readme_has_commands_and_python():
    assert len(COMMANDS) >= 10 and blocks(("python",)), "README's code blocks were not found"


@pytest.mark.parametrize("line,command", COMMANDS + inline_commands(), ids=lambda v: str(v)[:60])
def test_readme_command_options_exist(line, command):
    assert not check_options(command), f"README.md:{line}: {check_options(command)}"


def test_option_check_can_fail():
    assert check_options("massviz estimate data_samples --no-such-flag")
    assert check_options("massviz nonsense --out x")
    assert check_options("massviz cloud REC --ray-address auto")
    assert not check_options("massviz estimate data_samples --detector depth --out preds.csv")


@pytest.fixture(scope="module")
def workdir(tmp_path_factory, shared_dir, samples_dir):
    """A user's folder: data_samples beside, the reference weights in $MASSVIZ_WEIGHTS, the session's trace cache."""
    cache = sample_cache(tmp_path_factory, shared_dir, samples_dir)
    root = tmp_path_factory.mktemp("readme")
    (root / "data_samples").symlink_to(samples_dir)
    env = {**os.environ, "MASSVIZ_WEIGHTS": str(shared_dir / WEIGHTS), "MASSVIZ_CACHE_DIR": str(cache),
           "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
           "PYTHONWARNINGS": "ignore", "MPLBACKEND": "Agg"}
    return root, env


@pytest.mark.slow
@pytest.mark.parametrize("line,code", blocks(("python",)), ids=lambda v: str(v)[:40])
def test_readme_python_block_runs(workdir, line, code):
    root, env = workdir
    script = root / f"readme_{line}.py"
    script.write_text(code)
    run = subprocess.run([sys.executable, str(script)], cwd=root, env=env, capture_output=True, text=True,
                         timeout=900)
    assert run.returncode == 0, f"README.md:{line}: the python block failed:\n{run.stderr[-3000:]}"


def runnable(command: str) -> bool:
    """Runs here: reads the bundled samples, no absolute path (a user's dataset), no placeholder (REC, N), and
    ends by itself."""
    argv = words(command)
    if argv[1] in NOT_RUN or any(re.fullmatch(r"[A-Z][A-Z0-9_]*", w) for w in argv[2:]):
        return False
    return any(w.startswith("data_samples") for w in argv) and not any(w.startswith("/") for w in argv)


def test_runnable_selection():
    assert runnable("massviz estimate data_samples/cup_handover --detector depth --out preds.csv")
    assert not runnable("massviz estimate /data/CCM/test --out test.csv")
    assert not runnable("massviz view3d data_samples/glass_handover --detector depth")
    assert not runnable("massviz log REC --rrd out.rrd")


@pytest.mark.slow
@pytest.mark.parametrize("line,command", [c for c in COMMANDS if runnable(c[1])], ids=lambda v: str(v)[:60])
def test_readme_sample_command_runs(workdir, line, command):
    root, env = workdir
    argv = [a for a in words(command)[1:]]
    run = subprocess.run([sys.executable, "-m", "massviz", *argv], cwd=root, env=env, capture_output=True,
                         text=True, timeout=900)
    assert run.returncode == 0, f"README.md:{line}: `{command}` exited {run.returncode}:\n{run.stderr[-2000:]}"
