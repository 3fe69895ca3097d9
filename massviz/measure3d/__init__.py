"""The optional 3D measure stage (Open3D): each chosen detection's point cloud and its measured size (not the
paper's features d, a and b: ``massviz.core.features``).

``geometry``: back-projection, a detection's cleaned cloud and its measured box; ``stage``: ``MeasureStage``, which
makes each cloud once while a run or a replay is observed and hands the same clouds to the sinks (Rerun, .ply) and
to the measurements. ``massviz.core`` never imports this package: a run without measurement (``massviz estimate``)
does not load Open3D.
"""
