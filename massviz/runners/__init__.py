"""Runners: loops that drive the per-frame pipeline step (``massviz.core.pipeline.FramePipeline``) over recordings."""
