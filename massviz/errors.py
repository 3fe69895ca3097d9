"""Errors massviz reports to users as one clear line (the CLI prints them without a traceback)."""
from __future__ import annotations

from pathlib import Path


class MassvizError(Exception):
    """A user-facing error: ``str(err)`` is one line naming the file and what is wrong."""

    def __init__(self, message: str, path: str | Path | None = None):
        self.path = None if path is None else str(path)
        super().__init__(f"{self.path}: {message}" if self.path else message)


class RecordingError(MassvizError):
    """A recording on disk is missing, incomplete or malformed."""


class WeightsError(MassvizError):
    """Model weights are missing, corrupt or come without their normalisation ranges."""


class DataError(MassvizError):
    """A CSV / JSON input (predictions, annotations, exclusions, ...) is malformed."""
