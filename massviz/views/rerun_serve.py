"""Serve a folder of massviz .rrd recordings as a dataset of Rerun's catalog server (``rr.server.Server``), with
massviz's layouts as the dataset's defaults and a Rerun web viewer, all bound to 127.0.0.1.

``open_catalog(folder)`` / ``catalog(folder)`` (a context manager) is the in-process part (the server, its dataset
entry and a DataFusion-backed client; needs ``rerun-sdk[catalog]``), ``serve`` the blocking command (``massviz serve``). The web viewer is Rerun's
own binary (``rerun --serve-web --bind 127.0.0.1 URL``: given a URL it serves only the viewer's page, no gRPC server,
and opens no browser) in a child process that dies with this one (Linux ``PR_SET_PDEATHSIG``) and is stopped and
waited for when the server stops; nothing is left running.

``view(rrd)`` (``massviz view``) is the same web viewer for one .rrd file, which a ``FileServer`` thread of this
process serves over HTTP (only to the viewer's page): no display needed, and idle it costs no CPU (``rerun
--serve-web FILE`` kept a core busy while serving a file, rerun 0.41).
"""
from __future__ import annotations

import contextlib
import logging
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
import urllib.parse
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
    """The readable .rrd files of ``folder`` (their first bytes are Rerun's header); each other ``*.rrd`` is one
    warning line naming it (the server skips it, the rest is served); none readable is a ``MassvizError``."""
    from massviz.io.untrusted import printable

    if not folder.is_dir():
        raise MassvizError("not a folder (make a dataset with: massviz log DATASET --rrd-dir OUT)", folder)
    found = sorted(folder.glob("*.rrd"))
    if not found:
        raise MassvizError("holds no .rrd file (make a dataset with: massviz log DATASET --rrd-dir OUT)", folder)
    files = []
    for path in found:
        try:
            files.append(check_rrd(path))
        except MassvizError as err:
            logging.getLogger(__name__).warning("massviz: warning: %s; not served", printable(err))
    if not files:
        raise MassvizError("holds no readable .rrd file (make a dataset with: massviz log DATASET --rrd-dir OUT)",
                           folder)
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

    from massviz.evaluation.browser import INDEX_NAME

    folder = Path(folder).resolve()
    _rrd_files(folder)
    _require_datafusion()
    name = name or re.sub(r"[^A-Za-z0-9_.-]", "_", folder.name) or "massviz"
    tmp = tempfile.TemporaryDirectory(prefix="massviz-serve-")
    try:
        try:
            server = rr.server.Server(host=HOST, port=port or None, datasets={name: str(folder)})
        except Exception as err:  # noqa: BLE001 - a busy port, an unreadable file: one line
            raise MassvizError(f"the catalog server did not start ({err})", folder) from None
        try:
            client = server.client()
            dataset = client.get_dataset(name)
            rec_bp, table_bp = save_layouts(dataset, tmp.name, k)
            dataset.register_blueprint(rec_bp.as_uri())
            dataset.register_blueprint(table_bp.as_uri(), segment_table=True)
            register_links(dataset, Path(tmp.name), folder / INDEX_NAME)
        except BaseException:
            with contextlib.suppress(Exception):
                server.shutdown()
            raise
    except BaseException:
        tmp.cleanup()
        raise
    return Catalog(server, name, dataset, client, tmp)


def save_layouts(dataset, folder: str | Path, k: int = 5) -> tuple[Path, Path]:
    """Write the recording and segment-table layouts that suit ``dataset`` into ``folder`` as ``.rbl`` files: a
    light recording's with ``k`` patch tiles and the one-run table (``massviz.views.rerun_dataset``), or, when its
    recordings have the ``label_b`` property (two-run recordings of ``massviz compare ... --rrd-dir``), both runs
    side by side with as many tiles as the most patches either run chose, and the two-run table
    (``massviz.views.rerun_runs``)."""
    from massviz.views import rerun_dataset, rerun_runs

    segments = dataset.segment_table()
    names = segments.schema().names
    if rerun_dataset.property_column("label_b") not in names:
        return rerun_dataset.save_blueprints(folder, rerun_dataset.dataset_blueprint(k))
    cols = [rerun_dataset.property_column(f"k_{side}") for side in "ab"]
    table = segments.select(*[c for c in cols if c in names]).to_pandas()

    def most(col: str) -> int:
        values = [int(v[0]) for v in table[col] if v is not None and len(v)] if col in table else []
        return max(values, default=k)

    return rerun_dataset.save_blueprints(folder, rerun_runs.two_runs_blueprint(most(cols[0]), most(cols[1])),
                                         rerun_runs.table_blueprint(present=names))


