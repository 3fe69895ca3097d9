"""Every fenced code block of README.md and docs/*.md runs, or says right above it why it cannot run here.

* A ```text block is a diagram and holds no command. A block preceded by ``<!-- not run: REASON -->`` (the line right above its fence) is not run; REASON must be one of
  ``REASONS`` and the block must show it (``REASONS`` maps each reason to what the block then contains: a CCM path, a
  camera, a command that runs until stopped...).
* ``json`` blocks must parse.
* ``python`` blocks are executed, each in a fresh interpreter in a temporary folder holding ``data_samples`` (a link to
  the bundled samples), with ``$MASSVIZ_WEIGHTS`` pointing at the reference weights and the session's trace cache,
  after the shell blocks ran there (a block may read what a documented command wrote, e.g. ``out/samples``).
* ``bash``/``console``/``sh`` blocks: every line is a ``massviz`` command (console: the ``$ `` lines; ``\\``
  continuations joined), run through the CLI in that folder (each distinct command once, two at a time) and must
  exit 0.
* Every ``massviz`` command of any block and of an inline code span names an existing command and only options that
  command's ``--help`` lists.
"""
from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from support import WEIGHTS
from support import sample_cache as fill_sample_cache

ROOT = Path(__file__).resolve().parents[1]
SHELL = ("bash", "sh", "console", "shell")
#: why a block may not run here, and what a block with that reason must contain
REASONS = {
    "needs a CUDA GPU": r"cuda",
    "needs a RealSense camera": r"massviz live",
    "needs a display": r"view3d|\brerun (?!rrd)",
    "needs the network": r"https?://|pip install",
    "needs the CCM dataset": r"/data/CCM|_annotations?\w*\.csv|Visual_\w+\.csv|F\d\.csv",
    "runs until stopped": r"massviz (serve|view)\b|jupyter lab",
    "takes minutes": r"massviz train|--detector maskrcnn",
    "installs software": r"setup\.sh|pip install",
}
NOT_RUN = re.compile(r"<!-- not run: (.*?) -->\s*$")


def pages() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def blocks(path: Path) -> list[dict]:
    """The fenced blocks of ``path``: ``lang``, ``code``, ``line`` (of the fence), ``reason`` (its not-run note)."""
    text, out = path.read_text(), []
    for m in re.finditer(r"^```(\w*)\n(.*?)^```", text, re.S | re.M):
        line = text[:m.start()].count("\n") + 1
        above = text[:m.start()].rstrip("\n").rsplit("\n", 1)[-1]
        note = NOT_RUN.search(above)
        out.append({"page": path.relative_to(ROOT).as_posix(), "line": line, "lang": m.group(1),
                    "code": m.group(2), "reason": note.group(1) if note else None})
    return out


ALL = [b for p in pages() for b in blocks(p)]


def where(b: dict) -> str:
    return f"{b['page']}:{b['line']}"


def shell_lines(code: str) -> list[str]:
    """The commands of a shell block (console: its ``$ `` lines), continuations joined, comments dropped."""
    console = any(line.startswith("$ ") for line in code.splitlines())
    out = []
    for line in re.sub(r"\\\n\s*", " ", code).splitlines():
        if console:
            if not line.startswith("$ "):
                continue  # output
            line = line[2:]
        line = line.split(" #", 1)[0].strip()
        if line and not line.startswith("#"):
            out.append(line)
    return out


def words(command: str) -> list[str]:
    return shlex.split(command)


def _subparsers(parser):
    import argparse

    return next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)


def check_options(command: str) -> list[str]:
    """What is wrong with a documented command: an unknown command or an option its --help does not list."""
    from massviz.cli import build_parser

    # [optional parts] are still options; "a | b" alternatives and "..." are placeholders
    argv = [w for w in shlex.split(command.replace("[", " ").replace("]", " ").replace("|", " ")) if w != "..."][1:]
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
                problems.append(f"`{' '.join(path)}` has no option {flag} ({command})")
    return problems


def documented_commands() -> list[tuple[str, str]]:
    """(where, command) of every ``massviz`` command in a shell block or an inline code span."""
    out = [(where(b), c) for b in ALL if b["lang"] in SHELL for c in shell_lines(b["code"]) if c.startswith("massviz ")]
    for path in pages():
        text = path.read_text()
        for m in re.finditer(r"`(massviz [a-z0-9]+[^`]*)`", text):
            out.append((f"{path.relative_to(ROOT).as_posix()}:{text[:m.start()].count(chr(10)) + 1}", m.group(1)))
    return out


def test_the_pages_have_blocks_and_every_block_is_run_or_says_why_not():
    assert len(ALL) >= 15 and any(b["lang"] == "python" for b in ALL), "the docs' code blocks were not found"
    bad = []
    for b in ALL:
        if b["reason"] is not None:
            pattern = REASONS.get(b["reason"])
            if pattern is None:
                bad.append(f"{where(b)}: 'not run: {b['reason']}' is none of {sorted(REASONS)}")
            elif not re.search(pattern, b["code"]):
                bad.append(f"{where(b)}: 'not run: {b['reason']}', but the block shows no sign of it")
        elif b["lang"] in SHELL:
            bad += [f"{where(b)}: `{c}` is not a massviz command: run it or say why not"
                    for c in shell_lines(b["code"]) if not c.startswith("massviz ")]
        elif b["lang"] == "text":  # a diagram: it must hold no command a reader would copy
            if re.search(r"^\s*(\$ |massviz |python|import |from \w+ import)", b["code"], re.M):
                bad.append(f"{where(b)}: a ```text block holds a command: make it a shell or python block")
        elif b["lang"] not in ("python", "json"):
            bad.append(f"{where(b)}: a ```{b['lang']} block is neither run nor said why not")
    assert not bad, "\n".join(bad)
    not_run = [f"{where(b)}: {b['reason']}" for b in ALL if b["reason"]]
    print(f"{len(ALL)} blocks, {len(not_run)} not run here:\n  " + "\n  ".join(not_run))


