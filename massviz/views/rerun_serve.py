"""Serve a folder of massviz .rrd recordings as a dataset of Rerun's catalog server (``rr.server.Server``), with
massviz's layouts as the dataset's defaults and a Rerun web viewer, all bound to 127.0.0.1.

``open_catalog(folder)`` / ``catalog(folder)`` (a context manager) is the in-process part (the server, its dataset
entry and a DataFusion-backed client; needs ``rerun-sdk[catalog]``), ``serve`` the command (``massviz serve``): the
catalog and Rerun's web viewer (``massviz.views.web_viewer.WebViewer``, given the dataset's URL) until Ctrl-C, SIGTERM
or SIGHUP (``massviz.views.web_viewer.run_until_stopped``). Only the .rrd files Rerun reads whole are served
(``check_rrd``); every other one is named, with its reason, in one warning line.

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
import socket
import sys
import tempfile
import threading
import urllib.parse
from dataclasses import dataclass, field
from pathlib import Path

from massviz.errors import MassvizError
from massviz.views.web_viewer import HOST, WebViewer, run_until_stopped

#: seconds ``Catalog.close`` waits for the server's shutdown before it ends the connections still open, and after
_SHUTDOWN_WAIT = 0.5
_SHUTDOWN_GRACE = 5.0


@dataclass
class Catalog:
    """A running catalog server with one dataset: ``url`` (``rerun+http://127.0.0.1:PORT``), ``name``, ``dataset``
    (``rerun.catalog.DatasetEntry``), ``client`` (``rerun.catalog.CatalogClient``); ``not_served``: each .rrd file of
    the folder that is not in the dataset, with the reason (said in a warning line when the catalog opened)."""

    server: object
    name: str
    dataset: object
    client: object
    _tmp: object = None  # the folder of the registered .rbl files, removed by close()
    not_served: dict[Path, str] = field(default_factory=dict)
    _closed: bool = False

    def close(self) -> None:
        """Stop the server (idempotent; ``stop_server``) and remove its layout files."""
        if self.server is not None and not self._closed:
            self._closed = True
            stop_server(self.server)
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


def _rrd_files(folder: Path) -> tuple[list[Path], dict[Path, str]]:
    """The .rrd files of ``folder`` to serve (``check_rrd``: Rerun reads each whole; of files holding the same
    recording, the first by name) and the others with the reason, each said in one warning line naming it; none to
    serve is a ``MassvizError``."""
    if not folder.is_dir():
        raise MassvizError("not a folder (make a dataset with: massviz log DATASET --rrd-dir OUT)", folder)
    found = sorted(folder.glob("*.rrd"))
    if not found:
        raise MassvizError("holds no .rrd file (make a dataset with: massviz log DATASET --rrd-dir OUT)", folder)
    files, skipped, holder = [], {}, {}
    for path in found:
        try:
            ids = rrd_recordings(path)
            same = next((i for i in ids if i in holder), None)
            if same is not None:
                raise MassvizError(f"holds recording {same!r} as {holder[same].name} does, which is served", path)
        except MassvizError as err:
            _not_served(skipped, path, err)
            continue
        files.append(path.resolve())
        holder.update(dict.fromkeys(ids, path))
    if not files:
        raise MassvizError("holds no readable .rrd file (make a dataset with: massviz log DATASET --rrd-dir OUT)",
                           folder)
    return files, skipped


def _not_served(skipped: dict[Path, str], path: Path, err: MassvizError) -> None:
    """Record ``path`` as not served for ``err`` and say so in one warning line naming it."""
    from massviz.io.untrusted import printable

    skipped[path] = str(err).removeprefix(f"{err.path}: ")
    logging.getLogger(__name__).warning("massviz: warning: %s; not served", printable(err))


def served_files(dataset) -> set[Path]:
    """The files the catalog server loaded into ``dataset`` (its segment table's storage URLs)."""
    table = dataset.segment_table().select("rerun_storage_urls").to_pandas()
    return {Path(urllib.parse.unquote(urllib.parse.urlsplit(u).path)) for urls in table["rerun_storage_urls"]
            for u in (urls if urls is not None else [])}


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
    files, skipped = _rrd_files(folder)
    _require_datafusion()
    name = name or re.sub(r"[^A-Za-z0-9_.-]", "_", folder.name) or "massviz"
    tmp = tempfile.TemporaryDirectory(prefix="massviz-serve-")
    try:
        try:
            server = rr.server.Server(host=HOST, port=port or None, datasets={name: [str(f) for f in files]})
        except Exception as err:  # noqa: BLE001 - a busy port, an unreadable file: one line
            raise MassvizError(f"the catalog server did not start ({err})", folder) from None
        try:
            client = server.client()
            dataset = client.get_dataset(name)
            loaded = served_files(dataset)
            for path in files:
                if path not in loaded:
                    _not_served(skipped, path, MassvizError("the catalog server did not load it", path))
            rec_bp, table_bp = save_layouts(dataset, tmp.name, k)
            dataset.register_blueprint(rec_bp.as_uri())
            dataset.register_blueprint(table_bp.as_uri(), segment_table=True)
            register_links(dataset, Path(tmp.name), folder / INDEX_NAME)
        except BaseException:
            stop_server(server)
            raise
    except BaseException:
        tmp.cleanup()
        raise
    return Catalog(server, name, dataset, client, tmp, skipped)


def stop_server(server, grace: float = _SHUTDOWN_GRACE) -> None:
    """Shut the catalog ``server`` down, within seconds whoever is connected. Rerun's shutdown stops taking connections
    at once, then waits for every open request to end, and a browser page's never does (the page would hold the
    server, and the command, for as long as it is open): the shutdown runs in a thread, and the connections still
    open after a moment are ended (``end_connections``); a shutdown still not done ``grace`` seconds later is left to
    the process's exit (it takes no new connection)."""
    with contextlib.suppress(Exception):  # (a server that never started, or was stopped already)
        if not server.is_running():
            return
    port = urllib.parse.urlsplit(server.url()).port  # asked first: the server answers nothing while it shuts down

    def shutdown() -> None:
        with contextlib.suppress(Exception):
            server.shutdown()

    thread = threading.Thread(target=shutdown, name="massviz-catalog-shutdown", daemon=True)
    thread.start()
    thread.join(_SHUTDOWN_WAIT)
    if thread.is_alive() and port:
        end_connections(port)
        thread.join(grace)


def end_connections(port: int) -> int:
    """End (``shutdown(2)``, both ways) every connection this process accepted on 127.0.0.1:``port``: its sockets
    whose own port is ``port`` and that have a peer (Linux: the sockets of ``/proc/self/fd``; elsewhere none).
    Returns how many."""
    fds = Path("/proc/self/fd")
    try:
        names = os.listdir(fds)
    except OSError:
        return 0
    ended = 0
    for name in names:
        try:
            if not os.readlink(fds / name).startswith("socket:"):
                continue
            dup = os.dup(int(name))
        except (OSError, ValueError):
            continue  # (closed meanwhile, or the listing's own descriptor)
        with socket.socket(fileno=dup) as sock:  # a duplicate: closing it leaves the server's socket open
            with contextlib.suppress(OSError):
                if sock.family in (socket.AF_INET, socket.AF_INET6) and sock.getsockname()[1] == port \
                        and sock.getpeername():
                    sock.shutdown(socket.SHUT_RDWR)
                    ended += 1
    return ended


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


#: the first bytes of an .rrd file (Rerun's stream header, "RRF2" since 0.x)
RRD_MAGIC = b"RRF2"
#: bytes of that header: the magic, Rerun's version and the encoding options.
RRD_HEADER_BYTES = 12


def check_rrd(path: str | Path) -> Path:
    """``path`` (resolved) as an .rrd file Rerun reads whole (``rrd_recordings``), else one ``MassvizError`` line
    saying why."""
    rrd_recordings(path)
    return Path(path).resolve()


def rrd_recordings(path: str | Path) -> list[str]:
    """The recording ids of the .rrd file ``path`` when Rerun reads it whole: its header, every message, and the
    footer (the manifest its writer adds when it closes the file). Else one ``MassvizError`` line naming it and
    saying why: missing, not a file, empty, not Rerun's, cut off (in its header, in a message, or before its footer),
    damaged, or holding no recording."""
    import warnings

    from massviz.io.untrusted import printable

    path = Path(path)
    if not path.is_file():
        raise MassvizError("no such .rrd file" if not path.exists() else "is not a file", path)
    try:
        with open(path, "rb") as f:
            head = f.read(RRD_HEADER_BYTES)
    except OSError as err:
        raise MassvizError(f"cannot read ({err.strerror or err})", path) from None
    if not head:
        raise MassvizError("is empty (0 bytes)", path)
    if not RRD_MAGIC.startswith(head[:len(RRD_MAGIC)]):
        raise MassvizError("not a Rerun .rrd file (make one with: massviz log REC --rrd OUT.rrd)", path)
    if len(head) < RRD_HEADER_BYTES:
        raise MassvizError(f"a Rerun .rrd file cut off in its header ({len(head)} bytes)", path)
    from rerun.chunk import RrdReader

    def said(err: BaseException) -> str:  # Rerun's words, without the path it repeats
        text = str(err).replace(f"Failed to read RRD file at {path}: ", "").replace(f": {path}", "")
        return printable(text.split(". ")[0].strip() or type(err).__name__)

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # (Rerun's "no footer" warning: the reason said below)
        try:
            reader = RrdReader(path)
            ids = [str(s.recording_id) for s in reader.recordings()]
            if ids:
                reader.store()  # the manifest, from the footer
        except (KeyboardInterrupt, SystemExit):
            raise
        except BaseException as err:  # noqa: BLE001 - (a Rust panic is a BaseException): one line
            if "without footer" in str(err):
                raise MassvizError("cut off: it ends before the footer Rerun writes when it closes a recording (its "
                                   "writer did not finish)", path) from None
            raise MassvizError(f"cut off or damaged: Rerun cannot read it ({said(err)})", path) from None
    if not ids:
        raise MassvizError("holds no recording (cut off before its first message, or only a blueprint)", path)
    return ids


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


def serve(folder: str | Path, *, name: str | None = None, port: int = 0, web_port: int = 0, web_viewer: bool = True,
          k: int = 5, out=None, ready=None) -> int:
    """``massviz serve``: run the catalog (and web viewer) until Ctrl-C, SIGTERM or SIGHUP (exit 0; ``run_until_stopped``);
    print how to open it. ``ready(catalog, page_url)`` (tests, benchmarks) is called once everything is up."""
    out = out or sys.stdout

    def start(stack: contextlib.ExitStack):
        cat = stack.enter_context(catalog(folder, name=name, port=port, k=k))
        n = len(cat.dataset.segment_ids())
        skipped = f"; {len(cat.not_served)} .rrd file(s) not served (each named above)" if cat.not_served else ""
        lines = [f"massviz serve: dataset {cat.name!r}: {n} recording(s) from {Path(folder).resolve()}{skipped}",
                 f"  catalog server: {cat.url}",
                 f"  native viewer:  rerun {cat.dataset_url}"]
        viewer = None
        if web_viewer:
            viewer = WebViewer(cat.dataset_url, port=web_port)
            stack.callback(viewer.stop)
            lines.append(f"  web viewer:     {viewer.url}")
        lines.append("  Ctrl-C stops the server" + (" and the web viewer" if viewer else ""))
        print("\n".join(lines), file=out, flush=True)
        if ready is not None:
            ready(cat, viewer.url if viewer else None)
        return viewer

    return run_until_stopped("serve", start)


def view(path: str | Path, *, port: int = 0, web_port: int = 0, out=None, ready=None) -> int:
    """``massviz view``: serve one .rrd to a browser from this machine (no display needed): the file from a small
    HTTP server and Rerun's web viewer (``WebViewer``), both on 127.0.0.1, until Ctrl-C, SIGTERM or SIGHUP
    (``run_until_stopped``); prints the page to open. ``ready(page_url)`` (tests) is called once both are up."""
    out = out or sys.stdout
    path = check_rrd(path)

    def start(stack: contextlib.ExitStack):
        files = FileServer(path, port)
        stack.callback(files.close)
        viewer = WebViewer(files.url, port=web_port)
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

    return run_until_stopped("view", start)


__all__ = ["Catalog", "open_catalog", "catalog", "stop_server", "end_connections", "served_files", "save_layouts",
           "best_frames", "register_links", "serve", "check_rrd", "rrd_recordings", "FileServer", "view", "HOST"]
