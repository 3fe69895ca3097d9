"""Test support (not part of the massviz package): what an .rrd file holds, read back with Rerun's own reader, so tests
(and a curious user) can check the entity tree a command wrote."""
from __future__ import annotations

from collections import defaultdict
from pathlib import Path

from massviz.errors import MassvizError


def rrd_contents(path: str | Path) -> dict[str, set[str]]:
    """Entity path → its components (e.g. ``"AssetVideo:blob"``) in the first recording of an .rrd file
    (recording properties ``/__properties`` left out)."""
    from rerun.chunk import RrdReader

    path = Path(path)
    if not path.is_file():
        raise MassvizError("no such .rrd file", path)
    try:
        reader = RrdReader(path)
        try:
            schema = reader.store().schema()
        except Exception:  # noqa: BLE001 - files without a footer: read every chunk instead
            schema = reader.stream().collect().schema()
    except Exception as err:  # noqa: BLE001 - any read problem is a corrupt file
        raise MassvizError(f"not a readable Rerun .rrd file ({type(err).__name__}: {err})", path) from None
    out: dict[str, set[str]] = defaultdict(set)
    for col in schema.component_columns():
        if not col.is_property:
            out[col.entity_path].add(col.component)
    return dict(out)


def rrd_entities(path: str | Path) -> set[str]:
    """Entity paths logged in the first recording of an .rrd file."""
    return set(rrd_contents(path))


__all__ = ["rrd_contents", "rrd_entities", "rrd_rows"]


def rrd_rows(path: str | Path, entity: str, timeline: str = "frame") -> list[dict]:
    """Every row logged at ``entity`` in an .rrd, in time order (ties: logging order): {"time": sequence on
    ``timeline`` (None for static rows), component or AnyValues field name: its value (lists as logged)}. A row
    holding only a ``Clear`` has the key ``"clear"``."""
    from rerun.chunk import RrdReader

    rows = []
    for chunk in RrdReader(Path(path)).stream():
        if chunk.entity_path != entity:
            continue
        batch = chunk.to_record_batch()
        names = batch.schema.names
        times = batch.column(names.index(timeline)).to_pylist() if timeline in names else [None] * batch.num_rows
        ids = batch.column(0).to_pylist()
        for r in range(batch.num_rows):
            row = {"time": times[r], "row_id": ids[r]}
            for c, name in enumerate(names):
                if c == 0 or batch.schema.field(c).metadata and b"rerun:kind" in batch.schema.field(c).metadata \
                        and batch.schema.field(c).metadata[b"rerun:kind"] in (b"index", b"control"):
                    continue
                value = batch.column(c)[r].as_py()
                if value is not None:
                    row["clear" if name.startswith("Clear:") else name] = value
            rows.append(row)
    return sorted(rows, key=lambda row: (row["time"] is not None, row["time"] or 0, row["row_id"]))
