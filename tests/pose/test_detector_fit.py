"""The fitted detector model: fitted from keypoints it drew itself, it gives back what drew them;
its JSON round-trips; a bad file is refused by name; the shipped BlazePose fit loads."""

import json

import numpy as np
import pytest

from stereo_bench.config.schema import load_rig
from pose_eval.body import NUM_JOINTS
from pose_eval.detector_fit import (DetectorFit, body_frames, fit_detector, load_fit,
                                    observe_fitted)
from pose_eval.motion import JOINT
from pose_eval.scene import make_scene

from tests.quickstart import ROOT


@pytest.fixture(scope="module")
def studio():
    cams = load_rig(ROOT / "configs/studios/h36m_rectangle.yaml").cameras_true()
    return cams, [make_scene(cams, m, 40) for m in ("walk_circle", "squat")]


def _model(seed=1) -> DetectorFit:
    rng = np.random.default_rng(seed)
    offset = rng.normal(scale=30, size=(NUM_JOINTS, 3))
    offset[[JOINT["spine1"], JOINT["spine2"]]] = np.nan  # joints it never reports
    full = np.full((NUM_JOINTS, 2), np.nan)

    def per(seen, hidden):
        return np.where(np.isnan(offset[:, :1]), full, [seen, hidden])
    return DetectorFit("drawn", offset, per(8.0, 20.0), per(0.02, 0.02), per(150.0, 150.0),
                       per(0.05, 0.05), per(0.9, 0.5))


def test_body_frames_are_rotations_that_turn_with_the_body(studio):
    _, scenes = studio
    R = body_frames(scenes[0].joints)
    assert np.allclose(R @ R.transpose(0, 2, 1), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(R), 1.0)
    # Turning the whole body turns its frame by the same rotation.
    turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    assert np.allclose(body_frames(scenes[0].joints @ turn.T), turn @ R, atol=1e-12)


def test_fit_recovers_the_model_that_drew_the_keypoints(studio):
    cams, scenes = studio
    truth = _model()
    keypoints = [observe_fitted(cams, s, truth, np.random.default_rng(i))
                 for i, s in enumerate(scenes)]
    fit = fit_detector("fitted", cams, scenes, keypoints)
    assert (fit.reported == truth.reported).all()
    ok = truth.reported
    # 2 x 40 frames x 4 cameras: the offset's standard error is about 8 mm / sqrt(300) ~ 0.5 mm
    # per joint, and the scatter was drawn with 2 % gross errors.
    assert np.abs(fit.offset_mm - truth.offset_mm)[ok].max() < 3.0
    # Seen views: the robust sigma within 6 % on average (hidden views are fewer: 15 %).
    assert abs(np.mean(fit.sigma_mm[ok, 0]) / 8.0 - 1) < 0.06
    assert abs(np.mean(fit.sigma_mm[ok, 1]) / 20.0 - 1) < 0.15
    assert abs(np.mean(fit.miss_rate[ok, 0]) - 0.05) < 0.015
    assert abs(np.mean(fit.gross_rate[ok, 0]) - 0.02) < 0.01
    assert np.allclose(fit.confidence[ok, 0], 0.9)
    # A joint hidden in fewer than MIN_VIEWS views borrows its seen figures (the wrist, here).
    assert np.median(fit.confidence[ok, 1]) == pytest.approx(0.5)


def test_json_round_trip_and_refusals(tmp_path):
    model = _model()
    path = tmp_path / "model.json"
    path.write_text(json.dumps(model.to_dict()))
    back = load_fit(path)
    assert np.nanmax(np.abs(back.offset_mm - model.offset_mm)) < 1e-6
    assert (back.reported == model.reported).all()
    bad = model.to_dict()
    bad["joints"]["pelvis"]["miss_rate"] = [0.1, 1.5]
    path.write_text(json.dumps(bad))
    with pytest.raises(ValueError, match=r"model.json: miss_rate: expected shares"):
        load_fit(path)
    bad = model.to_dict()
    bad["joints"]["tail"] = bad["joints"].pop("pelvis")
    path.write_text(json.dumps(bad))
    with pytest.raises(ValueError, match=r"joints.tail: not one of SMPL's joints"):
        load_fit(path)
    for bad in ({"joints": 3}, [1, 2], {"joints": {"pelvis": 1}}):
        path.write_text(json.dumps(bad))
        with pytest.raises(ValueError, match=r"model.json: (expected a mapping|joints.pelvis)"):
            load_fit(path)
    with pytest.raises(FileNotFoundError, match="no detector model here"):
        load_fit(tmp_path / "none.json")


def test_the_shipped_blazepose_fit_loads_and_reports_blazepose_joints():
    fit = load_fit()
    assert fit.name == "blazepose"
    # BlazePose has no spine or collar landmarks: those joints are never reported.
    for name in ("spine1", "spine2", "spine3", "left_collar", "right_collar"):
        assert not fit.reported[JOINT[name]]
    assert fit.reported.sum() == 19
    # Its midpoint joints sit below SMPL's: the pelvis and neck offsets are tens of mm.
    assert np.linalg.norm(fit.offset_mm[JOINT["pelvis"]]) > 20
