from pathlib import Path

import pytest

from workbench.synth import make_scenes

# The tests' generated data is made with the kinect-like sensor their expectations were set on: make-scenes' default
# is the measured xtion since 2026-12-07, and tests/test_sensor_stats.py tests the sensors themselves.


@pytest.fixture(scope="session")
def touching_dataset(tmp_path_factory) -> Path:
    """One generated frame of two touching boxes (the estimator's acceptance case), 320x240 to stay quick."""
    out = tmp_path_factory.mktemp("touching")
    make_scenes(out, ["touching"], 1, seed=3, width=320, height=240, sensor="kinect-like")
    return out


@pytest.fixture(scope="session")
def hidden_handle_dataset(tmp_path_factory) -> Path:
    """One generated frame of a mug whose handle is hidden behind its body, seen from the camera: the depth leaves
    its heading open, so even a short run's posterior has several modes (the workbench's posterior tests)."""
    out = tmp_path_factory.mktemp("hidden_handle")
    make_scenes(out, ["handle_hidden"], 1, seed=0, width=320, height=240, sensor="kinect-like")
    return out


@pytest.fixture(scope="session", autouse=True)
def workbench_home(tmp_path_factory) -> Path:
    """The user data folder (where the app copies the demo) of every test and the processes it starts: never the
    real home."""
    import os

    home = tmp_path_factory.mktemp("workbench-home")
    os.environ["WORKBENCH_HOME"] = str(home)
    return home


@pytest.fixture(scope="session", autouse=True)
def private_cache(tmp_path_factory):
    """Collision shapes and decimated render meshes are cached under $XDG_CACHE_HOME: keep the tests' own."""
    import os

    saved = os.environ.get("XDG_CACHE_HOME")
    os.environ["XDG_CACHE_HOME"] = str(tmp_path_factory.mktemp("cache"))
    yield
    if saved is None:
        os.environ.pop("XDG_CACHE_HOME", None)
    else:
        os.environ["XDG_CACHE_HOME"] = saved


@pytest.fixture(scope="session")
def seeing():
    """``seeing(problem, scene)``: the problem with its observed depth replaced by ``scene`` (K, 4, 4, table frame)
    drawn as given, over the problem's table: an observation that a test controls exactly."""
    from dataclasses import replace

    import numpy as np

    from workbench.evaluation import LocalEvaluator
    from workbench.render.likelihood import predicted_depth

    def draw(problem, scene):
        local = LocalEvaluator(problem)
        try:
            rendered = local.renderer.render(np.asarray(scene)[None])
        finally:
            local.close()
        return replace(problem, observed=predicted_depth(rendered, problem.background)[0].astype(np.float32))

    return draw


@pytest.fixture(scope="module")
def cluster():
    """A one-node Ray cluster of 2 CPUs, as `ray start --head --num-cpus 2` would start -> its address (one per test
    module that asks for it: tests/test_estimate_ray.py, tests/test_track_ray.py)."""
    ray = pytest.importorskip("ray")
    from ray.cluster_utils import Cluster

    head = Cluster(initialize_head=True, head_node_args={"num_cpus": 2, "include_dashboard": False})
    yield head.address
    ray.shutdown()
    head.shutdown()
