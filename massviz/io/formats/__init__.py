"""The recording formats, one module per format, each owning its reader and (where massviz writes the format) its
writer: ``folder`` (massviz folders; ``FolderFrameWriter``/``write_folder``), ``ccm`` (CORSMAL, read only),
``realsense_file`` (.db3/.bag; writer ``realsense_write``), ``realsense_live`` (cameras, software devices), on
``common`` (shared helpers) and ``realsense_decode``/``realsense_device``. ``massviz.io.recording.open_recording``
dispatches a path to its format; the protocol they implement is ``massviz.core.recording_protocol.Recording``."""
