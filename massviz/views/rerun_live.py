"""Old import path of ``massviz.views.rerun.live`` (kept so existing imports work)."""
from __future__ import annotations

from massviz.views.rerun.live import LiveLogger  # noqa: F401

__all__ = ["LiveLogger"]
