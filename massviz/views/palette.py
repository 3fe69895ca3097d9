"""The colours every view uses, defined once (RGB 0..1): Rerun, Open3D, the matplotlib figures and the notebook
widgets import them here, so a chosen patch has one colour everywhere and a flagged one another.

* ``CHOSEN_COLOUR``: a chosen patch (its box, mask, points, tile outline, prediction series);
* ``FLAGGED_COLOUR``: a chosen patch that is flagged as probably not the container (``trace.flags``), instead of
  the chosen colour;
* ``OTHER_COLOUR``: other detections in the matplotlib figures; ``BELOW_THRESHOLD_COLOUR``: detections at or below
  the trace's threshold;
* ``track_colour(t)``: the other detections in Rerun, one colour per object track (``detections.track``), from a
  qualitative palette without the chosen and flagged colours' hues;
* ``BOX_COLOUR``: the measured 3D box of a chosen detection.
"""
from __future__ import annotations

#: a chosen patch's points, box and outline (other detections keep their own colours).
CHOSEN_COLOUR = (1.0, 0.1, 0.75)
#: a chosen patch flagged as probably not the container.
FLAGGED_COLOUR = (1.0, 0.23, 0.19)
#: the estimate without the flagged patches (Rerun's /predictions/estimate_without_flagged, the estimate figure).
WITHOUT_FLAGGED_COLOUR = (0.2, 0.8, 1.0)
#: other detections (matplotlib figures) and detections at or below the threshold.
OTHER_COLOUR = (0.22, 0.71, 1.0)
BELOW_THRESHOLD_COLOUR = (0.5, 0.5, 0.5)
#: the measured 3D box of a chosen detection.
BOX_COLOUR = (0.05, 0.85, 0.2)
#: one colour per track (Tableau 10 without its red and pink, too close to the flagged and chosen colours).
TRACK_COLOURS = ((0.12, 0.47, 0.71), (1.0, 0.5, 0.05), (0.17, 0.63, 0.17), (0.58, 0.4, 0.74), (0.55, 0.34, 0.29),
                 (0.5, 0.5, 0.5), (0.74, 0.74, 0.13), (0.09, 0.75, 0.81))


def track_colour(track: int) -> tuple[float, float, float]:
    """The colour of object track ``track`` (ids >= 1; 0 = untracked gets the first)."""
    return TRACK_COLOURS[(max(int(track), 1) - 1) % len(TRACK_COLOURS)]


def rgb255(colour) -> tuple[int, int, int]:
    """A palette colour as 0..255 integers (Rerun, OpenCV)."""
    return tuple(int(round(255 * c)) for c in colour)


def hex_colour(colour) -> str:
    """A palette colour as ``#rrggbb`` (matplotlib, HTML)."""
    return "#" + "".join(f"{v:02x}" for v in rgb255(colour))


CHOSEN_HEX, FLAGGED_HEX, OTHER_HEX = hex_colour(CHOSEN_COLOUR), hex_colour(FLAGGED_COLOUR), hex_colour(OTHER_COLOUR)
