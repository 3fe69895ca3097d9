"""massviz: container empty-mass estimation from one RGB-D camera, every stage traced and visible."""
from __future__ import annotations

__version__ = "0.1.0"
