"""What a new user meets first: the figures' colours and labels and the command line's messages.

The command-line tests run ``python -m massviz`` as a user would and check the exit code, the one error line and that
nothing was written.
"""
from __future__ import annotations

import itertools
import os
import subprocess
import sys
from pathlib import Path

import nbformat
import numpy as np
import pytest

from fakes import run_cli_as_user
from support import WEIGHTS, no_other_ray
from support import sample_cache as fill_sample_cache

ROOT = Path(__file__).resolve().parents[1]


# ------------------------------------------------------------------------------------------ item 5: the figures
@pytest.fixture(scope="module")
def cup(tmp_path_factory, shared_dir, samples_dir):
    from massviz.app import process_recordings
    from massviz.io.recording import open_recording

    cache = fill_sample_cache(tmp_path_factory, shared_dir, samples_dir)
    rec = open_recording(samples_dir / "cup_handover")
    [trace] = process_recordings([rec], detector="depth", weights=str(shared_dir / WEIGHTS), cache=str(cache),
                                 threshold=0.4, quiet=True)
    return rec, trace


def _scatter_colours(fig) -> np.ndarray:
    [ax] = fig.axes
    [points] = ax.collections
    return np.asarray(points.get_facecolors())[:, :3]


def _count(colours: np.ndarray, colour) -> int:
    return int((np.abs(colours - np.asarray(colour)) < 1e-3).all(axis=1).sum())


@pytest.mark.slow  # more than ~3 s on 2 idle cores (a massviz subprocess or a pipeline run)
def test_point_cloud_figure_colours_by_the_palette(cup):
    """A chosen patch's mask in the chosen colour, a flagged one in the flagged colour (not magenta as well)."""
    from massviz.views import plots
    from massviz.views.palette import CHOSEN_COLOUR, FLAGGED_COLOUR

    rec, trace = cup
    flagged = {p.detection for p in trace.flags.flagged}
    assert flagged, "the cup_handover sample should have flagged patches (the pitcher)"
    frames = {int(trace.detections.frame[i]): [] for i in trace.selection}
    for i in trace.selection:
        frames[int(trace.detections.frame[i])].append(int(i) in flagged)
    only_flagged = next(f for f, fl in frames.items() if all(fl))
    only_chosen = next(f for f, fl in frames.items() if not any(fl))
    for frame_index, flagged_there in ((only_flagged, True), (only_chosen, False)):
        fig = plots.point_cloud_figure(trace, rec.read_frame(frame_index), rec.intrinsics)
        colours = _scatter_colours(fig)
        red, magenta = _count(colours, FLAGGED_COLOUR), _count(colours, CHOSEN_COLOUR)
        if flagged_there:
            assert red > 50 and magenta == 0, (frame_index, red, magenta)
        else:
            assert magenta > 50 and red == 0, (frame_index, red, magenta)
        assert "flagged in red" in fig.axes[0].get_title()


def _overlap(a, b) -> bool:
    return a.x0 < b.x1 and b.x0 < a.x1 and a.y0 < b.y1 and b.y0 < a.y1


def test_point_cloud_figure_labels_do_not_overlap(cup):
    from massviz.views import plots

    rec, trace = cup
    fig = plots.point_cloud_figure(trace, rec.read_frame(plots.best_frame(trace)), rec.intrinsics)
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    renderer = canvas.get_renderer()
    [ax] = fig.axes
    for axis in (ax.xaxis, ax.yaxis, ax.zaxis):
        ticks = [t.get_window_extent(renderer) for t in axis.get_ticklabels() if t.get_visible() and t.get_text()]
        assert len(ticks) >= 2
        for a, b in itertools.combinations(ticks, 2):
            assert not _overlap(a, b), f"{axis.axis_name} tick labels overlap"
        label = axis.label.get_window_extent(renderer)
        assert not any(_overlap(label, t) for t in ticks), f"{axis.axis_name} label overlaps its tick labels"


def test_notebook_01_names_the_palette_colours():
    text = "\n".join(c.source for c in nbformat.read(ROOT / "notebooks" / "01_inspect_recording.ipynb", 4).cells
                     if c.cell_type == "markdown")
    assert "yellow" not in text
    cloud = text[text.index("## The depth as a point cloud"):]
    assert "magenta" in cloud.split("##")[1] and "red" in cloud.split("##")[1]


