"""Words the views share: how a flagged patch is named in tile labels, plot titles, series names and tables."""
from __future__ import annotations


def short_reason(flag) -> str:
    """What a flagged patch (``massviz.core.flags.PatchFlag``) is, in a few words: the ground-truth instance its mask
    lies on ("the pitcher", "the container (a part of it)"), else the cues that fired ("border cut, too far")."""
    if flag.ground_truth is not None:
        return f"the {flag.ground_truth}" + (" (a part of it)" if flag.ground_truth == "container" else "")
    return ", ".join(k.replace("_", " ") for k in flag.cue_kinds)


__all__ = ["short_reason"]
