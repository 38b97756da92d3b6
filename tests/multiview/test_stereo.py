"""Rig calibration against ground truth and against cv2.stereoCalibrate on the same observations.

The synthetic rig: cameras 150 mm apart, toed in to converge 600 mm ahead, watching a board of
8x11 inner corners at 15 mm that moves and tilts in front of them (40 frames).
"""

import cv2
import numpy as np
import pytest

from stereo_bench.core.camera import Camera
from stereo_bench.core.poses import look_at_rotation, matrix_to_rodrigues, rodrigues_to_matrix
from stereo_bench.multiview.bundle import average_rotations, calibrate_rig, initial_rig, rig_errors
from stereo_bench.core.poses import cam_from_cam0

RECT = Camera("rect", 4096, 3072, 3000, 3000, 2048, 1536, 0, [0.05, 0.02, 0.001, 0, 0, 0, 0, 0])
WIDE = Camera("wide", 640, 480, 600, 450, 320, 240, 0, [0.5, 0.1, 0.03, 0, 0, 0, 0, 0])
# Non-zero k4..k6: what cv2.stereoCalibrate drops without CALIB_RATIONAL_MODEL (TRAPS.md).
RATIONAL = Camera("rational", 4096, 3072, 3000, 3000, 2048, 1536, 0,
                  [0.05, 0.02, 0.001, -0.0005, 0.01, 0.02, 0.005, 0.001])
FRAMES = 40


def placed(cam, position, name):
    R = look_at_rotation(np.array(position, float), np.array([0.0, 0, 600]), np.array([0, -1.0, 0]))
    return cam.with_params(name=name, rvec=matrix_to_rodrigues(R),
                           tvec=-R @ np.array(position, float))


def pair(left, right):
    return [placed(left, (-75, 0, 0), "left"), placed(right, (75, 0, 0), "right")]


def board():
    gx, gy = np.meshgrid(np.arange(11) * 15.0, np.arange(8) * 15.0)
    return np.stack([gx.ravel(), gy.ravel(), np.zeros(88)], -1)


def observe(cameras, noise_px, seed=0, frames=FRAMES):
    """Image points (C,F,N,2) and perturbed per-camera cam_from_board poses (C,F,3) x 2."""
    rng = np.random.default_rng(seed)
    obj = board()
    R_wb = rodrigues_to_matrix(rng.uniform(-1, 1, (frames, 3)) * [0.5, 0.5, 0.3])
    centre = np.stack([rng.uniform(-60, 60, frames), rng.uniform(-50, 50, frames),
                       rng.uniform(450, 800, frames)], -1)
    t_wb = centre - R_wb @ obj.mean(0)
    Xw = np.einsum("fij,nj->fni", R_wb, obj) + t_wb[:, None]
    img = np.stack([cam.project(Xw) for cam in cameras])
    for c, cam in enumerate(cameras):  # the data must be valid observations
        assert np.all((img[c] >= 0) & (img[c] <= [cam.width - 1, cam.height - 1]))
    img = img + rng.normal(0, noise_px, img.shape)
    # Each camera's own (imperfect) cam_from_board: truth perturbed by ~0.5 deg and ~2 mm.
    R_cb = np.stack([cam.R @ R_wb for cam in cameras])
    t_cb = np.stack([t_wb @ cam.R.T + cam.tvec for cam in cameras])
    turn = rodrigues_to_matrix(rng.normal(0, 0.005, R_cb.shape[:2] + (3,)))
    rv = matrix_to_rodrigues(turn @ R_cb)
    return obj, img, rv, t_cb + rng.normal(0, 2.0, t_cb.shape)


def relative_errors(estimated, reference):
    """Relative errors of each camera's cam_from_cam0 rvec and tvec (cameras 1..)."""
    Re, te = cam_from_cam0(estimated)
    Rr, tr = cam_from_cam0(reference)
    re, rr = matrix_to_rodrigues(Re[1:]), matrix_to_rodrigues(Rr[1:])
    return (np.linalg.norm(re - rr, axis=1) / np.linalg.norm(rr, axis=1),
            np.linalg.norm(te[1:] - tr[1:], axis=1) / np.linalg.norm(tr[1:], axis=1))


