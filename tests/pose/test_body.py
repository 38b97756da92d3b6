"""The open stand-in body through smplx: rest pose, skinning, kinematics, shape, loading errors."""

import pickle
import runpy
from pathlib import Path

import numpy as np
import pytest
import smplx
import torch
import trimesh

from pose_eval import body
from pose_eval.motion import JOINT, PARENTS, STANDIN_MODEL_PATH
from stereo_bench.core.poses import rodrigues_to_matrix

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def model():
    return body.load_body_model()


@pytest.fixture(scope="module")
def data():
    with np.load(STANDIN_MODEL_PATH) as d:
        return dict(d)


def test_standin_is_an_smplx_smpl(model, data):
    assert isinstance(model, smplx.SMPL)
    assert model.num_betas == 3 and model.v_template.dtype == torch.float64
    assert model.parents.tolist() == list(PARENTS)
    out = model(betas=torch.zeros(1, 3, dtype=torch.float64))
    assert out.joints.shape == (1, 45, 3)  # 24 joints + smplx's 21 vertex keypoints, as for SMPL
    assert STANDIN_MODEL_PATH.stat().st_size < 3e6


def test_zero_pose_reproduces_template_and_rest_joints(model, data):
    joints, vertices = body.forward(model, np.zeros((2, 69)), np.zeros((2, 3)))
    np.testing.assert_allclose(vertices, np.broadcast_to(data["v_template"], vertices.shape), atol=1e-6)
    np.testing.assert_allclose(joints, np.broadcast_to(data["J"], joints.shape), atol=1e-6)
    np.testing.assert_allclose(data["J_regressor"].astype(float) @ data["v_template"], data["J"], atol=1e-6)


def test_weights_and_regressor_are_normalized(data):
    w = data["weights"]
    np.testing.assert_allclose(w.sum(axis=1), 1, atol=1e-6)
    assert (w >= 0).all() and (np.count_nonzero(w, axis=1) <= 4).all()
    np.testing.assert_allclose(data["J_regressor"].sum(axis=1), 1, atol=1e-6)


def test_mesh_is_closed_outward_capsules(data):
    mesh = trimesh.Trimesh(data["v_template"], data["f"], process=False)
    parts = mesh.split(only_watertight=False)
    assert len(parts) == 24 and all(p.is_watertight and p.volume > 0 for p in parts)
    height = np.ptp(data["v_template"][:, 1])
    assert 1.6 < height < 1.8


def test_asset_is_what_the_build_script_makes(data):
    rebuilt = runpy.run_path(str(ROOT / "scripts" / "build_body_model.py"))["build"]()
    assert rebuilt.keys() == data.keys()
    for key in rebuilt:  # floats to rounding: numpy's sin/cos may differ in the last bit across CPUs
        if rebuilt[key].dtype.kind == "f":
            np.testing.assert_allclose(rebuilt[key], data[key], rtol=1e-6, atol=1e-7, err_msg=key)
        else:
            np.testing.assert_array_equal(rebuilt[key], data[key], err_msg=key)


def test_elbow_rotation_moves_the_wrist_by_the_forearm(model, data):
    J = data["J"]
    pose = np.zeros((1, 24, 3))
    pose[0, JOINT["left_elbow"]] = [0, -np.pi / 2, 0]  # flexes the left forearm (+x) forward (+z)
    joints, _ = body.forward(model, pose[:, 1:], pose[:, 0])
    elbow, wrist = JOINT["left_elbow"], JOINT["left_wrist"]
    forearm = J[wrist] - J[elbow]
    expected = J[elbow] + rodrigues_to_matrix(pose[0, elbow]) @ forearm
    np.testing.assert_allclose(joints[0, wrist], expected, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(joints[0, wrist] - joints[0, elbow]), np.linalg.norm(forearm), atol=1e-6)
    # the forearm is perpendicular to the axis, so the wrist travels a chord of sqrt(2) forearms
    np.testing.assert_allclose(np.linalg.norm(joints[0, wrist] - J[wrist]), np.sqrt(2) * np.linalg.norm(forearm), atol=1e-6)
    np.testing.assert_allclose(joints[0, :elbow + 1], J[:elbow + 1], atol=1e-6)  # joints before it stay


def test_shape_directions(model, data):
    heights = []
    for b in np.linspace(-2, 2, 5):
        _, v = body.forward(model, np.zeros((1, 69)), np.zeros(3), betas=[b])
        heights.append(np.ptp(v[0, :, 1]))
    assert np.all(np.diff(heights) > 0.05)
    np.testing.assert_allclose(body.rest_skeleton(model, [1.0]).joints, 1.06 * data["J"], atol=1e-6)  # stature: +6 %
    girth = body.rest_skeleton(model, [0, 2.0])
    np.testing.assert_allclose(girth.joints, data["J"], atol=1e-6)  # girth keeps the skeleton
    _, v = body.forward(model, np.zeros((1, 69)), np.zeros(3), betas=[0, 2.0])
    assert np.abs(v[0] - data["v_template"]).max() > 0.01


def test_forward_accepts_both_pose_layouts_and_pads_betas(model):
    rng = np.random.default_rng(0)
    pose = rng.normal(scale=0.3, size=(3, 23, 3))
    orient, transl = rng.normal(size=(3, 3)), rng.normal(size=(3, 3))
    j1, v1 = body.forward(model, pose, orient, transl, betas=[0.5])
    j2, v2 = body.forward(model, pose.reshape(3, 69), orient, transl, betas=np.tile([0.5, 0, 0], (3, 1)))
    np.testing.assert_array_equal(j1, j2)
    np.testing.assert_array_equal(v1, v2)
    np.testing.assert_allclose(body.to_mm(j1), 1000 * j1)
    with pytest.raises(ValueError, match="betas has 4 coefficients"):
        body.forward(model, pose, orient, betas=np.zeros(4))
    with pytest.raises(ValueError, match="body_pose has shape"):
        body.forward(model, np.zeros((3, 72)), orient)
    with pytest.raises(ValueError, match="transl has shape"):
        body.forward(model, pose, orient, np.zeros((2, 3)))


def test_user_model_file_and_folder(tmp_path, model, data):
    folder = tmp_path / "models"
    folder.mkdir()
    with open(folder / "SMPL_NEUTRAL.pkl", "wb") as f:
        pickle.dump(data, f)
    user = body.load_body_model(folder)
    pose = np.full((1, 69), 0.1)
    np.testing.assert_allclose(body.forward(user, pose, np.zeros(3))[1], body.forward(model, pose, np.zeros(3))[1])
    with pytest.raises(FileNotFoundError, match="SMPL_MALE.pkl"):
        body.load_body_model(folder, gender="male")


def test_bad_model_paths(tmp_path, data):
    with pytest.raises(FileNotFoundError, match="nowhere.pkl"):
        body.load_body_model(tmp_path / "nowhere.pkl")
    partial = tmp_path / "partial.npz"
    np.savez(partial, **{k: v for k, v in data.items() if k != "weights"})
    with pytest.raises(ValueError, match=r"partial.npz lacks \['weights'\]"):
        body.load_body_model(partial)
    text = tmp_path / "model.obj"
    text.write_text("v 0 0 0\n")
    with pytest.raises(ValueError, match=r"model.obj: expected .*\.pkl or \.npz"):
        body.load_body_model(text)
    with pytest.raises(ValueError, match="gender-neutral"):
        body.load_body_model(gender="female")
    with pytest.raises(ValueError, match="has 3 shape directions"):
        body.load_body_model(num_betas=10)
