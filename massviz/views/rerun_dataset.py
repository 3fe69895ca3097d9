"""A dataset of Rerun recordings: one .rrd per recording, with recording properties a catalog can sort and filter.

``massviz log DATASET --rrd-dir OUT/`` runs ``write_recording`` on every recording (on the dataset runner's workers,
local or Ray) and ``write_index`` at the end. OUT then holds:

* ``<id>.rrd`` — one recording per input recording (Rerun recording id = segment id = the recording's id). By
  default a **light** recording: the overlays (``/camera/detections`` of every processed frame), the chosen patches
  (``/patches/<rank>``, static: shown whatever the time cursor), the predictions, decisions and summary, a JPEG of the best frame (the frame of the nearest
  chosen patch, at ``/camera/rgb``, and a small ``/thumbnail``) and ``/source`` (a ``TextDocument`` naming the source
  frames, which are *referenced*, not copied: the path is also the ``source`` property). ``full=True`` logs
  everything ``massviz log`` logs (``massviz.views.rerun.log_trace_with_clouds``: every frame, depth, masks, 3D
  clouds).
* ``index.csv`` — one row per recording: the properties, the .rrd file and its bytes, the input bytes.
* ``patches.csv`` and ``patches/<id>_<rank>.jpg`` — one row and one thumbnail per chosen patch (rank, frame, track,
  class, d, prediction, flag, cues, box), what the failure browser (notebook 04) shows without opening a recording.

**Recording properties** (``rr.send_property("massviz", AnyValues(...))``; in a catalog's segment table they are the
columns ``property:massviz:<name>``): ``id``, ``container_class``, ``gt_mass_g``, ``estimate_g``, ``rel_error``
(|estimate − truth| / truth), ``score`` (the CORSMAL per-recording score: exp(−ε), 0 when not estimated),
``n_flagged`` (flagged chosen patches), ``cues`` (their cues' kinds, and ``ground truth`` when ground-truth masks
decided), ``flagged_ranks``, ``detector``, ``k``, ``threshold``, ``stride``, ``weights_id``, ``view`` (CCM camera
view, 0 for other recordings), ``source``, ``frames`` (processed), ``detections``, ``best_frame``, ``estimated``,
``input_bytes`` and ``kind`` (``light`` or ``full``). Values that are unknown (no ground truth: ``gt_mass_g``,
``rel_error``, ``score``; not estimated: ``estimate_g``, ``rel_error``) are left out, i.e. null in the table.
``massviz serve`` adds ``open`` (the recording's URL at its best frame, ``…?segment_id=ID#when=frame@N``, a
``rerun.components.Url``) as each segment's ``link`` layer: the segment table's first column, a button.

Every property is a one-value list in the segment table (Rerun stores each component as a batch; there is no scalar
property): a SQL query reads ``"property:massviz:rel_error"[1]``.
"""
from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import rerun as rr
import rerun.blueprint as rrb

from massviz.core.trace import Trace, frame_results
from massviz.evaluation.browser import (
    INDEX_NAME,
    PATCHES_NAME,
    best_frame,
    patch_rows,
    recording_properties,
    recordings_table,
    rounded_properties,
)
from massviz.evaluation.browser import PATCH_COLUMNS as _PATCH_COLUMNS
from massviz.io.atomic import atomic_path
from massviz.io.untrusted import safe_filename, write_csv
from massviz.views.rerun import entities as rl
from massviz.views.rerun.output import APPLICATION_ID
from massviz.views.rerun.trace_logger import log_conclusion, log_opening, log_overlays, log_trace_with_clouds

PROPERTY = "massviz"
PATCHES_DIR = "patches"
#: width (px) of ``/thumbnail`` and of the patch thumbnails' longer side.
THUMB_PX = 160
#: the columns of the segment table the dataset's table blueprint shows first (in this order).
TABLE_COLUMNS = ("id", "container_class", "rel_error", "score", "estimate_g", "gt_mass_g", "n_flagged", "cues",
                 "detector", "k", "threshold", "stride", "view", "weights_id", "source")
