"""The test floor itself: conftest's guard ends and reports a process a test leaves behind (also an orphan whose
parent has exited, as a server behind a wrapper would be), and passes a session that ends what it starts; a test not
marked ``slow`` that starts a massviz process fails before the process starts."""
from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

psutil = pytest.importorskip("psutil")
TESTS = Path(__file__).resolve().parent

INNER_CONFTEST = f"""
import importlib.util, sys
sys.path.insert(0, {str(TESTS)!r})
spec = importlib.util.spec_from_file_location("massviz_conftest", {str(TESTS / "conftest.py")!r})
mod = importlib.util.module_from_spec(spec)
spec.loader.exec_module(mod)
no_process_outlives_the_suite = mod.no_process_outlives_the_suite
"""


def inner_session(tmp_path: Path, body: str) -> subprocess.CompletedProcess:
    (tmp_path / "conftest.py").write_text(INNER_CONFTEST)
    (tmp_path / "test_inner.py").write_text(textwrap.dedent(body))
    return subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "no:dash",
                           "--rootdir", str(tmp_path), str(tmp_path / "test_inner.py")], cwd=tmp_path,
                          capture_output=True, text=True, timeout=120)


@pytest.mark.slow
def test_a_leaked_orphan_is_an_error_and_is_ended(tmp_path):
    pid_file = tmp_path / "orphan.pid"
    run = inner_session(tmp_path, f"""
        import subprocess

        def test_leaves_a_server_behind():
            # the shell exits at once: its background child is an orphan (as a wrapper's server was)
            subprocess.run(["sh", "-c", "sleep 300 >/dev/null 2>&1 & echo $! > {pid_file}"], check=True)
    """)
    out = run.stdout + run.stderr
    assert run.returncode != 0, out
    assert "1 passed, 1 error" in out and "outlived them (ended now)" in out and "sleep 300" in out, out
    pid = int(pid_file.read_text())
    assert not psutil.pid_exists(pid) or psutil.Process(pid).status() == psutil.STATUS_ZOMBIE


@pytest.mark.slow
def test_a_session_that_ends_its_processes_passes(tmp_path):
    run = inner_session(tmp_path, """
        import subprocess

        def test_starts_and_ends_a_server():
            proc = subprocess.Popen(["sleep", "300"])
            proc.terminate()
            proc.wait()
    """)
    assert run.returncode == 0 and "1 passed" in run.stdout and "error" not in run.stdout, run.stdout + run.stderr



@pytest.mark.parametrize("argv", [["-m", "massviz", "--help"], ["massviz", "--version"],
                                  ["-c", "import sys\nfrom massviz.cli import main\nsys.exit(main(['--help']))"],
                                  [str(TESTS / "forkserver.py")]],
                         ids=["python-m-massviz", "console-script", "python-c-main", "fork-server"])
def test_a_fast_test_that_starts_massviz_fails(argv):
    """conftest's ``fast_tests_start_no_massviz``: this test is not marked slow, so starting a massviz process fails
    it (``pytest.fail``, before anything is started); a Python process that only imports massviz is not a command."""
    cmd = argv if argv[0] == "massviz" else [sys.executable, *argv]
    with pytest.raises(pytest.fail.Exception, match="is not marked slow but starts a massviz process"):
        subprocess.run(cmd, capture_output=True, timeout=60)
    assert subprocess.run([sys.executable, "-c", "import massviz.cli"], timeout=60).returncode == 0
