"""`workbench label` on generated sequences (``make-scenes --sequence``): a whole sequence labelled in one go as
BOP files that `workbench score` reads back as ground truth, a label moved 3 cm flagged on every frame and clear
once put back, an object taken out halfway flagged until its label ends there. Real pybullet and OpenGL; 320x240
to stay quick."""

import json

import pytest

from workbench.cli import main
from workbench.inference.config import EstimatorConfig
from workbench.io import bop
from workbench.io.results import ResultRow, write_results_csv
from workbench.label.config import LabelConfig
from workbench.label.run import FrameChecker, carry_and_check, gone_from, label_sequence
from workbench.score.metrics import is_right
from workbench.score.scoring import score_results
from workbench.synth.sequence import TakeOut, make_sequences
from workbench.track.config import TrackConfig

pytestmark = pytest.mark.slow

FIRST = ["--particles", "100", "--iterations", "8", "--workers", "1"]  # the first frame's budget: two boxes
CONFIG = EstimatorConfig(particles=100, iterations=8)


def _sequence(out, frames, take_out=None):
    make_sequences(out, ["touching"], 1, frames, seed=0, width=320, height=240, arc_deg=6.0, take_out=take_out,
                   sensor="kinect-like")
    return out


def _label(data, frames, object_ids=None):
    return label_sequence(data, 0, frames, CONFIG, TrackConfig(), LabelConfig(fit_frames=3), workers=1,
                          object_ids=object_ids)


def _checker(data, run):
    ids = run.labels.obj_ids
    return FrameChecker(data, 0, None, ids, bop.load_models(data, ids), LabelConfig().check)


def test_a_sequence_is_labelled_in_one_go_and_score_reads_the_labels_back_as_ground_truth(tmp_path, capsys):
    data = _sequence(tmp_path / "seq", 4)
    scene = data / "test" / "000000"
    truth = {i: bop.load_frame(data, 0, i) for i in range(4)}
    had_info = (scene / "scene_gt_info.json").exists()
    assert main(["label", str(data), "--scene", "0", "--overwrite-gt", *FIRST]) == 0
    err = capsys.readouterr().err
    assert "labelled 4 frame(s) of scene 0: 0 flagged" in err
    assert len(list(scene.glob("scene_gt.json.bak-*"))) == 1
    assert len(list(scene.glob("scene_gt_info.json.bak-*"))) == int(had_info)
    models = bop.load_models(data, truth[0].object_ids)
    for i, frame in truth.items():
        labelled = bop.load_frame(data, 0, i)
        assert labelled.object_ids == frame.object_ids
        assert all(is_right(G, L, models[o].symmetries)
                   for o, G, L in zip(frame.object_ids, frame.gt_T_cam_obj, labelled.gt_T_cam_obj))
    info = json.loads((scene / "scene_gt_info.json").read_text())
    assert all(0.3 < e["visib_fract"] <= 1.0 for e in info["0"])
    provenance = json.loads((scene / "label_provenance.json").read_text())
    assert [f["source"] for f in provenance["frames"].values()] == ["propagated"] * 4
    # The true poses, as results, scored against the labels as ground truth: every object right.
    out = tmp_path / "truth.csv"
    write_results_csv(out, [ResultRow(0, i, o, 1.0, T, 1.0) for i, f in truth.items()
                            for o, T in zip(f.object_ids, f.gt_T_cam_obj)])
    assert main(["score", str(data), str(out)]) == 0
    frames = score_results(data, [ResultRow(0, i, o, 1.0, T, 1.0) for i, f in truth.items()
                                  for o, T in zip(f.object_ids, f.gt_T_cam_obj)])
    assert len(frames) == 4 and all(f.right for f in frames)


def test_a_label_moved_3_cm_is_flagged_on_every_frame_and_clear_once_put_back(tmp_path):
    data = _sequence(tmp_path / "seq", 4)
    run = _label(data, [0, 1, 2, 3])
    assert run.flagged == []
    label = run.labels.objects[0]
    good = label.T_world_obj.copy()
    label.T_world_obj = good.copy()
    label.T_world_obj[0, 3] += 0.03  # along the table
    checker = _checker(data, run)
    try:
        checks, _ = carry_and_check(run.labels, {}, checker)
        assert all(checks[i][0].flagged for i in run.labels.frames)
        label.T_world_obj = good
        checks, _ = carry_and_check(run.labels, {}, checker)
        assert not any(c.flagged for i in run.labels.frames for c in checks[i])
    finally:
        checker.close()


def test_an_object_taken_out_halfway_is_flagged_until_its_label_ends_there(tmp_path):
    data = _sequence(tmp_path / "seq", 4, take_out=TakeOut(frame=2))  # out from frame 2 on
    ids = bop.load_frame(data, 0, 0).object_ids
    out_id = next(o for o in ids if o not in bop.load_frame(data, 0, 2).object_ids)
    run = _label(data, [0, 1, 2, 3], object_ids=ids)
    k = ids.index(out_id)
    assert run.flagged == [2, 3] and [run.checks[i][k].flagged for i in (2, 3)] == [True, True]
    assert gone_from(run) == {out_id: 2}
    run.labels.ends_at(k, 1)
    checker = _checker(data, run)
    try:
        checks, _ = carry_and_check(run.labels, run.tracked, checker)
    finally:
        checker.close()
    assert not any(c.flagged for i in run.labels.frames for c in checks[i])
    assert run.labels.camera_poses(2)[k] is None
