"""Kept for modules that still import from here: the samples' trace cache now lives in ``support`` and is served by
the ``sample_cache``/``sample_traces`` fixtures of conftest.py."""
from support import WEIGHTS, sample_cache  # noqa: F401
