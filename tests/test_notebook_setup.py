"""What a new user meets in the notebooks: JupyterLab of the set-up's venv opens without a "Build Recommended" dialog,
and the patch map's plotly toolbar stays clear of the figure's title."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pandas as pd

from support import ROOT


def setup_page_config_step() -> str:
    """scripts/setup.sh's JupyterLab step: the ``python -c`` that writes the venv's page config."""
    text = (ROOT / "scripts" / "setup.sh").read_text()
    start = text.index("# setup: JupyterLab without the build check")
    return text[text.index(".venv/bin/python -c '", start) + len(".venv/bin/python -c '"):
                text.index("'\n", text.index("p.write_text", start))]


def test_setup_turns_jupyterlabs_build_check_off_for_its_venv(tmp_path):
    prefix = tmp_path / "venv"
    conf = prefix / "etc" / "jupyter" / "labconfig" / "page_config.json"
    conf.parent.mkdir(parents=True)
    conf.write_text(json.dumps({"disabledExtensions": {"x": True}}))  # what is there already is kept
    code = "import sys; sys.prefix = sys.argv[1]\n" + setup_page_config_step()
    subprocess.run([sys.executable, "-c", code, str(prefix)], check=True, timeout=60)
    env = {"JUPYTER_CONFIG_PATH": str(prefix / "etc" / "jupyter"), "JUPYTER_CONFIG_DIR": str(tmp_path / "home"),
           "JUPYTER_PLATFORM_DIRS": "1", "PATH": "/usr/bin:/bin"}
    read = ("import json; from jupyterlab_server.config import get_static_page_config as g; "
            "print(json.dumps(g(level='all')))")
    seen = json.loads(subprocess.run([sys.executable, "-c", read], env=env, capture_output=True, text=True,
                                     check=True, timeout=60).stdout)
    assert seen["buildCheck"] is False and seen["buildAvailable"] is False
    assert seen["disabledExtensions"] == {"x": True}


def test_the_patch_maps_toolbar_is_a_column_beside_the_title():
    from massviz.evaluation.patch_map import PatchMap
    from massviz.views.patch_map_view import PatchMapView

    cols = ["patch_id", "recording", "frame", "rank", "class", "rel_error", "run", "flagged", "x", "y",
            "container_class", "ground_truth"]
    view = PatchMapView(PatchMap(pd.DataFrame(columns=cols), np.zeros((0, 4), np.float32), "pca"), lambda row: b"")
    layout = view.fig.layout
    assert layout.modebar.orientation == "v"  # a horizontal bar sits over the title at the top right
    assert layout.margin.r >= 30 and layout.title.text