# ------------------------------------------------------------------------------- item 9: the command line's messages
def massviz_cli(*args, cwd: Path = ROOT, env_extra: dict | None = None, timeout: float = 900):
    env = {k: v for k, v in os.environ.items() if k not in ("MASSVIZ_DEBUG", "RAY_ADDRESS")}
    env.update({"PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
                "PYTHONWARNINGS": "ignore", **(env_extra or {})})
    return subprocess.run([sys.executable, "-m", "massviz", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, cwd=cwd, env=env)


def error_lines(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if "error" in line.lower()]


@pytest.mark.parametrize("command, out", [("cloud", "clouds"), ("render", "scene.png")])
def test_3d_commands_without_intrinsics_exit_2_up_front_and_write_nothing(command, out, samples_dir, tmp_path):
    """``cloud`` and ``render`` need the intrinsics: without them one line before any work (the weights, which do
    not exist here, are never loaded; ``render`` ran the whole pipeline, ~3.6 s, then failed with a warning's text)."""
    import shutil

    rec = tmp_path / "no_intrinsics"
    shutil.copytree(samples_dir / "cup_handover", rec)
    (rec / "intrinsics.json").unlink()
    out = tmp_path / out
    run = run_cli_as_user(command, rec, "--detector", "depth", "--out", out, "--no-cache", "--quiet",
                          "--weights", tmp_path / "missing.torch")
    assert run.returncode == 2, (run.returncode, run.stderr)
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and "no_intrinsics" in lines[0], lines
    assert f"no camera intrinsics (intrinsics.json in the recording folder): massviz {command} needs them" in lines[0]
    assert "Traceback" not in run.stderr and not out.exists()


def test_score_per_container_table_has_no_nan(tmp_path):
    ann, pred = tmp_path / "ann.csv", tmp_path / "pred.csv"
    ann.write_text("id,container id,container mass\n0,1,10\n1,1,12\n2,5,30\n3,9,100\n")
    pred.write_text("Configuration ID,Container mass\n0,11\n1,-1\n2,-1\n3,-1\n")  # containers 5, 9: none estimated
    run = run_cli_as_user("score", pred, "--annotations", ann)
    assert run.returncode == 0, run.stderr
    assert "per container:" in run.stdout and "nan" not in run.stdout.lower(), run.stdout
    rows = run.stdout.split("per container:")[1].strip().splitlines()[1:]
    assert len(rows) == 3 and rows[1].split()[-1] == "-" and rows[0].split()[-1] == "0.100", rows


@pytest.mark.slow
def test_ray_error_names_massviz_option(samples_dir, tmp_path, shared_dir, tmp_path_factory):
    pytest.importorskip("ray")
    (tmp_path / "raytmp").mkdir()  # no Ray cluster recorded there: "auto" finds none by its files
    with no_other_ray(tmp_path_factory):  # nor by its processes: no test_runners cluster is up meanwhile
        run = massviz_cli("estimate", samples_dir, "--detector", "depth", "--engine", "ray", "--ray-address", "auto",
                          "--out", tmp_path / "x.csv", "--quiet", "--no-cache", cwd=tmp_path,
                          env_extra={"RAY_TMPDIR": str(tmp_path / "raytmp"),
                                     "MASSVIZ_WEIGHTS": str(shared_dir / WEIGHTS)})
    assert run.returncode == 2, run.stderr
    [line] = error_lines(run.stderr)
    assert "--ray-address" in line and "`--address`" not in line and "RAY_ADDRESS" not in line, line
    assert not (tmp_path / "x.csv").exists()


@pytest.mark.slow
def test_extract_error_names_the_real_file(tmp_path, shared_dir):
    from fakes import make_ccm

    video = make_ccm(tmp_path / "ccm")
    out = tmp_path / "patches"
    run = massviz_cli("extract", video, "--detector", "depth", "--out", out, "--no-cache", "--quiet",
                      env_extra={"MASSVIZ_WEIGHTS": str(shared_dir / WEIGHTS)})
    assert run.returncode == 2, run.stderr
    [line] = error_lines(run.stderr)
    assert str(video) in line and "000000.mp4/" not in line and "--annotations" in line, line
    assert not out.exists()


@pytest.mark.slow
def test_live_summary_says_how_many_of_k(samples_dir, shared_dir, tmp_path):
    from fakes import need_realsense

    need_realsense()
    from fakes import write_recording
    from massviz.io.formats.realsense_write import write_realsense
    from massviz.io.recording import open_recording

    sample = open_recording(samples_dir / "cup_handover")
    frames = list(sample.frames(indices=[30, 31, 32]))
    short = write_recording(tmp_path / "short", [f.rgb for f in frames], [f.depth for f in frames],
                            intrinsics=sample.intrinsics.to_dict(), meta={"id": "short", "fps": 10})
    db3 = write_realsense(open_recording(short), tmp_path / "short.db3")
    run = massviz_cli("live", "--file", db3, "--detector", "depth", "--k", 50, "--no-cache", "--quiet",
                      "--rrd", tmp_path / "live.rrd", env_extra={"MASSVIZ_WEIGHTS": str(shared_dir / WEIGHTS)})
    assert run.returncode == 0, run.stderr
    last = run.stderr.strip().splitlines()[-1]
    import re

    m = re.search(r"\((\d+) of K=50, ", last)  # 3 frames cannot give 50 detections
    assert m and 1 <= int(m.group(1)) < 50, last


# ----------------------------------------------------------------------------- item 10: a CPU-only install
FAKE_PYTHON = """#!/usr/bin/env bash
echo "python $*" >> "$FAKE_LOG"
case "$*" in *"import torch"*) echo "${FAKE_CUDA:-}" ;; esac
exit 0
"""


def run_setup(tmp_path: Path, torch_kind: str | None, cuda: str = "") -> tuple[subprocess.CompletedProcess, list[str]]:
    """scripts/setup.sh demo in a copy of the repository whose .venv, dpkg and massviz are stand-ins that log what
    they were asked (nothing is installed)."""
    repo = tmp_path / "repo"
    (repo / "scripts").mkdir(parents=True)
    (repo / "scripts" / "setup.sh").write_text((ROOT / "scripts" / "setup.sh").read_text())
    for name in ("pyproject.toml", "constraints.txt"):
        (repo / name).write_text((ROOT / name).read_text())
    bins = {repo / ".venv" / "bin" / "python": FAKE_PYTHON,
            repo / ".venv" / "bin" / "massviz": '#!/usr/bin/env bash\necho "massviz $*" >> "$FAKE_LOG"\n',
            tmp_path / "fakebin" / "dpkg": "#!/usr/bin/env bash\nexit 0\n"}
    for path, text in bins.items():
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
        path.chmod(0o755)
    log = tmp_path / "calls.log"
    log.write_text("")
    env = {k: v for k, v in os.environ.items() if k != "MASSVIZ_TORCH"}
    env.update(FAKE_LOG=str(log), FAKE_CUDA=cuda, PYTHON=sys.executable,
               PATH=os.pathsep.join([str(tmp_path / "fakebin"), env.get("PATH", "")]))
    if torch_kind is not None:
        env["MASSVIZ_TORCH"] = torch_kind
    run = subprocess.run(["bash", "scripts/setup.sh", "demo"], cwd=repo, env=env, capture_output=True, text=True,
                         timeout=120)
    return run, log.read_text().splitlines()


def test_setup_cpu_torch_comes_from_the_cpu_index_first(tmp_path):
    run, calls = run_setup(tmp_path, "cpu")
    assert run.returncode == 0, run.stderr
    pip = [c for c in calls if " pip install " in c]
    assert "--index-url https://download.pytorch.org/whl/cpu torch==2.14.1 torchvision==0.29.1" in pip[0], pip
    assert "-c constraints.txt -e .[test,notebooks]" in pip[1] and "--index-url" not in pip[1], pip
    assert "warning" not in run.stderr


def test_setup_default_is_what_ci_uses(tmp_path):
    run, calls = run_setup(tmp_path, None)
    assert run.returncode == 0, run.stderr
    pip = [c for c in calls if " pip install " in c]
    assert len(pip) == 1 and "-c constraints.txt -e .[test,notebooks]" in pip[0] and "--index-url" not in pip[0], pip


def test_setup_cpu_says_when_it_got_a_cuda_torch(tmp_path):
    run, _ = run_setup(tmp_path, "cpu", cuda="13.0")
    assert run.returncode == 0 and "built for CUDA 13.0" in run.stderr, run.stderr


def test_setup_bad_torch_choice_is_one_line_before_any_work(tmp_path):
    run, calls = run_setup(tmp_path, "rocm")
    assert run.returncode == 2 and run.stderr.strip().count("\n") == 0 and "MASSVIZ_TORCH" in run.stderr
    assert calls == []


def test_readme_setup_stays_two_commands_and_documents_cpu():
    text = (ROOT / "README.md").read_text()
    section = text.split("## Set-up", 1)[1].split("\n## ", 1)[0]
    block = section.split("```bash\n", 1)[1].split("```", 1)[0]
    assert [line.split("#")[0].strip() for line in block.strip().splitlines()] == [
        "bash scripts/setup.sh demo", "bash scripts/setup.sh test"]
    assert "MASSVIZ_TORCH=cpu" in section


# ------------------------------------------------------------------------- examples whose next command never runs
#: commands that run until Ctrl-C: ``A && B`` after one of them never runs B
UNTIL_STOPPED = ("massviz serve", "massviz view")


def _help_texts() -> dict[str, str]:
    import argparse

    from massviz.cli import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return {name: p.format_help() for name, p in sub.choices.items()}


def test_no_example_chains_a_command_after_one_that_runs_until_stopped():
    """``massviz serve … && rerun …`` (serve --help's example) never ran the second command: serve runs until
    Ctrl-C. No --help text nor the README chains anything after such a command (or after a live session with no end:
    no --duration, no --file)."""
    texts = {**{f"massviz {n} --help": t for n, t in _help_texts().items()},
             **{p.relative_to(ROOT).as_posix(): p.read_text() for p in [ROOT / "README.md",
                                                                          *(ROOT / "docs").glob("*.md")]}}
    bad = []
    for where, text in texts.items():
        for line in text.splitlines():
            for first in line.split("&&")[:-1]:
                cmd = first.split("$ ")[-1].strip().strip("`")
                endless_live = cmd.startswith("massviz live") and "--duration" not in cmd and "--file" not in cmd
                if cmd.startswith(UNTIL_STOPPED) or endless_live:
                    bad.append(f"{where}: {line.strip()}")
    assert not bad, bad
