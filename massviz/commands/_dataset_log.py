"""``massviz log DATASET --rrd-dir OUT/``: one .rrd per recording, with recording properties, for a catalog
(``massviz serve OUT/``). The recordings run on the dataset runner (``--engine local|ray``) like ``estimate``; each
worker writes its recording's .rrd itself (``massviz.views.rerun_dataset.write_recording``), the driver writes
``index.csv`` and ``patches.csv`` at the end, all in a hidden folder beside OUT that replaces OUT when the run ends
(``massviz.io.atomic.atomic_dir``: the files of OUT that are not a dataset's are kept)."""
from __future__ import annotations

import functools
import os
import sys
from pathlib import Path

#: what a dataset folder holds that ``--force`` may replace (nothing else is touched).
OWN_FILES = ("*.rrd", "index.csv", "patches.csv", "patches/*.jpg")
#: the sub-folder massviz writes the thumbnails into.
OWN_DIRS = ("patches",)


def collect_rrd(trace, recording, truth, *, out_dir: str, full: bool, view: int | None, video: str) -> dict:
    """What a worker does with one trace: write its .rrd (and patch thumbnails) and return the index row."""
    from massviz.commands._common import flag_warning
    from massviz.measure3d.stage import measured_replay
    from massviz.views.rerun_dataset import write_recording

    if truth is not None:  # --annotations: the CCM ground truth goes into the trace's meta, read by its properties
        meta = dict(trace.recording.meta)
        meta["container"] = {**meta.get("container", {}), **truth}
        trace.recording.meta = meta
    result = write_recording(trace, recording, out_dir, full=full, view=view, video=video, replay=measured_replay)
    result["warning"] = flag_warning("log", trace)
    return result


def _check_no_links(out: Path) -> None:
    """A symlink where massviz writes (``patches/``, a ``.rrd``, ``index.csv`` ...) is refused before anything is
    written or removed: files are never written through, or removed behind, a link out of OUT."""
    from massviz.errors import MassvizError

    for name in OWN_DIRS:
        if (out / name).is_symlink():
            raise MassvizError(f"holds the symlink {name}; massviz writes its own {name}/ folder there, never through "
                               "a link (remove the link)", out)
    for pattern in OWN_FILES:
        for p in out.glob(pattern):
            if p.is_symlink():
                raise MassvizError(f"holds the symlink {p.relative_to(out)}; massviz never replaces or writes through "
                                   "a link in its output (remove the link)", out)


def run_rrd_dir(args) -> int:
    from massviz.commands._common import build
    from massviz.commands._runner import exit_status, open_dataset, run_tasks
    from massviz.errors import MassvizError
    from massviz.io.atomic import atomic_dir, check_output_dir
    from massviz.runners.dataset import Task
    from massviz.views.rerun_dataset import INDEX_NAME, rrd_name, write_index

    if args.spawn or args.rrd or args.ply:
        raise MassvizError("--rrd-dir writes one .rrd per recording: leave out --rrd, --spawn and --ply")
    out = check_output_dir(args.rrd_dir, "--rrd-dir")
    if out.is_dir() and (os.path.lexists(out / INDEX_NAME) or any(out.glob("*.rrd"))) and not args.force:
        raise MassvizError("already holds a dataset of .rrd files (pass --force to replace it)", out)
    if out.is_dir():
        _check_no_links(out)
    args.recordings = [args.recording]
    tasks, failed, recordings, on_error = open_dataset(args)
    names: dict[str, str] = {}
    for rec in recordings.values():
        if (other := names.setdefault(rrd_name(rec.id), rec.id)) != rec.id or \
                sum(r.id == rec.id for r in recordings.values()) > 1:
            raise MassvizError(f"recording id {rec.id!r} (or {other!r}) is not unique in this dataset: each recording "
                               "is one segment, named by its id", rec.path)
    truths = {}
    if args.annotations:
        from massviz.evaluation.metrics import default_class_of
        from massviz.io.ccm_annotations import read_annotations
        from massviz.io.patch_set import annotation_for

        table = read_annotations(args.annotations)
        for t in tasks:
            ann = annotation_for(recordings[t.index], table, args.annotations)
            cls = default_class_of(ann.container_id) if 1 <= ann.container_id <= 9 else None
            truths[t.index] = {"mass_g": ann.mass_g, "id": ann.container_id, **({"class": cls} if cls else {})}
    tasks = [Task(t.index, t.path, t.id, truths.get(t.index)) for t in tasks]
    view = args.view if any(recordings[t.index].kind == "ccm" for t in tasks) else None
    # the whole dataset is written in a hidden folder beside OUT and renamed into place at the end: a killed run
    # leaves OUT as it was, and of writers at once OUT ends as one writer's whole output
    with atomic_dir(out, keep_others=OWN_FILES + OWN_DIRS) as stage:
        collect = functools.partial(collect_rrd, out_dir=str(stage.resolve()), full=args.full, view=view,
                                    video=args.video)
        outcomes = run_tasks(args, "log", build(args), tasks, failed, on_error, collect, desc="log",
                             recordings=recordings)
        results = [o.value for o in outcomes if o.ok]
        for r in results:
            if r.get("warning"):
                print(r["warning"], file=sys.stderr)
        index, _ = write_index(stage, results)
    kind = "full" if args.full else "light"
    if len(index):
        rrd, inp = float(index["rrd_bytes"].mean()), float(index["input_bytes"].mean())
        ratio = f", {rrd / inp:.2f}x the input's {inp:,.0f}" if inp > 0 else ""
        size = f"; {rrd:,.0f} bytes per recording{ratio}"
    else:
        size = ""
    n_failed = sum(not o.ok for o in outcomes)
    print(f"wrote {len(index)} {kind} recording(s) to {out}{size}"
          + (f", {n_failed} failed" if n_failed else "") + f"; browse them with: massviz serve {out}",
          file=sys.stderr)
    return exit_status(outcomes)
