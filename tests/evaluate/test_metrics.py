"""Metrics against cases whose answer is known exactly."""

import numpy as np
import pytest

from stereo_bench.core.camera import Camera, project_points
from stereo_bench.evaluate.metrics import (PAPER_PARAMS, parameter_errors, parameter_rmse,
                                           pose_errors, projection_difference, rpe_rms)

RECT = Camera("rect", 4096, 3072, 3000, 3000, 2048, 1536, 0, [0.05, 0.02, 0.001])
WIDE = Camera("wide", 640, 480, 600, 450, 320, 240, 0, [0.5, 0.1, 0.03])


@pytest.mark.parametrize("camera", [RECT, WIDE], ids=["rect", "wide"])
def test_a_camera_against_itself_differs_by_nothing(camera):
    d = projection_difference(camera, camera)
    assert d["max_px"] < 1e-9 and d["rotation_compensated_max_px"] < 1e-9
    assert d["rotation_deg"] < 1e-9


def test_principal_point_shift_moves_every_pixel_by_the_shift():
    # u = fx xd + skew yd + cx: the same ray lands exactly (dcx, dcy) away, whatever the distortion.
    d = projection_difference(WIDE.with_params(cx=WIDE.cx + 3.0, cy=WIDE.cy - 4.0), WIDE)
    assert d["mean_px"] == pytest.approx(5.0, abs=1e-9)
    assert d["max_px"] == pytest.approx(5.0, abs=1e-9)
    # A rotation explains most of a shift (not all: the image is not a sphere).
    assert d["rotation_compensated_mean_px"] < 0.5 * d["mean_px"]


def test_rotation_compensation_removes_a_pure_rotation():
    rvec = np.array([0.01, -0.02, 0.03])
    d = projection_difference(WIDE, WIDE, rotation=rvec)
    assert d["mean_px"] > 5.0
    assert d["rotation_compensated_max_px"] < 1e-8
    assert d["rotation_deg"] == pytest.approx(np.degrees(np.linalg.norm(rvec)), rel=1e-9)


def test_rpe_rms_is_the_root_mean_squared_residual_norm():
    board = np.stack(np.meshgrid(np.arange(11) * 15.0, np.arange(8) * 15.0), -1).reshape(-1, 2)
    board = np.column_stack([board, np.zeros(len(board))])
    rvecs, tvecs = np.array([[0.1, -0.2, 0.05]] * 2), np.array([[-70, -50, 400], [-60, -40, 500.0]])
    image = [project_points(board, RECT.intrinsics, RECT.dist, r, t) for r, t in zip(rvecs, tvecs)]
    assert rpe_rms(RECT, rvecs, tvecs, [board] * 2, image) < 1e-12
    shifted = [image[0] + [0.3, 0.4], image[1] - [0.6, 0.8]]  # |residual| 0.5 and 1.0
    assert rpe_rms(RECT, rvecs, tvecs, [board] * 2, shifted) == pytest.approx(np.sqrt(0.625))


def test_parameter_errors_and_the_papers_rmse():
    est = RECT.with_params(fx=RECT.fx + 3.0, dist=RECT.dist + np.r_[0.01, 0, 0, 0, 0, 0, 0, 0.02])
    err = parameter_errors(est, RECT)
    assert err["fx"] == pytest.approx(3.0) and err["k1"] == pytest.approx(0.01)
    assert err["k6"] == pytest.approx(0.02) and err["cy"] == 0.0 and err["skew"] == 0.0
    assert len(PAPER_PARAMS) == 12
    assert parameter_rmse(est, RECT) == pytest.approx(np.sqrt((9 + 1e-4 + 4e-4) / 12))


def test_pose_errors_measure_angle_and_distance():
    true_r, true_t = np.array([[0.2, 0.1, -0.3], [0.0, 0.0, 0.0]]), np.array([[1, 2, 500.0]] * 2)
    # A rotation by 1e-7 rad about z composed on the second pose; the first translated by (3, 4, 0).
    est_r = np.array([[0.2, 0.1, -0.3], [0.0, 0.0, 1e-7]])
    est_t = true_t + [[3, 4, 0], [0, 0, 0]]
    e = pose_errors(est_r, est_t, true_r, true_t)
    assert e["rotation_deg"][0] < 1e-12
    assert e["rotation_deg"][1] == pytest.approx(np.degrees(1e-7), rel=1e-6)
    assert e["translation_mm"] == pytest.approx([5.0, 0.0])
    assert e["translation_mm_max"] == pytest.approx(5.0)
