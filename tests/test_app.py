"""The workbench server without a browser: the viser-edge conversions, and surviving crashed processes."""

from __future__ import annotations

import io
import os
import signal
import socket

import numpy as np

from workbench.app import protocol as p
from workbench.app.colors import MISSING, VIRIDIS, apply_map
from workbench.app.headless import image_stats
from workbench.app.views import wxyz_from_matrices
from workbench.geometry import matrix_to_quat_wxyz, quat_wxyz_to_matrix, random_rotations, rot_x, rot_z


def test_wxyz_from_matrices_matches_geometry_including_half_turns():
    rng = np.random.default_rng(0)
    R = np.concatenate([random_rotations(rng, 200), rot_x(np.array([np.pi, np.pi - 1e-7])), rot_z(np.array([np.pi]))])
    q = wxyz_from_matrices(R)
    assert np.allclose(quat_wxyz_to_matrix(q), R, atol=1e-6)
    ref = matrix_to_quat_wxyz(R)
    assert np.allclose(np.abs(np.sum(q * ref, axis=-1)), 1.0, atol=1e-6)  # same rotation (q and -q alike)


def test_apply_map_ends_and_missing():
    rgb = apply_map(np.array([-1.0, 0.0, 1.0, 2.0, np.nan]), 0.0, 1.0)
    assert (rgb[0] == VIRIDIS[0]).all() and (rgb[1] == VIRIDIS[0]).all()
    assert (rgb[2] == VIRIDIS[-1]).all() and (rgb[3] == VIRIDIS[-1]).all()
    assert (rgb[4] == MISSING).all()


def test_image_stats_tell_blank_from_drawn():
    from PIL import Image

    def png(a):
        buf = io.BytesIO()
        Image.fromarray(a).save(buf, format="PNG")
        return buf.getvalue()

    blank = np.full((60, 80, 3), 255, np.uint8)
    drawn = blank.copy()
    drawn[20:40, 20:60] = (30, 90, 200)
    assert image_stats(png(blank)) == (0.0, 0.0)
    std, frac = image_stats(png(drawn))
    assert std > 10 and 0.15 < frac < 0.2


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_dead_worker_and_dead_engine_are_restarted_and_the_run_goes_on():
    from workbench.app.server import serve
    from workbench.estimators import EstimatorConfig

    handle = serve(demo=True, block=False, port=free_port(), workers=2,
                   config=EstimatorConfig(particles=16, iterations=50))
    app = handle.app
    try:
        assert app.wait_for(lambda s: s.view is not None and len(s.worker_pids) == 2, 180), app.state.failures
        app.send(p.Step())
        assert app.wait_for(lambda s: s.iteration == 0, 120)

        # A worker dies between iterations: the next step finds out, a new pool takes over, the step is retried.
        dead = app.state.worker_pids[0]
        os.kill(dead, signal.SIGKILL)
        app.send(p.Step())
        assert app.wait_for(lambda s: s.iteration == 1, 120), app.state.failures
        assert app.state.restarts == 1 and dead not in app.state.worker_pids
        assert not app.state.failures

        # The estimator process itself dies: the server starts a new one and reloads the frame.
        old = app.state.engine_pid
        os.kill(old, signal.SIGKILL)
        assert app.wait_for(lambda s: s.engine_pid not in (None, old) and s.view is not None
                            and s.last_state is not None and s.last_state.reason == "reset", 180)
        assert app.state.restarts == 2
        app.send(p.Step())
        assert app.wait_for(lambda s: s.iteration == 0, 120), app.state.failures
        assert not app.state.display_errors
    finally:
        handle.stop()
