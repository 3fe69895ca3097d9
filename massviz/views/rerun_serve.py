"""Serve a folder of massviz .rrd recordings as a dataset of Rerun's catalog server (``rr.server.Server``), with
massviz's layouts as the dataset's defaults and a Rerun web viewer, all bound to 127.0.0.1.

``open_catalog(folder)`` / ``catalog(folder)`` (a context manager) is the in-process part (the server, its dataset
entry and a DataFusion-backed client; needs ``rerun-sdk[catalog]``), ``serve`` the blocking command (``massviz serve``). The web viewer is Rerun's
own binary (``rerun --web-viewer --bind 127.0.0.1 URL``) in a child process that dies with this one (Linux
``PR_SET_PDEATHSIG``) and is stopped and waited for when the server stops; nothing is left running.
"""
from __future__ import annotations

import contextlib
import os
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from massviz.errors import MassvizError

HOST = "127.0.0.1"
_WEB_URL = re.compile(r"connect at (http://\S+)")


@dataclass
class Catalog:
    """A running catalog server with one dataset: ``url`` (``rerun+http://127.0.0.1:PORT``), ``name``, ``dataset``
    (``rerun.catalog.DatasetEntry``), ``client`` (``rerun.catalog.CatalogClient``)."""

    server: object
    name: str
    dataset: object
    client: object
    _tmp: object = None  # the folder of the registered .rbl files, removed by close()

    def close(self) -> None:
        """Stop the server (idempotent)."""
        with contextlib.suppress(Exception):
            if self.server.is_running():
                self.server.shutdown()
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None

    @property
    def url(self) -> str:
        return self.server.url()

    @property
    def dataset_url(self) -> str:
        """The dataset's URL (``rerun+http://127.0.0.1:PORT/dataset/ID``): a viewer opens its segment table."""
        return f"{self.url}/dataset/{self.dataset.id}"

    def segment_table(self):
        """The dataset's segment table as a pandas DataFrame (one row per recording, ``property:massviz:*``)."""
        return self.dataset.segment_table().to_pandas()

    def sql(self, query: str):
        """A DataFusion SQL query over the segment table, registered as ``segments`` (pandas DataFrame)."""
        ctx = self.client.ctx
        with contextlib.suppress(Exception):
            ctx.deregister_table("segments")
        ctx.register_view("segments", self.dataset.segment_table())
        return ctx.sql(query).to_pandas()


def _rrd_files(folder: Path) -> list[Path]:
    if not folder.is_dir():
        raise MassvizError("not a folder (make a dataset with: massviz log DATASET --rrd-dir OUT)", folder)
    files = sorted(folder.glob("*.rrd"))
    if not files:
        raise MassvizError("holds no .rrd file (make a dataset with: massviz log DATASET --rrd-dir OUT)", folder)
    return files


def _require_datafusion() -> None:
    try:
        import datafusion  # noqa: F401
    except ImportError:
        raise MassvizError("the catalog needs DataFusion: pip install 'rerun-sdk[catalog]==0.41.*' (or "
                           "'massviz[catalog]')") from None


def open_catalog(folder: str | Path, *, name: str | None = None, port: int = 0, k: int = 5) -> "Catalog":
    """Start the catalog server on 127.0.0.1 with ``folder``'s .rrd files as dataset ``name`` (default: the folder's
    name) and massviz's recording and segment-table layouts registered as its defaults. Runs until
    ``Catalog.close()`` (or the process ends); ``catalog`` is the same as a context manager."""
    import rerun as rr

    from massviz.views.rerun_dataset import save_blueprints

    folder = Path(folder).resolve()
    _rrd_files(folder)
    _require_datafusion()
    name = name or re.sub(r"[^A-Za-z0-9_.-]", "_", folder.name) or "massviz"
    tmp = tempfile.TemporaryDirectory(prefix="massviz-serve-")
    try:
        rec_bp, table_bp = save_blueprints(tmp.name, k)
        try:
            server = rr.server.Server(host=HOST, port=port or None, datasets={name: str(folder)})
        except Exception as err:  # noqa: BLE001 - a busy port, an unreadable file: one line
            raise MassvizError(f"the catalog server did not start ({err})", folder) from None
        try:
            client = server.client()
            dataset = client.get_dataset(name)
            dataset.register_blueprint(rec_bp.as_uri())
            dataset.register_blueprint(table_bp.as_uri(), segment_table=True)
        except BaseException:
            with contextlib.suppress(Exception):
                server.shutdown()
            raise
    except BaseException:
        tmp.cleanup()
        raise
    return Catalog(server, name, dataset, client, tmp)