def test_the_not_run_check_can_fail():
    assert not re.search(REASONS["needs the CCM dataset"], "massviz estimate data_samples --out x.csv")
    assert re.search(REASONS["runs until stopped"], "$ massviz serve out/samples")
    assert NOT_RUN.search("<!-- not run: needs a display -->").group(1) == "needs a display"


@pytest.mark.parametrize("at,command", documented_commands(), ids=lambda v: str(v)[:60])
def test_documented_command_options_exist(at, command):
    assert not check_options(command), f"{at}: {check_options(command)}"


def test_option_check_can_fail():
    assert check_options("massviz estimate data_samples --no-such-flag")
    assert check_options("massviz nonsense --out x")
    assert not check_options("massviz estimate data_samples --detector depth --out preds.csv")


@pytest.mark.parametrize("b", [b for b in ALL if b["lang"] == "json" and not b["reason"]], ids=where)
def test_json_block_parses(b):
    json.loads(b["code"])


@pytest.fixture(scope="module")
def workdir(tmp_path_factory, shared_dir, samples_dir):
    """A user's folder: data_samples beside, the reference weights in $MASSVIZ_WEIGHTS, the session's trace cache."""
    cache = fill_sample_cache(tmp_path_factory, shared_dir, samples_dir)
    root = tmp_path_factory.mktemp("docs")
    (root / "data_samples").symlink_to(samples_dir)
    env = {**os.environ, "MASSVIZ_WEIGHTS": str(shared_dir / WEIGHTS), "MASSVIZ_CACHE_DIR": str(cache),
           "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
           "PYTHONWARNINGS": "ignore", "MPLBACKEND": "Agg"}
    return root, env


@pytest.mark.slow
def test_shell_blocks_run(workdir):
    """The shell blocks' massviz commands, each distinct one once (README's quickstart repeats some): a block's
    commands in order (a later one may read an earlier one's output), two blocks at a time."""
    from concurrent.futures import ThreadPoolExecutor

    root, env = workdir
    commands, seen = {}, set()
    for b in ALL:
        if b["lang"] in SHELL and not b["reason"]:
            todo = [c for c in shell_lines(b["code"]) if c not in seen]
            seen.update(todo)
            if todo:
                commands[where(b)] = todo

    def run(at: str) -> str | None:
        for command in commands[at]:
            done = subprocess.run([sys.executable, "-m", "massviz", *words(command)[1:]], cwd=root, env=env,
                                  capture_output=True, text=True, timeout=300)
            if done.returncode != 0:
                return f"{at}: `{command}` exited {done.returncode}:\n{done.stderr[-1500:]}"
        return None

    assert commands, "no shell block to run"
    with ThreadPoolExecutor(2) as pool:
        failed = [f for f in pool.map(run, commands) if f]
    assert not failed, "\n".join(failed)


@pytest.mark.slow
@pytest.mark.parametrize("b", [b for b in ALL if b["lang"] == "python" and not b["reason"]], ids=where)
def test_python_block_runs(workdir, b):
    root, env = workdir
    script = root / f"block_{b['page'].replace('/', '_')}_{b['line']}.py"
    script.write_text(b["code"])
    run = subprocess.run([sys.executable, str(script)], cwd=root, env=env, capture_output=True, text=True,
                         timeout=120)
    assert run.returncode == 0, f"{where(b)}: the python block failed:\n{run.stderr[-3000:]}"


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces as hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def anchors(path: Path) -> set[str]:
    text = re.sub(r"^```.*?^```", "", path.read_text(), flags=re.S | re.M)
    return {slug(m.group(1)) for m in re.finditer(r"^#+ (.*)$", text, re.M)}


def test_links_between_the_pages_resolve():
    """Every ``](#anchor)`` names a heading of its page, every ``](page.md#anchor)`` one of that page, and every
    picture a file: the sections moved between README and docs/ keep their links."""
    bad = []
    for path in pages():
        for m in re.finditer(r"\]\(([^)\s]+)\)", path.read_text()):
            target = m.group(1)
            if re.match(r"[a-z+]+:", target):
                continue  # a web address
            file, _, anchor = target.partition("#")
            dest = (path.parent / file).resolve() if file else path
            if file and not file.endswith(".md") and not dest.is_file():
                bad.append(f"{path.name}: {target}: no such file")
            elif anchor and dest.is_file() and anchor not in anchors(dest):
                bad.append(f"{path.name}: {target}: no such heading")
    assert not bad, "\n".join(bad)
    assert slug("Live: RealSense cameras and recordings") == "live-realsense-cameras-and-recordings"
    assert slug("Training: extract → train → estimate") == "training-extract--train--estimate"
