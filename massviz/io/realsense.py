"""Intel RealSense recordings and cameras, through ``pyrealsense2`` (the optional extra ``massviz[realsense]``).

The code lives in ``massviz.io.formats``, one module per job: ``realsense_decode`` (framesets -> ``Frame``, stream
checks), ``realsense_device`` (reading an ``rs.device``), ``realsense_file`` (the .db3/.bag reader),
``realsense_live`` (cameras, real-time playback, software devices) and ``realsense_write`` (the .db3 writer).
This module re-exports their public names for older imports.
"""
from __future__ import annotations

from massviz.io.formats.realsense_decode import (INSTALL_HINT, SUFFIXES, FrameDecoder, StreamInfo, import_rs,
                                                 is_realsense_file, stream_info)
from massviz.io.formats.realsense_device import FILE_TIMEOUT_S, DeviceReader, FileFrames, playback_device
from massviz.io.formats.realsense_file import RealSenseRecording, db3_check, db3_frames, open_realsense
from massviz.io.formats.realsense_live import (LiveStream, SoftwareCamera, list_cameras, open_camera,
                                               open_device_stream, open_file_stream)
from massviz.io.formats.realsense_write import SoftwareRig, write_realsense

_SoftwareRig = SoftwareRig  # the name older tests and benchmarks use

__all__ = ["INSTALL_HINT", "SUFFIXES", "FILE_TIMEOUT_S", "FrameDecoder", "StreamInfo", "DeviceReader", "FileFrames",
           "RealSenseRecording", "LiveStream", "SoftwareCamera", "SoftwareRig", "import_rs", "is_realsense_file",
           "stream_info", "playback_device", "db3_check", "db3_frames", "open_realsense", "list_cameras",
           "open_camera", "open_device_stream", "open_file_stream", "write_realsense"]
