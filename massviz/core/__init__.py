"""The pipeline's data types and stages: detections, features, the mass CNN, selection, the per-frame step, the trace."""
