"""``Selection`` is the one check of K, threshold and stride (``Selection.check``): the options, the command line,
``massviz sweep``'s grid, a run folder's ``index.csv``, a trace file and the trace cache refuse a bad value with the
same words; and a run's selection is resolved for the detector's score cut once (``Selection.at_cut``), when the
pipeline is made, then carried to every stage."""
from __future__ import annotations

import json
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from massviz.app import Pipeline, PipelineOptions, build_pipeline
from massviz.core.selection import Selection
from massviz.core.trace import Trace
from massviz.core.types import Detections
from massviz.errors import MassvizError
from massviz.io.recording import open_recording

CUP = Path(__file__).resolve().parents[1] / "data_samples" / "cup_handover"

#: (selection value, bad value, the words every edge refuses it with)
BAD = [("threshold", 1.2, "must be in [0, 1), got 1.2"), ("threshold", -0.5, "must be in [0, 1), got -0.5"),
       ("k", 0, "must be >= 1, got 0"), ("k", 2.5, "must be an integer, got 2.5"),
       ("stride", 0, "must be >= 1, got 0")]


def _trace() -> Trace:
    """A valid trace of the cup sample without detections (what a file's header is checked on)."""
    return Trace(recording={"id": "cup_handover"}, detector={"name": "fake"}, detect_threshold=0.4, threshold=0.5,
                 k=5, stride=1, frames=np.arange(3), detections=Detections(), selection=np.zeros(0, np.int64),
                 estimate=-1.0)


def _with_header(path: Path, name: str, value) -> None:
    """Rewrite the trace file ``path`` with ``value`` as its header's ``name``."""
    data = dict(np.load(path))
    header = json.loads(data["header"].tobytes())
    header[name] = value
    data["header"] = np.frombuffer(json.dumps(header).encode(), dtype=np.uint8)
    np.savez_compressed(path, **data)


@pytest.mark.parametrize("name, value, words", BAD)
def test_a_bad_k_threshold_or_stride_is_refused_with_the_same_words_everywhere(name, value, words, tmp_path,
                                                                               capsys, caplog):
    from massviz.cli import main
    from massviz.io.cache import TraceCache
    from massviz.io.run_folder import row_settings
    from massviz.io.trace_file import load_trace, save_trace

    refusals = {}
    with pytest.raises(ValueError) as err:
        Selection(**{name: value})
    refusals["Selection"] = (str(err.value), name)
    with pytest.raises(MassvizError) as err:
        PipelineOptions(**{name: value}).check()
    refusals["the options"] = (str(err.value), f"--{name}")
    if isinstance(value, int) or name == "threshold":  # what the command line's parser passes on
        capsys.readouterr()
        assert main(["estimate", str(CUP), "--detector", "depth", "--no-cache", "--out", str(tmp_path / "o.csv"),
                     f"--{name}", str(value)]) == 2
        refusals["massviz estimate"] = (capsys.readouterr().err.strip().splitlines()[-1], f"--{name}")
        assert not (tmp_path / "o.csv").exists()
        if name != "stride":  # sweep's grid of thresholds and K
            assert main(["sweep", str(CUP), "--cached-only", f"--{name}", f"{'0.4' if name == 'threshold' else 1},"
                         f"{value}"]) == 2
            refusals["massviz sweep"] = (capsys.readouterr().err.strip().splitlines()[-1], f"--{name}")
    index = tmp_path / "run" / "index.csv"
    row = pd.Series({"detector": "depth", "threshold": 0.4, "k": 5, "stride": 1, name: value})
    with pytest.raises(MassvizError) as err:
        row_settings(row, index, "cup_handover")
    refusals["a run folder"] = (str(err.value), f"{index}: recording 'cup_handover': column '{name}'")
    path = save_trace(_trace(), tmp_path / "t.npz")
    _with_header(path, name, value)
    with pytest.raises(MassvizError) as err:
        load_trace(path)
    refusals["a trace file"] = (str(err.value), f"header {name}")
    with tempfile.TemporaryDirectory() as root:  # a short path: the cache's warning keeps 200 characters of it
        cache = TraceCache(root)
        cup = open_recording(CUP)
        entry = cache.save(_trace(), cup, {"name": "fake"})
        _with_header(entry, name, value)
        caplog.clear()
        assert cache.load(cup, {"name": "fake"}, 1, 0.9) is None  # dropped, to be computed again
        refusals["the trace cache"] = (caplog.text, f"header {name}")
        assert not entry.exists()
    for edge, (message, label) in refusals.items():
        assert f"{label} {words}" in message, (edge, message)


def test_the_selection_is_resolved_once_when_the_pipeline_is_made_and_carried(weights, tmp_path, monkeypatch):
    """A spy counts ``Selection.at_cut``: once for the pipeline, whatever runs after it (the detector, the cache, a
    per-frame step); once for a pipeline made from memory; once for a selection given to one call."""
    calls = []
    at_cut = Selection.at_cut
    monkeypatch.setattr(Selection, "at_cut", lambda self, cut: calls.append(cut) or at_cut(self, cut))
    cup = open_recording(CUP)
    pipeline = build_pipeline(detector="depth", weights=str(weights), cache=str(tmp_path), stride=6, quiet=True)
    assert calls == [0.4] and pipeline.selection == Selection(k=5, threshold=0.4, stride=6)
    cold = pipeline.process(cup)  # the detector runs: app.process, run and FramePipeline get the resolved selection
    warm = pipeline.process(cup, exclude=[int(cold.selection[0])])  # from the cache, with an exclusion
    pipeline.frame_pipeline(cup.info())
    assert "cache" not in cold.timings and "cache" in warm.timings and warm.estimate != cold.estimate
    assert calls == [0.4]
    cached = Pipeline.from_memory(pipeline.options, pipeline.memory(), tmp_path)
    assert cached.selection == pipeline.selection and len(calls) == 2
    assert cached.process(cup).estimate == cold.estimate and len(calls) == 2
    assert pipeline.process(cup, selection=Selection(k=2, stride=6)).k == 2 and len(calls) == 3
