"""The colours every view uses, defined once (RGB 0..1): Rerun, Open3D and the matplotlib figures import them here."""
from __future__ import annotations

#: a chosen patch's points, box and outline (other detections keep their own colours).
CHOSEN_COLOUR = (1.0, 0.1, 0.75)
#: the measured 3D box of a chosen detection.
BOX_COLOUR = (0.05, 0.85, 0.2)


def rgb255(colour) -> tuple[int, int, int]:
    """A palette colour as 0..255 integers (Rerun, OpenCV)."""
    return tuple(int(round(255 * c)) for c in colour)