PATCH_COLUMNS = (*_PATCH_COLUMNS, "thumb")
#: the property (and first segment-table column) ``massviz serve`` adds: the recording's URL at its best frame
OPEN = "open"
#: the layer of each segment that holds ``OPEN`` (a recording of that property only)
LINK_LAYER = "link"
#: the column of segment URLs Rerun's viewer adds to a segment table (they open at the last frame)
VIEWER_LINK_COLUMN = "recording link"


def property_column(name: str) -> str:
    """The segment-table column of property ``name`` (``property:massviz:<name>``)."""
    return f"property:{PROPERTY}:{name}"


def ccm_view(path: str | Path) -> int:
    """The CCM camera view of a recording path (``.../view3/rgb/000123.mp4`` → 3), 0 for other recordings."""
    m = re.search(r"(?:^|/)view([1-4])/rgb/[^/]+$", Path(path).as_posix())
    return int(m.group(1)) if m else 0


def input_bytes(recording) -> int:
    """Bytes of the files the recording's frames are read from (RGB video or images, depth images)."""
    try:
        return int(sum(Path(p).stat().st_size for p in recording.input_files()))
    except (AttributeError, OSError):
        return 0


def send_properties(stream: rr.RecordingStream, props: dict) -> None:
    """``props`` as the recording's ``massviz`` property (lists stay lists; an empty list is left out)."""
    values = {k: v for k, v in props.items() if not (isinstance(v, list) and not v)}
    stream.send_property(PROPERTY, rr.AnyValues(**values))


def log_thumbnail(stream: rr.RecordingStream, rgb_best: np.ndarray | None) -> None:
    """``/thumbnail``: the best frame, small (static); nothing when there is no best frame."""
    if rgb_best is not None:
        stream.log("/thumbnail", rr.EncodedImage(contents=rl.jpeg_bytes(thumbnail(rgb_best), 80),
                                                 media_type="image/jpeg"), static=True)


def thumbnail(rgb: np.ndarray, px: int = THUMB_PX) -> np.ndarray:
    """``rgb`` scaled so that its longer side is ``px`` (never enlarged)."""
    h, w = rgb.shape[:2]
    s = min(1.0, px / max(h, w, 1))
    return rgb if s >= 1.0 else cv2.resize(rgb, (max(1, round(w * s)), max(1, round(h * s))),
                                           interpolation=cv2.INTER_AREA)


def _patch_images(trace: Trace, recording) -> tuple[dict[int, np.ndarray], np.ndarray | None]:
    """(chosen detection → its RGB patch, the best frame's RGB); frames are read only where the trace kept no
    patch, and for the best frame; a patch the trace did not keep is its frame's result's
    (``massviz.core.trace.frame_results``: the patches as the pipeline cut them)."""
    dets = trace.detections
    patches = {int(i): dets.patches[int(i)] for i in trace.selection if dets.patches[int(i)] is not None}
    need = {int(dets.frame[int(i)]) for i in trace.selection if int(i) not in patches}
    best = best_frame(trace)
    rgb_best = None
    if len(trace.frames) or need:
        for frame, result in frame_results(trace, recording.frames(indices=sorted(need | {best}))):
            for i in trace.selection:
                if int(i) not in patches and int(dets.frame[int(i)]) == frame.index:
                    patches[int(i)] = result.patches[int(i) - result.offset]
            if frame.index == best:
                rgb_best = frame.rgb
    return patches, rgb_best


