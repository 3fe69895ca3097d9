"""Sinks: Rerun, Open3D, matplotlib figures and notebook widgets. They only read traces (and recordings' frames)."""
