"""Rerun's web viewer served from this machine on 127.0.0.1, for ``massviz view``, ``massviz serve`` and ``massviz
live --serve-web``: :class:`WebViewer` (Rerun's own binary in a child process) and :func:`run_until_stopped` (the
wait of ``view`` and ``serve``: until Ctrl-C, SIGTERM or SIGHUP, through :mod:`massviz.signals`).

The viewer is Rerun's binary itself (``rerun --serve-web --bind 127.0.0.1``), not the Python wrapper ``python -m
rerun``, which runs the server as a child of its own that outlived the wrapper when it was killed. The child runs in a
session of its own (a terminal's Ctrl-C reaches massviz only, which stops it), gets SIGTERM when massviz dies first
(Linux ``PR_SET_PDEATHSIG``), and ``stop()`` ends it (SIGTERM, then SIGKILL) and waits for it: nothing is left
running.
"""
from __future__ import annotations

import contextlib
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.parse
from pathlib import Path

from massviz.errors import MassvizError
from massviz.signals import signals_end_like_ctrl_c

HOST = "127.0.0.1"
#: the binary's log lines that say where it serves (read with ``RUST_LOG=info``)
_PAGE = re.compile(r"Hosting a web-viewer at (http://\S+?)(?:\s|,|$)")
_CONNECT = re.compile(r"connect at (http://\S+)")
_GRPC = re.compile(r"Listening for gRPC connections on [0-9.]+:(\d+)")
_ANSI = re.compile(r"\x1b\[[0-9;]*m")


def _viewer_binary() -> Path:
    import rerun_cli

    exe = Path(rerun_cli.__file__).parent / ("rerun.exe" if sys.platform.startswith("win") else "rerun")
    if not exe.is_file():
        raise MassvizError("Rerun's viewer binary is missing (reinstall rerun-sdk)", exe)
    return exe


def _die_with_parent() -> None:  # runs in the child before exec (Linux): SIGTERM when massviz goes away
    with contextlib.suppress(Exception):
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


def port_in_use(port: int) -> bool:
    """Whether something accepts connections on 127.0.0.1:``port``."""
    with socket.socket() as s:
        return s.connect_ex((HOST, port)) == 0


class WebViewer:
    """Rerun's web viewer on 127.0.0.1 (module docstring), in one of two ways:

    * ``WebViewer(url)``: only the viewer's page, which opens ``url`` (a catalog dataset for ``massviz serve``, an
      .rrd served over HTTP for ``massviz view``);
    * ``WebViewer(grpc_port=N)``: also Rerun's gRPC server on port N (0: a free one), which a recording stream sends
      to (``.grpc``, ``rerun+http://127.0.0.1:N/proxy``) and the page shows as it arrives (``massviz live
      --serve-web``).

    ``port`` is the page's (0: a free one); ``.url`` is the page to open. ``alive()``; ``stop()`` ends it (SIGTERM,
    SIGKILL after ``grace`` seconds) and waits for it, however often it is called."""

    def __init__(self, url: str | None = None, *, port: int = 0, grpc_port: int | None = None,
                 timeout: float = 60.0):
        if (url is None) == (grpc_port is None):
            raise ValueError("WebViewer needs a url to open or a grpc_port to serve, not both")
        cmd = [str(_viewer_binary()), "--serve-web", "--bind", HOST, "--web-viewer-port", str(port)]
        cmd += [url] if url is not None else ["--port", str(grpc_port)]
        self.proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                     text=True, start_new_session=True,
                                     preexec_fn=_die_with_parent if sys.platform.startswith("linux") else None,
                                     # its log lines say where it serves: on even when massviz quiets Rerun's logs
                                     env={**os.environ, "RERUN_TELEMETRY_ENABLED": "false", "RUST_LOG": "info"})
        self.url: str | None = None
        self.grpc: str | None = None
        self._tail: list[str] = []
        found = threading.Event()

        def read() -> None:  # reads the binary's output for as long as it runs (a full pipe would stall it)
            page = connect = grpc = None
            for line in self.proc.stdout:
                self._tail = (self._tail + [line])[-20:]
                line = _ANSI.sub("", line)
                grpc = grpc or _match(_GRPC, line)
                page = page or _match(_PAGE, line)
                connect = connect or _match(_CONNECT, line)
                if self.url is None and url is not None and connect:
                    self.url = connect.rstrip(",")
                    found.set()
                elif self.url is None and url is None and page and grpc:
                    self.grpc = f"rerun+http://{HOST}:{grpc}/proxy"
                    self.url = f"{page.rstrip('/,')}/?url={urllib.parse.quote(self.grpc, safe='')}"
                    found.set()
            found.set()

        threading.Thread(target=read, name="massviz-web-viewer-log", daemon=True).start()
        found.wait(timeout)
        if self.url is None:
            self.stop()
            raise MassvizError("Rerun's web viewer did not start: " + "".join(self._tail)[-300:].strip())

    def alive(self) -> bool:
        return self.proc.poll() is None

    def stop(self, grace: float = 5.0) -> None:
        """End the viewer (SIGTERM, SIGKILL if it is still there after ``grace`` seconds) and wait for it."""
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(grace)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


def _match(pattern: re.Pattern, line: str) -> str | None:
    m = pattern.search(line)
    return m.group(1) if m else None


def run_until_stopped(command: str, start) -> int:
    """``start(stack)`` starts the servers (each one's stop on the ``contextlib.ExitStack``) and returns the web
    viewer (or None); then wait until Ctrl-C, SIGTERM or SIGHUP (exit 0) or until the viewer exits by itself (exit
    1). Everything started is stopped either way, before this returns; a second SIGTERM or SIGHUP while it stops is
    ignored (:func:`massviz.signals.terminate`), a second Ctrl-C interrupts the stop that runs."""
    try:
        with signals_end_like_ctrl_c(), contextlib.ExitStack() as stack:
            viewer = start(stack)
            while viewer is None or viewer.alive():
                time.sleep(1.0)  # (a wake-up a second: no CPU to speak of; a signal ends the sleep at once)
            print(f"massviz {command}: the web viewer exited; stopping", file=sys.stderr)
            return 1
    except KeyboardInterrupt:  # Ctrl-C, or massviz.signals.Terminated (SIGTERM, SIGHUP)
        print(f"massviz {command}: stopped", file=sys.stderr)
        return 0


__all__ = ["HOST", "WebViewer", "run_until_stopped", "port_in_use"]