def log_light(stream: rr.RecordingStream, trace: Trace, recording, patches: dict, rgb_best,
              source_text: str) -> None:
    """The light recording (module docstring) into ``stream``."""
    dets, frames = trace.detections, [int(f) for f in trace.frames]
    rank_of = {int(i): r for r, i in enumerate(trace.selection)}
    flag_of = {p.detection: p for p in trace.flags.patches}
    log_opening(stream, trace)
    stream.log("/source", rr.TextDocument(source_text, media_type=rr.MediaType.MARKDOWN), static=True)
    best = best_frame(trace)
    log_thumbnail(stream, rgb_best)
    if frames and recording.intrinsics is not None:
        stream.set_time("frame", sequence=frames[0])
        rl.log_pinhole(stream, recording.intrinsics, 0.3)
    if best in frames and rgb_best is not None:
        stream.set_time("frame", sequence=best)
        stream.log("/camera/rgb", rr.EncodedImage(contents=rl.jpeg_bytes(rgb_best, 85), media_type="image/jpeg"))
    log_overlays(stream, trace)  # detections only: a light recording has no masks
    # the chosen patches are static: every tile shows its patch whatever the time cursor (a recording opens at its
    # best frame, before the frames some patches come from); each says its frame (``frame`` in its values)
    stream.reset_time()
    for i, rank in rank_of.items():
        if i in patches:
            rl.log_patch(stream, rank, dets, i, patches[i], flag_of.get(i), static=True)
    log_conclusion(stream, trace)
    rl.log_timings(stream, trace.timings, len(frames))


def light_blueprint(n_patches: int, flagged=()) -> rrb.Blueprint:
    """The layout of a light recording: the best frame with every frame's overlays, the chosen patches, the
    predictions and the text (decisions, summary, the source frames, timings); no depth or 3D view (no depth is
    logged). Tiles are named as in ``default_blueprint`` ("patch ★r ⚑ flagged")."""
    flagged = {int(r) for r in flagged}
    tiles = rrb.Grid(*[rrb.Spatial2DView(name=f"patch ★{r}" + (" ⚑ flagged" if r in flagged else ""),
                                         origin=f"/patches/{r}") for r in range(n_patches)],
                     name="Chosen patches (model input)") if n_patches else \
        rrb.TextDocumentView(name="Summary", origin="/summary")
    camera = rrb.Spatial2DView(name="best frame · detections of every frame", origin="/camera",
                               contents=["/camera/rgb", "/camera/detections"])
    text = rrb.Tabs(rrb.TextLogView(name="Decisions", origin="/log"),
                    rrb.TextDocumentView(name="Summary", origin="/summary"),
                    rrb.TextDocumentView(name="Source", origin="/source"),
                    rrb.TextDocumentView(name="Timings", origin="/timings"))
    return rrb.Blueprint(
        rrb.Horizontal(rrb.Vertical(camera, text, row_shares=[3, 2]),
                       rrb.Vertical(tiles, rrb.TimeSeriesView(name="Predictions (g)", origin="/predictions",
                                                         # (the legend covered the small plot)
                                                         plot_legend=rrb.PlotLegend(visible=False)),
                                    row_shares=[1, 1]),
                       column_shares=[3, 2]),
        rrb.TimePanel(timeline="frame"), collapse_panels=False)


def source_markdown(trace: Trace, recording) -> str:
    files = recording.input_files() if hasattr(recording, "input_files") else []
    source = recording.source_description()
    rgb, depth = source["rgb"], source["depth"]
    return (f"# source of {trace.recording.id}\n\nThe frames are not copied into this light recording; they are "
            f"here:\n\n- recording: `{recording.path}`\n- RGB: {rgb}\n- depth: {depth}\n- {len(files)} files, "
            f"{input_bytes(recording)} bytes\n\nThe full recording: `massviz log {recording.path} --rrd FULL.rrd` "
            f"(or `massviz log DATASET --rrd-dir OUT --full`).\n")


def rrd_name(recording_id: str) -> str:
    return f"{safe_filename(recording_id)}.rrd"


