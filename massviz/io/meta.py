"""meta.json and intrinsics.json of a recording: the one check of every meta.json field massviz reads, and the one
writer of intrinsics.json.

``check_meta`` runs where a meta.json is read (``massviz.io.recording``); ``massviz.core.types.GroundTruth.from_meta``
then reads the checked dict and never fails.
"""
from __future__ import annotations

import json
from pathlib import Path

from massviz.core.types import Intrinsics
from massviz.errors import RecordingError
from massviz.io.untrusted import MAX_INDEX, frame_path, number, text_id

#: the container's sizes in meta.json (mm, and mL for the capacity).
SIZE_KEYS = ("width_top_mm", "width_bottom_mm", "height_mm", "depth_mm", "capacity_ml")


def check_meta(meta: dict, path: Path, folder: Path, err=RecordingError) -> dict:
    """Check the fields of a meta.json massviz reads (``err`` naming ``path``): ``id`` and ``config_id`` are text
    without control characters (``config_id`` may be an integer), ``fps`` a finite number in (0, 1000], ``container``
    an object whose ``mass_g`` is finite and > 0, whose sizes are finite and whose ``id`` is an integer,
    ``instances`` maps integer ids to names, and ``instance_masks`` is a ``{frame}`` pattern of a path inside
    ``folder`` (the recording). Returns ``meta``."""
    if "id" in meta:
        text_id(meta["id"], "'id'", path, err)
    if "config_id" in meta:
        cid = meta["config_id"]
        if isinstance(cid, int) and not isinstance(cid, bool):
            number(cid, "'config_id'", path, lo=0, hi=MAX_INDEX, integral=True, error=err)
        elif isinstance(cid, str):
            text_id(cid, "'config_id'", path, err)
        else:
            raise err(f"'config_id' must be a string or an integer, got {cid!r}"[:200], path)
    if "fps" in meta:
        number(meta["fps"], "'fps'", path, lo=0, lo_open=True, hi=1000, error=err)
    container = meta.get("container")
    if container is not None:
        if not isinstance(container, dict):
            raise err(f"'container' must be a JSON object, got {type(container).__name__}", path)
        if container.get("mass_g") is not None:
            number(container["mass_g"], "'container.mass_g'", path, lo=0, lo_open=True, error=err)
        for key in SIZE_KEYS:
            if container.get(key) is not None:
                number(container[key], f"'container.{key}'", path, error=err)
        if container.get("id") is not None:
            number(container["id"], "'container.id'", path, lo=-1, hi=MAX_INDEX, integral=True, error=err)
        if container.get("class") is not None:
            text_id(container["class"], "'container.class'", path, err)
    instances = meta.get("instances")
    if instances is not None:
        if not isinstance(instances, dict):
            raise err("'instances' must be a JSON object {\"id\": {\"name\": ...}}", path)
        for key, value in instances.items():
            if not (key.isdigit() and int(key) <= 65535):
                raise err(f"'instances': key {key[:40]!r} is not an instance id (an integer 0..65535)", path)
            name = value.get("name") if isinstance(value, dict) else value
            text_id(name, f"'instances.{key}' name", path, err)
    if meta.get("instance_masks") is not None:
        frame_path(meta["instance_masks"], folder, 0, path, "'instance_masks'", err)
    return meta


def write_intrinsics(intrinsics: Intrinsics, path: str | Path) -> Path:
    """Write ``intrinsics.json`` (fx, fy, cx, cy, width, height) of a massviz recording folder."""
    path = Path(path)
    path.write_text(json.dumps(intrinsics.to_dict(), indent=1) + "\n")
    return path


__all__ = ["SIZE_KEYS", "check_meta", "write_intrinsics"]