def best_frames(dataset, index: Path | None = None) -> dict[str, int | None]:
    """Each segment's best frame: from ``index`` (the ``index.csv`` that ``massviz log --rrd-dir`` writes beside the
    .rrd files: read in milliseconds) when it names every segment with a whole frame, else from the segment table's
    ``best_frame`` property (a scan of every segment: ~2 s at 1,140 recordings); None where neither has one."""
    import pandas as pd

    from massviz.views.rerun_dataset import property_column

    segments = [str(s) for s in dataset.segment_ids()]
    if index is not None and index.is_file():
        try:
            table = pd.read_csv(index, usecols=["id", "best_frame"], dtype={"id": str})
            frames = dict(zip(table["id"], pd.to_numeric(table["best_frame"], errors="coerce")))
            if all(s in frames and frames[s] >= 0 and float(frames[s]).is_integer() for s in segments):
                return {s: int(frames[s]) for s in segments}
        except (OSError, ValueError, KeyError, pd.errors.ParserError):
            pass  # not massviz's index (or damaged): the recordings' own property says
    best = property_column("best_frame")
    table = dataset.segment_table()
    if best not in table.schema().names:
        return dict.fromkeys(segments)
    table = table.select("rerun_segment_id", best).to_pandas()
    return {str(s): int(v[0]) if v is not None and len(v) else None
            for s, v in zip(table["rerun_segment_id"], table[best])}


def register_links(dataset, folder: Path, index: Path | None = None) -> list[str]:
    """Give every segment of ``dataset`` its ``open`` property (the segment table's first column, a button): the
    segment's URL at its best frame (``best_frames``; ``#when=frame@N``), registered as layer ``link`` from one small
    .rrd per segment written into ``folder``. Returns the URLs."""
    from massviz.views.rerun_dataset import LINK_LAYER, write_link

    uris, urls = [], []
    for i, (segment, frame) in enumerate(best_frames(dataset, index).items()):
        urls.append(dataset.segment_url(segment, "frame", frame) if frame is not None else
                    dataset.segment_url(segment))
        uris.append(write_link(folder / f"link_{i}.rrd", segment, urls[-1]).as_uri())
    if uris:
        dataset.register(uris, layer_name=LINK_LAYER).wait()
    return urls


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
        cmd = [str(_viewer_binary()), "--serve-web", "--bind", HOST, "--web-viewer-port", str(port), url]
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


@contextlib.contextmanager
def _until_stopped():
    """Run the block until Ctrl-C or SIGTERM (``_Stop``), whichever comes; the SIGTERM handler is restored after."""

    def stop(signum, frame):
        raise _Stop()

    previous = signal.signal(signal.SIGTERM, stop)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _wait(viewer: "WebViewer") -> None:
    """Block while the viewer runs (a wake-up a second: no CPU to speak of)."""
    while viewer is None or viewer.alive():
        time.sleep(1.0)


def serve(folder: str | Path, *, name: str | None = None, port: int = 0, web_port: int = 0, web_viewer: bool = True,
          k: int = 5, out=None, ready=None) -> int:
    """``massviz serve``: run the catalog (and web viewer) until Ctrl-C or SIGTERM; print how to open it.
    ``ready(catalog, page_url)`` (tests, benchmarks) is called once everything is up."""
    out = out or sys.stdout

    def start(stack: contextlib.ExitStack):
        cat = stack.enter_context(catalog(folder, name=name, port=port, k=k))
        n = len(cat.dataset.segment_ids())
        lines = [f"massviz serve: dataset {cat.name!r}: {n} recording(s) from {Path(folder).resolve()}",
                 f"  catalog server: {cat.url}",
                 f"  native viewer:  rerun {cat.dataset_url}"]
        viewer = None
        if web_viewer:
            viewer = WebViewer(cat.dataset_url, web_port)
            stack.callback(viewer.stop)
            lines.append(f"  web viewer:     {viewer.url}")
        lines.append("  Ctrl-C stops the server" + (" and the web viewer" if viewer else ""))
        print("\n".join(lines), file=out, flush=True)
        if ready is not None:
            ready(cat, viewer.url if viewer else None)
        return viewer

    return _run_until_stopped("serve", start)


def _run_until_stopped(command: str, start) -> int:
    """``start(stack)`` starts the servers (their clean-ups on the ``ExitStack``) and returns the web viewer (or
    None); then wait until Ctrl-C or SIGTERM (exit 0) or until the viewer exits (exit 1); everything started is
    stopped either way."""
    try:
        with _until_stopped(), contextlib.ExitStack() as stack:
            _wait(start(stack))
            print(f"massviz {command}: the web viewer exited; stopping", file=sys.stderr)
            return 1
    except (KeyboardInterrupt, _Stop):
        print(f"massviz {command}: stopped", file=sys.stderr)
        return 0


