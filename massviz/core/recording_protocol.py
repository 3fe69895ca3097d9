"""The ``Recording`` protocol: what every recording format gives the pipeline and the sinks.

Pure typing (no I/O): the formats that implement it live in ``massviz.io.formats`` (one module per format, each
owning its reader and its writer), ``massviz.io.recording.open_recording`` picks the format of a path.

Sinks ask a recording for what they need through these members only (``video_file()``, ``source_description()``,
the encoded bytes on each ``Frame``), never by testing a format's own attributes.
"""
from __future__ import annotations

from pathlib import Path
from typing import Iterator, Protocol, runtime_checkable

import numpy as np

from massviz.core.types import Frame, Intrinsics, RecordingInfo


@runtime_checkable
class Recording(Protocol):
    """An RGB-D recording: frames streamed in order, one frame or one depth map by index, and what a trace keeps.

    ``kind`` names the format ("folder", "ccm", "realsense"); ``meta`` is the recording's annotations (meta.json,
    or what a format records about itself); ``notes`` are one-line warnings about the data (e.g. a partial video),
    which the pipeline copies into the trace's events."""

    path: Path
    kind: str
    id: str
    width: int
    height: int
    num_frames: int
    fps: float
    intrinsics: Intrinsics | None
    meta: dict
    notes: list

    @property
    def config_id(self) -> str:
        """The id of the challenge CSV's 'Configuration ID' column."""

    def input_files(self) -> list[Path]:
        """Every file the frames are read from (the content key hashes their bytes)."""

    def fingerprint(self, hasher=None, read: bool = True, known: dict | None = None) -> str | None:
        """Content key of the frames (a digest of the input files' bytes; ``known``: of the bytes a run read);
        ``read`` False: None when a file would have to be read to know it."""

    def info(self) -> RecordingInfo:
        """What a trace keeps of this recording."""

    def video_file(self) -> Path | None:
        """The RGB video a viewer can show as one asset, or None when the format has none."""

    def source_description(self) -> dict[str, str]:
        """Where the frames come from, for people: {"rgb": ..., "depth": ...}."""

    def frames(self, stride: int = 1, indices=None) -> Iterator[Frame]:
        """Every ``stride``-th frame (or only ``indices``), streamed in order."""

    def read_frame(self, index: int) -> Frame:
        """One frame by index."""

    def read_depth(self, index: int) -> np.ndarray:
        """Depth of frame ``index`` (H×W uint16 mm); each format's docstring says what it costs."""


__all__ = ["Recording"]