def patch_table_rows(trace: Trace, patches: dict, out_dir: Path | None) -> list[dict]:
    """``massviz.evaluation.browser.patch_rows`` with a ``thumb`` column; with ``out_dir`` each thumbnail is
    written to ``out_dir/patches/<id>_<rank>.jpg``."""
    rows = []
    for row in patch_rows(trace):
        row["thumb"] = f"{PATCHES_DIR}/{safe_filename(trace.recording.id)}_{row['rank']}.jpg"
        if out_dir is not None and row["detection"] in patches:
            with atomic_path(out_dir / row["thumb"]) as tmp:
                tmp.write_bytes(rl.jpeg_bytes(thumbnail(patches[row["detection"]], 96), 85))
        rows.append(row)
    return rows


def write_recording(trace: Trace, recording, out_dir: str | Path, *, full: bool = False, view: int | None = None,
                    video: str = "auto", replay=None) -> dict:
    """Write ``out_dir/<id>.rrd`` for ``trace`` (light, or ``full``) with its properties, and the patch thumbnails.
    ``replay(trace, recording)``: (the trace measured, its frames with each detection's cloud), the measure stage's
    ``massviz.measure3d.stage.measured_replay``; without it the trace is logged as it is, a full one without clouds.
    Returns what ``write_index`` needs: ``properties``, ``rrd`` (file name), ``rrd_bytes``, ``patches`` (rows)."""
    frames = None
    if replay is not None:
        trace, frames = replay(trace, recording)
        if not full:
            frames = None
    out_dir = Path(out_dir)
    (out_dir / PATCHES_DIR).mkdir(parents=True, exist_ok=True)
    view = ccm_view(recording.path) if view is None else view
    props = recording_properties(trace, source=str(recording.path), view=view, n_input_bytes=input_bytes(recording),
                                 kind="full" if full else "light")
    patches, rgb_best = _patch_images(trace, recording)
    name = rrd_name(trace.recording.id)
    stream = rr.RecordingStream(APPLICATION_ID, recording_id=trace.recording.id)
    with atomic_path(out_dir / name) as tmp:
        stream.save(tmp)
        try:
            stream.send_recording_name(f"massviz {trace.recording.id}")
            send_properties(stream, rounded_properties(props))
            if full:
                log_trace_with_clouds(trace, recording, stream=stream, video=video, frames=frames)
                log_thumbnail(stream, rgb_best)
            else:
                stream.send_blueprint(light_blueprint(len(trace.selection), [p.rank for p in trace.flags.flagged]),
                                      make_active=True, make_default=True)
                log_light(stream, trace, recording, patches, rgb_best, source_markdown(trace, recording))
            stream.flush()
        finally:
            stream.disconnect()
    return {"properties": props, "rrd": name, "rrd_bytes": (out_dir / name).stat().st_size,
            "patches": patch_table_rows(trace, patches, out_dir)}


def write_index(out_dir: str | Path, results: list[dict]) -> tuple[pd.DataFrame, pd.DataFrame]:
    """``index.csv`` (one row per recording: its properties, ``rrd``, ``rrd_bytes``) and ``patches.csv`` (one row
    per chosen patch), atomically. Returns both tables."""
    out_dir = Path(out_dir)
    index = recordings_table([{**r["properties"], "rrd": r["rrd"], "rrd_bytes": r["rrd_bytes"]} for r in results]) \
        if results else pd.DataFrame(columns=["id", "rrd", "rrd_bytes", "input_bytes"])
    patches = pd.DataFrame([row for r in results for row in r["patches"]], columns=list(PATCH_COLUMNS))
    with atomic_path(out_dir / INDEX_NAME) as tmp:
        write_csv(index, tmp)
    with atomic_path(out_dir / PATCHES_NAME) as tmp:
        write_csv(patches, tmp)
    return index, patches


