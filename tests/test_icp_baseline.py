"""ICP baseline on a generated touching scene."""

from __future__ import annotations

import numpy as np
import pytest

from workbench import synth
from workbench.bench import baseline
from workbench.geometry import invert_pose
from workbench.io import bop
from workbench.score import metrics

pytestmark = pytest.mark.slow  # needs generated scenes (pybullet)


@pytest.fixture(scope="module")
def touching(tmp_path_factory):
    out = tmp_path_factory.mktemp("icp")
    synth.make_scenes(out, ["touching"], 1, seed=1, width=320, height=240, sensor="kinect-like")
    frame = bop.load_frame(out, 0, 0)
    return frame, bop.load_models(out, frame.object_ids)


def test_icp_finds_visible_touching_boxes_within_3cm(touching):
    frame, models = touching
    est = baseline.estimate_icp(frame, models, None, None, n_starts=24, seed=0)
    assert sorted(est) == sorted(frame.object_ids)
    T_world_cam = invert_pose(frame.camera.T_cam_world)
    for k, obj_id in enumerate(frame.object_ids):
        gt, T = T_world_cam @ frame.gt_T_cam_obj[k], T_world_cam @ est[obj_id]
        assert metrics.position_error(gt, T) < 0.03, obj_id
        assert metrics.rotation_error(gt, T, models[obj_id].symmetries) < 10, obj_id


def test_unseen_object_is_parked_on_the_table_with_no_score(touching):
    frame, models = touching
    vis = synth.visible_masks(frame.camera.K, frame.camera.width, frame.camera.height,
                              [models[i].mesh for i in frame.object_ids], frame.gt_T_cam_obj)
    seen, unseen = frame.object_ids
    masks = {seen: vis[0], unseen: np.zeros_like(vis[1])}
    fits = baseline.estimate_icp_fits(frame, models, masks, n_starts=8)
    assert fits[unseen].n_points == 0 and fits[unseen].fitness == 0.0
    assert fits[seen].n_points > 100 and fits[seen].fitness > 0.8
    T_world = invert_pose(frame.camera.T_cam_world) @ fits[unseen].T_cam_obj
    lo, _ = models[unseen].mesh.bounds
    assert np.allclose(T_world[:3, 3], [0, 0, -lo[2]], atol=1e-9)  # resting at the table centre
