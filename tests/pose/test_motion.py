"""Procedural motions (shapes, floor contact, determinism), numpy kinematics vs smplx, AMASS loading."""

import numpy as np
import pytest

from pose_eval import body
from pose_eval.motion import (FOOT_JOINTS, MOTIONS, Y_UP_FROM_Z_UP, forward_kinematics, load_amass,
                              make_motion, standin_skeleton)
from stereo_bench.core.poses import rodrigues_to_matrix

FRAMES = 90


@pytest.fixture(scope="module")
def model():
    return body.load_body_model()


@pytest.mark.parametrize("name", sorted(MOTIONS))
def test_motion_shapes_floor_and_determinism(name, model):
    motion = make_motion(name, FRAMES, fps=30)
    assert motion.poses.shape == (FRAMES, 24, 3) and motion.transl.shape == (FRAMES, 3)
    assert motion.body_pose.shape == (FRAMES, 69) and motion.fps == 30.0
    assert np.isfinite(motion.poses).all() and np.isfinite(motion.transl).all()
    joints, vertices = body.forward(model, motion.body_pose, motion.global_orient, motion.transl)
    skeleton = standin_skeleton()
    rest_height = skeleton.joints[FOOT_JOINTS, 1] - skeleton.floor_y
    clearance = (joints[:, FOOT_JOINTS, 1] - rest_height).min(axis=1)
    assert clearance.min() > -1e-6  # no foot joint below its standing height
    assert vertices[..., 1].min() > -1e-3  # nor the soles below the floor
    grounded = clearance < 1e-6
    assert grounded.mean() > 0.25 and (name == "jumping_jacks" or grounded.all())
    np.testing.assert_array_equal(make_motion(name, FRAMES).poses, motion.poses)
    varied = make_motion(name, FRAMES, seed=3)
    np.testing.assert_array_equal(make_motion(name, FRAMES, seed=3).transl, varied.transl)
    assert not np.allclose(varied.poses, motion.poses)


def test_numpy_kinematics_matches_smplx(model):
    rng = np.random.default_rng(1)
    poses, transl = rng.normal(scale=0.5, size=(20, 24, 3)), rng.normal(size=(20, 3))
    joints, _ = body.forward(model, poses[:, 1:], poses[:, 0], transl)
    np.testing.assert_allclose(forward_kinematics(poses, standin_skeleton(), transl), joints, atol=1e-6)


def test_motions_follow_the_skeleton_they_are_made_for(model):
    tall = body.rest_skeleton(model, betas=[1.5])
    motion = make_motion("squat", FRAMES, skeleton=tall)
    joints, vertices = body.forward(model, motion.body_pose, motion.global_orient, motion.transl, betas=[1.5])
    assert abs(vertices[..., 1].min()) < 1e-3
    np.testing.assert_allclose(joints, forward_kinematics(motion.poses, tall, motion.transl), atol=1e-6)


def test_walk_circle_follows_its_circle():
    motion = make_motion("walk_circle", 300)
    pelvis = forward_kinematics(motion.poses, standin_skeleton(), motion.transl)[:, 0]
    np.testing.assert_allclose(np.hypot(pelvis[:, 0], pelvis[:, 2]), 1.5, atol=1e-9)
    step = np.linalg.norm(np.diff(pelvis[:, [0, 2]], axis=0), axis=1) * 30
    np.testing.assert_allclose(step, 1.1, rtol=1e-3)  # walking speed, m/s
    facing = rodrigues_to_matrix(motion.global_orient)[:-1, :, 2][:, [0, 2]]  # body +z, horizontal
    travel = np.diff(pelvis[:, [0, 2]], axis=0) / (step[:, None] / 30)
    assert np.all(np.einsum("ij,ij->i", facing, travel) > np.cos(np.deg2rad(8)))  # faces where it goes


def test_make_motion_errors():
    with pytest.raises(ValueError, match="walk_circle, arm_raise, squat, jumping_jacks, turn_in_place"):
        make_motion("moonwalk", 10)
    with pytest.raises(ValueError, match="frames"):
        make_motion("squat", 0)


def _write_amass(path, width, frames=6, **drop):
    rng = np.random.default_rng(2)
    arrays = {"poses": rng.normal(scale=0.4, size=(frames, width)), "trans": rng.normal(size=(frames, 3)),
              "betas": rng.normal(size=16), "mocap_framerate": np.array(120.0), "gender": np.array("female")}
    np.savez(path, **{k: v for k, v in arrays.items() if k not in drop})
    return arrays


def test_load_amass_layouts(tmp_path):
    smplh = _write_amass(tmp_path / "smplh.npz", 156)
    motion = load_amass(tmp_path / "smplh.npz", z_up=False)
    assert motion.name == "smplh" and motion.fps == 120.0 and motion.poses.shape == (6, 24, 3)
    np.testing.assert_array_equal(motion.poses.reshape(6, 72)[:, :66], smplh["poses"][:, :66])
    assert not motion.poses[:, 22:].any()  # SMPL-H's 66..72 are finger joints, not SMPL's hands
    np.testing.assert_array_equal(motion.transl, smplh["trans"])
    np.testing.assert_array_equal(motion.betas, smplh["betas"])
    smpl = _write_amass(tmp_path / "smpl.npz", 72)
    np.testing.assert_array_equal(load_amass(tmp_path / "smpl.npz", z_up=False).poses.reshape(6, 72), smpl["poses"])


def test_load_amass_turns_z_up_into_y_up(tmp_path):
    _write_amass(tmp_path / "walk.npz", 156)
    raw, converted = load_amass(tmp_path / "walk.npz", z_up=False), load_amass(tmp_path / "walk.npz")
    skeleton = standin_skeleton()
    before = forward_kinematics(raw.poses, skeleton, raw.transl)
    after = forward_kinematics(converted.poses, skeleton, converted.transl)
    np.testing.assert_allclose(after, before @ Y_UP_FROM_Z_UP.T, atol=1e-9)  # the same motion, rotated
    np.testing.assert_array_equal(converted.poses[:, 1:], raw.poses[:, 1:])


def test_load_amass_errors(tmp_path):
    _write_amass(tmp_path / "no_trans.npz", 156, trans=None)
    with pytest.raises(KeyError, match=r"no_trans.npz: missing key\(s\) \['trans'\]"):
        load_amass(tmp_path / "no_trans.npz")
    _write_amass(tmp_path / "no_rate.npz", 156, mocap_framerate=None)
    with pytest.raises(KeyError, match="mocap_framerate"):
        load_amass(tmp_path / "no_rate.npz")
    _write_amass(tmp_path / "narrow.npz", 63)
    with pytest.raises(ValueError, match=r"narrow.npz: 'poses' has shape \(6, 63\)"):
        load_amass(tmp_path / "narrow.npz")
    with pytest.raises(FileNotFoundError, match="absent.npz"):
        load_amass(tmp_path / "absent.npz")