def write_dataset(traces, recordings, out_dir: str | Path, *, full: bool = False,
                  replay=None) -> tuple[pd.DataFrame, pd.DataFrame]:
    """A dataset folder from traces made in this process (notebooks; ``massviz log --rrd-dir`` runs
    ``write_recording`` on the dataset runner's workers instead): one .rrd per trace, then ``write_index``
    (``replay``: see ``write_recording``)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    return write_index(out_dir, [write_recording(t, r, out_dir, full=full, replay=replay)
                                     for t, r in zip(traces, recordings)])


# ----------------------------------------------------------------------------------------------- catalog layout
def dataset_blueprint(k: int = 5) -> rrb.Blueprint:
    """The dataset's default layout for its recordings: that of a light recording with ``k`` patch tiles."""
    return light_blueprint(k)


def table_blueprint(columns=TABLE_COLUMNS, sort_by: str = "rel_error", direction: str = "descending",
                    present=None):
    """The segment table's layout: first "recording", a button with the recording's id that opens it at its best
    frame (the ``open`` property ``massviz serve`` adds, shown as a ``rerun.components.Url``), then the properties
    ``columns`` (``id`` aside: the button shows it; with ``present``, the segment table's column names, only those it
    has: a property no recording has is no column); the segment id and the viewer's own "recording link" (it opens a
    recording at its last frame) hidden; sorted by property ``sort_by`` (default: the worst relative error first).
    (A ``PreviewCell`` of ``/thumbnail`` needs a column of recording URLs, which the segment table has not.)"""
    from rerun.blueprint import table as rbt
    from rerun.blueprint.encodings import SortBy

    shown = [rbt.Column(property_column(OPEN), name="recording", column_type=rr.components.Url),
             rbt.Column("rerun_segment_id", visible=False)]  # the button shows the id
    shown += [rbt.Column(property_column(c), name=c) for c in columns
              if c != "id" and (present is None or property_column(c) in present)]
    shown.append(rbt.Column(VIEWER_LINK_COLUMN, visible=False))
    return rbt.TableBlueprint(table_layout=rbt.TableLayout(columns=shown),
                              sort_by=SortBy(property_column(sort_by), direction=direction))


def write_link(path: str | Path, segment_id: str, url: str) -> Path:
    """``path``: a recording of ``segment_id`` holding only the ``open`` property, ``url`` as a
    ``rerun.components.Url`` (the viewer shows it as a button that opens it): what ``massviz serve`` registers as
    each segment's ``link`` layer (``LINK_LAYER``) once the dataset's URL is known."""
    path = Path(path)
    stream = rr.RecordingStream(APPLICATION_ID, recording_id=segment_id)
    try:
        data = stream.binary_stream()  # in memory, then one write: a third of a file sink's time (~1 ms)
        stream.send_property(PROPERTY, rr.AnyValues().with_component_override(OPEN, "rerun.components.Url", url))
        path.write_bytes(data.read(flush=True))
    finally:
        stream.disconnect()
    return path


def save_blueprints(folder: str | Path, recording: rrb.Blueprint | None = None,
                    table=None) -> tuple[Path, Path]:
    """Write a dataset's recording layout and segment-table layout as ``.rbl`` files into ``folder`` (default: a
    light recording's with 5 patch tiles, ``dataset_blueprint``, and ``table_blueprint``)."""
    folder = Path(folder)
    paths = folder / "massviz_recording.rbl", folder / "massviz_table.rbl"
    (recording or dataset_blueprint()).save(APPLICATION_ID, paths[0])
    (table or table_blueprint()).save(APPLICATION_ID, paths[1])
    return paths


__all__ = ["PROPERTY", "INDEX_NAME", "PATCHES_NAME", "TABLE_COLUMNS", "PATCH_COLUMNS", "property_column", "ccm_view",
           "input_bytes", "best_frame", "recording_properties", "send_properties", "write_recording", "write_index", "write_dataset",
           "log_light", "light_blueprint", "dataset_blueprint", "table_blueprint", "save_blueprints", "rrd_name",
           "OPEN", "LINK_LAYER", "write_link"]
