"""Test support (not used by massviz itself): what an .rrd file holds, read back with Rerun's own reader, so tests
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


__all__ = ["rrd_contents", "rrd_entities"]