#: the first bytes of an .rrd file (Rerun's stream header, "RRF2" since 0.x)
RRD_MAGIC = b"RRF2"
#: bytes of that header: the magic, Rerun's version and the encoding options.
RRD_HEADER_BYTES = 12


def check_rrd(path: str | Path) -> Path:
    """``path`` as a readable .rrd file (its first bytes are Rerun's header), else one ``MassvizError`` line."""
    path = Path(path)
    if not path.is_file():
        raise MassvizError("no such .rrd file" if not path.exists() else "is not a file", path)
    try:
        with open(path, "rb") as f:
            head = f.read(RRD_HEADER_BYTES)
    except OSError as err:
        raise MassvizError(f"cannot read ({err.strerror or err})", path) from None
    if not head.startswith(RRD_MAGIC):
        raise MassvizError("not a Rerun .rrd file (make one with: massviz log REC --rrd OUT.rrd)", path)
    if len(head) < RRD_HEADER_BYTES:
        raise MassvizError(f"a Rerun .rrd file cut off in its header ({len(head)} bytes)", path)
    return path.resolve()


class FileServer:
    """One file over HTTP on 127.0.0.1 (a thread of this process), readable by pages of ``origin`` (CORS; set it to
    the viewer's): ``url`` is the file's address, ``port`` its port; every other path is 404. ``close()`` stops
    it."""

    def __init__(self, path: Path, port: int = 0):
        import http.server

        name = urllib.parse.quote(path.name)
        self.origin = "*"

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_GET(handler):  # noqa: N805 - the handler instance
                if urllib.parse.urlsplit(handler.path).path != f"/{name}":
                    handler.send_error(404)
                    return
                try:
                    f = open(path, "rb")
                except OSError:
                    handler.send_error(404)
                    return
                with f:
                    handler.send_response(200)
                    handler.send_header("Content-Type", "application/octet-stream")
                    handler.send_header("Content-Length", str(f.seek(0, os.SEEK_END)))
                    f.seek(0)
                    handler.send_header("Access-Control-Allow-Origin", self.origin)
                    handler.end_headers()
                    with contextlib.suppress(ConnectionError):
                        shutil.copyfileobj(f, handler.wfile)

            def log_message(handler, *args):  # noqa: N805
                pass

        try:
            self.httpd = http.server.ThreadingHTTPServer((HOST, port), Handler)
        except OSError as err:
            raise MassvizError(f"cannot serve the file on {HOST}:{port} ({err.strerror or err})", path) from None
        self.httpd.daemon_threads = True
        self.port = int(self.httpd.server_address[1])
        self.url = f"http://{HOST}:{self.port}/{name}"
        self._thread = threading.Thread(target=self.httpd.serve_forever, kwargs={"poll_interval": 1.0},
                                        name="massviz-view-file", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()
        self._thread.join(5)


def view(path: str | Path, *, port: int = 0, web_port: int = 0, out=None, ready=None) -> int:
    """``massviz view``: serve one .rrd to a browser from this machine (no display needed): the file from a small
    HTTP server and Rerun's web viewer (its own binary, ``WebViewer``), both on 127.0.0.1, until Ctrl-C or SIGTERM;
    prints the page to open. ``ready(page_url)`` (tests) is called once both are up."""
    out = out or sys.stdout
    path = check_rrd(path)

    def start(stack: contextlib.ExitStack):
        files = FileServer(path, port)
        stack.callback(files.close)
        viewer = WebViewer(files.url, web_port)
        stack.callback(viewer.stop)
        page = urllib.parse.urlsplit(viewer.url)
        files.origin = f"{page.scheme}://{page.netloc}"  # only the viewer's page may read the file
        print(f"massviz view: {path}\n"
              f"  open in a browser: {viewer.url}\n"
              f"  from another machine: ssh -L {page.port}:127.0.0.1:{page.port} -L {files.port}:127.0.0.1:"
              f"{files.port} THIS_HOST, then the same URL there\n"
              "  Ctrl-C stops the viewer", file=out, flush=True)
        if ready is not None:
            ready(viewer.url)
        return viewer

    return _run_until_stopped("view", start)


__all__ = ["Catalog", "open_catalog", "catalog", "save_layouts", "best_frames", "register_links", "WebViewer", "serve", "check_rrd", "FileServer", "view", "HOST"]
