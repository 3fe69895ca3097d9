"""A fork server for running ``massviz`` many times in a test: one process imports massviz, torch and OpenCV once,
then forks one child per command. The child is a fresh process as far as a command can tell: it gets the request's
environment, working folder, stdin (/dev/null), stdout and stderr files and argv, runs :func:`massviz.cli.main`
(what ``python -m massviz`` runs once it has imported it) and exits as the interpreter does (the exit code, atexit
handlers, flushes) without tearing down the modules it did not import itself. What it does not repeat is the 1-3 s of
imports (torch is most of it), the point of it: the hostile-input tests run ~140 commands.

Protocol (the test's side is :class:`ForkServer`): one JSON request per line on the server's stdin
(``argv``, ``env``, ``cwd``, ``stdout``, ``stderr``: paths); the server answers on its reply pipe with one line
``{"pid": ...}`` as soon as the child runs, then one line ``{"status": ...}`` (``os.wait4``'s raw status) when it
has ended. End of stdin ends the server.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _child(request: dict) -> int:
    """In the forked child: become the command's process, run it, return its exit code. (It keeps the server's
    reply pipe open and never writes to it: closing it here would leave the server's file object to close a
    descriptor number the command may have reused.)"""
    os.environ.clear()
    os.environ.update(request["env"])
    import tempfile

    tempfile.tempdir = None  # $TMPDIR is read again (the request's)
    os.chdir(request["cwd"])
    for fd, path, flags in ((0, os.devnull, os.O_RDONLY),
                            (1, request["stdout"], os.O_WRONLY | os.O_CREAT | os.O_TRUNC),
                            (2, request["stderr"], os.O_WRONLY | os.O_CREAT | os.O_TRUNC)):
        new = os.open(path, flags, 0o644)
        os.dup2(new, fd)
        os.close(new)
    sys.argv = [str(ROOT / "massviz" / "__main__.py"), *request["argv"]]
    from massviz.cli import main

    return main(list(request["argv"]))


def _exit(request: dict) -> None:
    """Run the command in the child and end it as the interpreter would, minus tearing down the server's modules
    (torch's take ~0.5 s): ``SystemExit``'s code, the atexit handlers (``weakref.finalize`` clean-ups among them),
    the streams flushed, then ``os._exit``."""
    import atexit
    import traceback

    try:
        code = _child(request)
    except SystemExit as stop:
        code = stop.code
    except BaseException:  # noqa: BLE001 - what the interpreter prints for an uncaught exception
        traceback.print_exc()
        code = 1
    if code is None:
        code = 0
    elif not isinstance(code, int):
        print(code, file=sys.stderr)
        code = 1
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except Exception:  # noqa: BLE001 - a closed stream (a reader that left)
            pass
    os._exit(code & 0xFF)


def serve() -> None:
    from massviz.cli import _quiet_native_logs

    _quiet_native_logs()  # before cv2 loads, as main() does before a command imports it
    import cv2  # noqa: F401
    import torch  # noqa: F401

    import massviz.app  # noqa: F401

    reply_fd = os.dup(1)  # replies go to the original stdout; the server's own fd 1 goes nowhere
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)
    os.close(devnull)
    reply = os.fdopen(reply_fd, "w", buffering=1)
    for line in sys.stdin:
        request = json.loads(line)
        pid = os.fork()
        if pid == 0:
            _exit(request)
        reply.write(json.dumps({"pid": pid}) + "\n")
        _, status, _ = os.wait4(pid, 0)
        reply.write(json.dumps({"status": status}) + "\n")


class ForkServer:
    """The test's side: ``start(argv, env, cwd, stdout, stderr)`` returns the command's pid once it runs,
    ``wait()`` its exit code (``os.waitstatus_to_exitcode``); one command at a time. ``close()`` ends the server."""

    def __init__(self, env: dict | None = None, argv: list[str] | None = None):
        """``argv``: the server's command line, ``python forkserver.py`` unless given (another one ends by calling
        :func:`serve`, e.g. ``python -c`` with code run before it)."""
        self.proc = subprocess.Popen(argv or [sys.executable, __file__], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True, bufsize=1, cwd=ROOT, env=env)

    def start(self, argv, env: dict, cwd: Path, stdout: Path, stderr: Path) -> int:
        request = {"argv": [str(a) for a in argv], "env": env, "cwd": str(cwd), "stdout": str(stdout),
                   "stderr": str(stderr)}
        self.proc.stdin.write(json.dumps(request) + "\n")
        self.proc.stdin.flush()
        return json.loads(self._line())["pid"]

    def wait(self) -> int:
        return os.waitstatus_to_exitcode(json.loads(self._line())["status"])

    def _line(self) -> str:
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError(f"the fork server ended (exit {self.proc.wait()})")
        return line

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.stdin.close()
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        self.proc.stdout.close()


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    serve()