RIGS = {"identical": pair(RECT, RECT), "identical-rational": pair(RATIONAL, RATIONAL),
        "mixed": pair(RECT, WIDE),
        "three": pair(RECT, WIDE) + [placed(RECT, (0, -100, 0), "top")]}


@pytest.mark.parametrize("rig", list(RIGS))
def test_noise_free_observations_give_the_true_rig(rig):
    cams = RIGS[rig]
    obj, img, rv, tv = observe(cams, 0.0)
    res = calibrate_rig(cams, obj, img, rv, tv)
    dr, dt = relative_errors(res.cameras, cams)
    # Relative errors of the rvec and tvec of cam_from_cam0 (measured ~1e-14).
    assert dr.max() < 1e-6 and dt.max() < 1e-6
    err = rig_errors(res.cameras, cams)
    assert err["rotation_deg"].max() < 1e-6 and err["translation_mm"].max() < 1e-6
    assert res.rms_px < 1e-6
    assert res.frames_used.all() and np.isfinite(res.board_rvecs).all()
    assert res.log["initial_rms_px"] > 1.0  # the start was genuinely off


@pytest.mark.parametrize("rig", ["identical", "identical-rational", "mixed"])
def test_agrees_with_opencv_stereo_calibrate(rig):
    cams = RIGS[rig]
    obj, img, rv, tv = observe(cams, 0.3, seed=1)
    res = calibrate_rig(cams, obj, img, rv, tv)
    f32 = lambda a: [x.astype(np.float32) for x in a]  # noqa: E731
    # CALIB_RATIONAL_MODEL, or OpenCV silently drops k4..k6 of the fixed intrinsics.
    flags = cv2.CALIB_FIX_INTRINSIC | cv2.CALIB_RATIONAL_MODEL
    rms, *_, R, T, _, _ = cv2.stereoCalibrate(
        f32([obj] * FRAMES), f32(img[0]), f32(img[1]), cams[0].K, cams[0].dist, cams[1].K,
        cams[1].dist, (cams[0].width, cams[0].height), flags=flags,
        criteria=(cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-15))
    ref = [cams[0].with_params(rvec=np.zeros(3), tvec=np.zeros(3)),
           cams[1].with_params(rvec=cv2.Rodrigues(R)[0], tvec=T)]
    dr, dt = relative_errors(res.cameras, ref)
    assert dr.max() < 1e-4 and dt.max() < 1e-4  # relative; measured ~1e-8 (float32 inputs)
    assert res.rms_px == pytest.approx(rms, rel=1e-5)
    # ... and both are near the truth, not at some shared wrong answer.
    err = rig_errors(res.cameras, cams)
    assert err["rotation_deg"][1] < 0.02 and err["translation_mm"][1] < 0.5


def test_noisy_three_camera_rig_is_near_truth_and_per_camera_rms_is_the_noise():
    cams = RIGS["three"]
    obj, img, rv, tv = observe(cams, 0.3, seed=2)
    res = calibrate_rig(cams, obj, img, rv, tv)
    err = rig_errors(res.cameras, cams)
    assert err["rotation_deg"].max() < 0.02 and err["translation_mm"].max() < 0.5
    assert np.abs(err["baseline_mm"]).max() < 0.5
    # 0.3 px per coordinate -> 0.42 px per point; the fit absorbs a few degrees of freedom.
    assert np.allclose(res.rms_px_per_camera, 0.3 * np.sqrt(2), rtol=0.05)
    assert res.iterations < 20


