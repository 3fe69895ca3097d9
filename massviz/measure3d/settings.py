"""What the measure stage needs before any cloud is made (no Open3D here): its settings and whether a recording
can be measured (its camera intrinsics)."""
from __future__ import annotations

from massviz.core.types import Intrinsics
from massviz.errors import MassvizError

#: default farthest depth (m) kept in clouds.
DEPTH_TRUNC_M = 4.0
#: half-width (m) of the depth band around a detection's median depth kept in its cloud.
BAND_M = 0.25


def skip_reason(recording) -> str | None:
    """One line saying why ``recording`` gets no 3D stage, or None when it has intrinsics."""
    if getattr(recording, "intrinsics", None) is None:
        where = ("a calib/NNNNNN.pickle beside the CCM view" if getattr(recording, "kind", "") == "ccm"
                 else "intrinsics.json in the recording folder")
        return f"{recording.id}: no camera intrinsics ({where}), so no 3D: clouds and measurements skipped"
    return None


def require_intrinsics(recording) -> Intrinsics:
    """The recording's intrinsics, or a ``MassvizError`` naming what is missing."""
    reason = skip_reason(recording)
    if reason:
        raise MassvizError(reason)
    return recording.intrinsics


__all__ = ["DEPTH_TRUNC_M", "BAND_M", "skip_reason", "require_intrinsics"]