@contextlib.contextmanager
def catalog(folder: str | Path, *, name: str | None = None, port: int = 0, k: int = 5):
    """``open_catalog`` as a context manager: yields the ``Catalog``, shuts the server down when the block ends."""
    cat = open_catalog(folder, name=name, port=port, k=k)
    try:
        yield cat
    finally:
        cat.close()


def _viewer_binary() -> Path:
    import rerun_cli

    exe = Path(rerun_cli.__file__).parent / ("rerun.exe" if sys.platform.startswith("win") else "rerun")
    if not exe.is_file():
        raise MassvizError("Rerun's viewer binary is missing (reinstall rerun-sdk)", exe)
    return exe


def _die_with_parent() -> None:  # runs in the child before exec (Linux): SIGTERM when massviz serve goes away
    with contextlib.suppress(Exception):
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


class WebViewer:
    """Rerun's web viewer (its own binary, not the Python wrapper that would leave it orphaned) on 127.0.0.1, opening
    ``url``; ``.url`` is the page to open. ``stop()`` terminates it and waits."""

    def __init__(self, url: str, port: int = 0, timeout: float = 60.0):
        cmd = [str(_viewer_binary()), "--web-viewer", "--bind", HOST, "--web-viewer-port", str(port), url]
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                     preexec_fn=_die_with_parent if sys.platform.startswith("linux") else None,
                                     # its log line says where it serves: on even when massviz quiets Rerun's logs
                                     env={**os.environ, "RERUN_TELEMETRY_ENABLED": "false", "RUST_LOG": "info"})
        self.url, found = None, threading.Event()
        self._tail: list[str] = []

        def read() -> None:
            for line in self.proc.stdout:
                self._tail = (self._tail + [line])[-20:]
                m = _WEB_URL.search(re.sub(r"\x1b\[[0-9;]*m", "", line))
                if m and self.url is None:
                    self.url = m.group(1).rstrip(",")
                    found.set()
            found.set()

        threading.Thread(target=read, daemon=True).start()
        found.wait(timeout)
        if self.url is None:
            self.stop()
            raise MassvizError("Rerun's web viewer did not start: " + "".join(self._tail)[-300:].strip())

    def alive(self) -> bool:
        return self.proc.poll() is None

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)


class _Stop(Exception):
    pass


def serve(folder: str | Path, *, name: str | None = None, port: int = 0, web_port: int = 0, web_viewer: bool = True,
          k: int = 5, out=None, ready=None) -> int:
    """``massviz serve``: run the catalog (and web viewer) until Ctrl-C or SIGTERM; print how to open it.
    ``ready(catalog, page_url)`` (tests, benchmarks) is called once everything is up."""
    out = out or sys.stdout

    def stop(signum, frame):
        raise _Stop()

    previous = signal.signal(signal.SIGTERM, stop)
    viewer = None
    try:
        with catalog(folder, name=name, port=port, k=k) as cat:
            n = len(cat.dataset.segment_ids())
            lines = [f"massviz serve: dataset {cat.name!r}: {n} recording(s) from {Path(folder).resolve()}",
                     f"  catalog server: {cat.url}",
                     f"  native viewer:  rerun {cat.dataset_url}"]
            if web_viewer:
                viewer = WebViewer(cat.dataset_url, web_port)
                lines.append(f"  web viewer:     {viewer.url}")
            lines.append("  Ctrl-C stops the server" + (" and the web viewer" if viewer else ""))
            print("\n".join(lines), file=out, flush=True)
            if ready is not None:
                ready(cat, viewer.url if viewer else None)
            while viewer is None or viewer.alive():
                time.sleep(0.3)
            print("massviz serve: the web viewer exited; stopping", file=sys.stderr)
            return 1
    except (KeyboardInterrupt, _Stop):
        print("massviz serve: stopped", file=sys.stderr)
        return 0
    finally:
        if viewer is not None:
            viewer.stop()
        signal.signal(signal.SIGTERM, previous)


__all__ = ["Catalog", "open_catalog", "catalog", "WebViewer", "serve", "HOST"]
