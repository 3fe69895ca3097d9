"""The one detector interface every detector implements: ``massviz.core.detector.Detector`` (re-exported here)."""
from __future__ import annotations

from massviz.core.detector import Detector

__all__ = ["Detector"]
