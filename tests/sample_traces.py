"""Traces of the bundled samples, computed once per test session into one trace cache (depth detector, published
weights, the paper's threshold 0.4 and K = 5, every frame) and shared by test_widgets and test_notebooks."""
from __future__ import annotations

from pathlib import Path

WEIGHTS = Path("weights") / "corsmal_visual" / "Encoder_pool_aug_158.torch"


def sample_cache(tmp_path_factory, shared_dir: Path, samples_dir: Path) -> Path:
    """The session's trace cache folder, filled with the samples' traces on first use."""
    import pytest

    from massviz.app import process_recordings
    from massviz.io.recording import collect_recordings

    if not (samples_dir / "cup_handover" / "meta.json").is_file():
        pytest.skip("the bundled samples (data_samples/) are missing")
    root = tmp_path_factory.getbasetemp() / "massviz-sample-traces"
    if not (root / "complete").is_file():
        process_recordings(collect_recordings([samples_dir]), detector="depth", weights=str(shared_dir / WEIGHTS), cache=str(root),
                           quiet=True)
        (root / "complete").write_text("ok\n")
    return root