def test_camera_without_a_frame_shared_with_camera_0_is_chained_through_another():
    cams = RIGS["three"]
    obj, img, rv, tv = observe(cams, 0.0)
    found = np.ones((3, FRAMES), bool)
    found[0, FRAMES // 2:] = False  # camera 0 sees the first half, "top" only the second
    found[2, :FRAMES // 2] = False
    res = calibrate_rig(cams, obj, img, rv, tv, found=found)
    half = FRAMES // 2
    assert res.log["initialization"][2] == {"camera": "top", "parent": "right",
                                            "shared_frames": half, "kept_frames": half}
    assert rig_errors(res.cameras, cams)["translation_mm"].max() < 1e-6
    assert res.frames_used.all()  # every frame is seen by two cameras


def test_unconnected_camera_is_a_clear_error():
    cams = RIGS["three"]
    obj, img, rv, tv = observe(cams, 0.0)
    found = np.ones((3, FRAMES), bool)
    found[:2, :10] = False
    found[2, 10:] = False
    with pytest.raises(ValueError, match="'top'.*share no frame"):
        calibrate_rig(cams, obj, img, rv, tv, found=found)


def test_planted_bad_pose_is_discarded_by_the_rotation_average():
    cams = RIGS["mixed"]
    obj, img, rv, tv = observe(cams, 0.0)
    rv[1, 7] = matrix_to_rodrigues(rodrigues_to_matrix([0.0, 0.5, 0.0])
                                   @ rodrigues_to_matrix(rv[1, 7]))  # 29 deg off
    seen = np.ones((2, FRAMES), bool)
    R, t, log = initial_rig(rodrigues_to_matrix(rv), tv, seen, ["left", "right"])
    assert log[1]["kept_frames"] == FRAMES - 1
    Rt, tt = cam_from_cam0(cams)
    # Averaging 39 frames perturbed by 0.5 deg and 2 mm each: well below the per-frame error.
    angle = np.degrees(np.linalg.norm(matrix_to_rodrigues(R[1] @ Rt[1].T)))
    assert angle < 0.25 and np.linalg.norm(t[1] - tt[1]) < 2.0
    assert rig_errors(calibrate_rig(cams, obj, img, rv, tv).cameras, cams)[
        "translation_mm"].max() < 1e-6


def test_average_rotations_is_the_chordal_mean_of_inliers():
    rng = np.random.default_rng(3)
    base = rodrigues_to_matrix([0.3, -0.2, 0.1])
    noise = rng.normal(0, 0.002, (30, 3))
    noise -= noise.mean(0)  # zero-mean scatter: the chordal mean is base to second order
    outliers = rodrigues_to_matrix([[2.0, 0, 0], [0, 0, 1.0]]) @ base
    Rs = np.concatenate([rodrigues_to_matrix(noise) @ base, outliers])
    R, inliers = average_rotations(Rs)
    assert inliers[:30].all() and not inliers[30:].any()
    assert np.linalg.norm(matrix_to_rodrigues(R @ base.T)) < 1e-5  # sigma^2 = 4e-6
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-14) and np.linalg.det(R) > 0


def test_rig_errors_are_frame_independent_and_measure_a_known_offset():
    cams = RIGS["three"]
    # Moving the world frame moves every cam_from_world but no relative pose.
    Rw, tw = rodrigues_to_matrix([0.4, -1.0, 0.2]), np.array([100.0, -20, 3000])
    moved = [c.with_params(rvec=matrix_to_rodrigues(c.R @ Rw), tvec=c.R @ tw + c.tvec)
             for c in cams]
    err = rig_errors(moved, cams)
    assert max(np.abs(v).max() for v in err.values()) < 1e-9
    # Camera 1's centre 2 mm farther from camera 0 along the baseline, and turned 0.1 deg.
    R1 = rodrigues_to_matrix([0.0, np.radians(0.1), 0.0]) @ cams[1].R
    centre = cams[1].center + 2.0 * (cams[1].center - cams[0].center) / 150.0
    off = [cams[0], cams[1].with_params(rvec=matrix_to_rodrigues(R1), tvec=-R1 @ centre), cams[2]]
    err = rig_errors(off, cams)
    assert err["baseline_mm"][1] == pytest.approx(2.0, abs=1e-9)
    assert err["rotation_deg"][1] == pytest.approx(0.1, abs=1e-9)
    assert err["translation_mm"][2] == 0 and err["rotation_deg"][2] < 1e-12


def test_bad_input_is_named():
    cams = RIGS["identical"]
    obj, img, rv, tv = observe(cams, 0.0, frames=5)
    with pytest.raises(ValueError, match="image_points"):
        calibrate_rig(cams, obj, img[:, :, :10], rv, tv)
    with pytest.raises(ValueError, match="board_tvecs"):
        calibrate_rig(cams, obj, img, rv, tv[:, :4])
    with pytest.raises(ValueError, match="at least 2 cameras"):
        calibrate_rig(cams[:1], obj, img[:1], rv[:1], tv[:1])
