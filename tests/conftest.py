from pathlib import Path

import pytest

from workbench.synth import make_scenes


@pytest.fixture(scope="session")
def touching_dataset(tmp_path_factory) -> Path:
    """One generated frame of two touching boxes (the estimator's acceptance case), 320x240 to stay quick."""
    out = tmp_path_factory.mktemp("touching")
    make_scenes(out, ["touching"], 1, seed=3, width=320, height=240)
    return out
