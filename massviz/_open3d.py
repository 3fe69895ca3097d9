"""The one import of Open3D, without its Jupyter side effects: ``from massviz._open3d import o3d``.

In a Jupyter kernel ``import open3d`` prints "Jupyter environment detected. Enabling Open3D WebVisualizer." and two
"[Open3D INFO] WebRTC ..." lines into the cell's output, and ``open3d.visualization`` imports ``draw_plotly``, which
imports Dash, whose Jupyter module opens a comm (target ``dash``) no notebook frontend here handles ("No handler found
for comm target 'dash'"). massviz draws with Rerun, matplotlib and Open3D's renderers, never with the WebVisualizer or
Plotly, so before the first import of Open3D this sets ``OPEN3D_DISABLE_WEB_VISUALIZER=true`` (unless the user set it)
and puts a stand-in for ``open3d.visualization.draw_plotly`` whose three functions import the real module (and Dash)
when first called. Importing Open3D yourself before massviz keeps Open3D's own behaviour.
"""
from __future__ import annotations

import importlib.machinery
import importlib.util
import os
import sys
import types

_PLOTLY = "open3d.visualization.draw_plotly"


def _real_plotly():
    mod = sys.modules.get(_PLOTLY)
    if mod is not None and not getattr(mod, "_massviz_stand_in", False):
        return mod
    import open3d.visualization as vis

    spec = importlib.machinery.PathFinder.find_spec(_PLOTLY.rsplit(".", 1)[1], list(vis.__path__))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    sys.modules[_PLOTLY] = mod
    return mod


def _stand_in() -> types.ModuleType:
    mod = types.ModuleType(_PLOTLY, "massviz's stand-in: imports open3d's draw_plotly (and Dash) on first use")
    mod._massviz_stand_in = True
    for name in ("get_plotly_fig", "draw_plotly", "draw_plotly_server"):
        def call(*args, _name=name, **kwargs):
            return getattr(_real_plotly(), _name)(*args, **kwargs)
        call.__name__ = name
        setattr(mod, name, call)
    return mod


if "open3d" not in sys.modules:
    os.environ.setdefault("OPEN3D_DISABLE_WEB_VISUALIZER", "true")
    if "dash" not in sys.modules:
        sys.modules.setdefault(_PLOTLY, _stand_in())

import open3d as o3d  # noqa: E402

__all__ = ["o3d"]
