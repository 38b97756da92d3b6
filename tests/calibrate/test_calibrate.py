"""Calibration methods against exact synthetic ground truth, OpenCV and the Cramer-Rao bound.

Observations are exact projections (through camera.py) of an 8 x 11 inner-corner board with 15 mm
spacing, seen from varied tilts, plus Gaussian noise where a test says so. Exactness tests use
cameras inside each method's model (Zhang: k1, k2; Bouguet: k1, k2, p1, p2).
"""

import cv2
import numpy as np
import pytest
from scipy.stats import chi2

from stereo_bench.calibrate import Observations, available_methods, get_calibrator
from stereo_bench.calibrate.refine import (CameraModel, _Problem, free_mask, intrinsic_information,
                                           refine)
from stereo_bench.core.camera import Camera
from stereo_bench.core.poses import matrix_to_rodrigues, rodrigues_to_matrix
from stereo_bench.evaluate.metrics import pose_errors

RECT = Camera("rect", 4096, 3072, 3000, 3000, 2048, 1536, 0, [0.05, 0.02, 0.001])
WIDE = Camera("wide", 640, 480, 600, 450, 320, 240, 0, [0.5, 0.1, 0.03])
RECT_K1K2 = RECT.with_params(dist=np.array([0.05, 0.02]))
WIDE_K1K2 = WIDE.with_params(dist=np.array([0.5, 0.1]))
MODEL = CameraModel()


def board_points(cols=11, rows=8, spacing=15.0):
    x, y = np.meshgrid(np.arange(cols) * spacing, np.arange(rows) * spacing)
    return np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], -1)


def synthetic_views(camera, n_views, rng, max_tilt_deg=40.0):
    """cam_from_board poses (rvecs, tvecs) of boards facing the camera, fully inside the image.

    Each board is tilted up to ``max_tilt_deg`` about its x and y axes, rolled up to 30 degrees,
    centred on a random pixel of the central 60 % of the image and sized to 35-80 % of its width.
    """
    board = board_points()
    centre = board.mean(0)
    diagonal = np.linalg.norm(np.ptp(board, axis=0))
    rvecs, tvecs = [], []
    while len(rvecs) < n_views:
        tilt = np.radians(rng.uniform(-max_tilt_deg, max_tilt_deg, 2))
        R = rodrigues_to_matrix(np.array([*tilt, rng.uniform(-0.5, 0.5)]))
        ray = np.append(camera.unproject(rng.uniform(0.2, 0.8, 2) * camera.size), 1.0)
        depth = diagonal / (rng.uniform(0.35, 0.8) * camera.width / camera.fx)
        t = ray * depth - R @ centre
        uv = camera.with_params(rvec=matrix_to_rodrigues(R), tvec=t).project(board)
        if np.all((uv > 0) & (uv < np.array(camera.size) - 1)):
            rvecs.append(matrix_to_rodrigues(R))
            tvecs.append(t)
    return board, np.array(rvecs), np.array(tvecs)


def observe(camera, board, rvecs, tvecs, sigma, rng):
    image = [camera.with_params(rvec=r, tvec=t).project(board) for r, t in zip(rvecs, tvecs)]
    image = [p + rng.normal(0.0, sigma, p.shape) for p in image]
    return Observations([board] * len(image), image, camera.size, list(range(len(image))),
                        camera.name)


def views(camera, n_views=30, sigma=0.0, seed=0):
    rng = np.random.default_rng(seed)
    board, rvecs, tvecs = synthetic_views(camera, n_views, rng)
    return observe(camera, board, rvecs, tvecs, sigma, rng), rvecs, tvecs


# --------------------------------------------------------------------------------- plumbing
def test_registry_lists_methods_and_rejects_unknown():
    assert available_methods() == ["zhang", "tsai", "bouguet", "opencv", "opencv-rational"]
    assert get_calibrator("opencv-rational").name == "opencv-rational"
    with pytest.raises(ValueError, match="available.*zhang.*bouguet"):
        get_calibrator("matlab")


def test_observations_reject_bad_input():
    board = board_points()
    with pytest.raises(ValueError, match="view 7.*plane"):
        Observations([board + [0, 0, 1]], [board[:, :2]], (640, 480), [7])
    with pytest.raises(ValueError, match="one of each per view"):
        Observations([board, board], [board[:, :2]], (640, 480), [0, 1])
    with pytest.raises(ValueError, match="view 0.*at least 4"):
        Observations([board[:3]], [board[:3, :2]], (640, 480), [0])


def test_refine_jacobians_match_finite_differences():
    """CameraModel's parameter Jacobian and the pose chain rule through rotate_jacobian."""
    obs, rvecs, tvecs = views(WIDE, n_views=3)
    problem = _Problem(MODEL, np.ones(13, bool), obs.object_points, obs.image_points)
    params = MODEL.params_of(WIDE) + np.r_[0, 0, 0, 0, 0.5, np.full(8, 0.01)]
    _, J_params, J_pose = problem.residuals(params, rvecs, tvecs, jacobians=True)
    h = 1e-6
    for i in range(13):
        d = np.zeros(13)
        d[i] = h * max(1.0, abs(params[i]))
        fd = (problem.residuals(params + d, rvecs, tvecs)
              - problem.residuals(params - d, rvecs, tvecs)) / (2 * d[i])
        assert np.abs(fd - J_params[:, :, i]).max() < 1e-5 * max(1.0, np.abs(fd).max()), i
    view0 = problem.view == 0
    for j in range(6):
        d = np.zeros((3, 6))
        d[0, j] = h
        rv_p, tv_p = rvecs + d[:, :3], tvecs + d[:, 3:]
        rv_m, tv_m = rvecs - d[:, :3], tvecs - d[:, 3:]
        fd = (problem.residuals(params, rv_p, tv_p)
              - problem.residuals(params, rv_m, tv_m)) / (2 * h)
        assert np.abs(fd[view0] - J_pose[view0, :, j]).max() < 1e-5 * np.abs(fd).max(), j
        assert np.all(fd[~view0] == 0)


# ------------------------------------------------------------------------------- exactness
# Measured on these views: zhang and bouguet reach 1e-15 relative (float64 floor); the OpenCV
# references 3e-8 (rect) and 8e-8 (wide) relative on fx..cy and 2e-7 / 6e-6 on k1..p2, the
# float32 rounding of their inputs (TRAPS.md).
EXACTNESS = [
    ("zhang", RECT_K1K2, {}, 1e-6, 1e-6),
    ("zhang", WIDE_K1K2, {}, 1e-6, 1e-6),
    ("zhang", RECT_K1K2, {"zero_skew": True}, 1e-6, 1e-6),
    ("bouguet", RECT, {}, 1e-6, 1e-6),
    ("bouguet", WIDE, {}, 1e-6, 1e-6),
    ("opencv", RECT, {}, 1e-6, 2e-5),
    ("opencv", WIDE, {}, 1e-6, 2e-5),
]


@pytest.mark.parametrize("method, camera, options, rel_tol, dist_tol", EXACTNESS,
                         ids=[f"{m}-{c.name}{'-zero_skew' if o else ''}"
                              for m, c, o, _, _ in EXACTNESS])
def test_noise_free_views_give_the_true_camera(method, camera, options, rel_tol, dist_tol):
    obs, rvecs, tvecs = views(camera)
    result = get_calibrator(method, **options).calibrate(obs)
    est, true = MODEL.params_of(result.camera), MODEL.params_of(camera)
    rel = np.abs(est[:4] - true[:4]) / true[:4]
    print(f"{method} {camera.name}: max relative error fx..cy {rel.max():.1e}, "
          f"max |dist error| {np.abs(est[5:] - true[5:]).max():.1e}")
    assert rel.max() < rel_tol
    assert abs(result.camera.skew) < rel_tol * camera.fx
    assert np.abs(est[5:] - true[5:]).max() < dist_tol
    poses = pose_errors(result.rvecs, result.tvecs, rvecs, tvecs)
    assert poses["rotation_deg_max"] < 1e-4 and poses["translation_mm_max"] < 1e-3


def test_opencv_rational_fits_the_projection_despite_unidentifiable_coefficients():
    obs, _, _ = views(RECT)
    result = get_calibrator("opencv-rational").calibrate(obs)
    rel = np.abs(result.camera.intrinsics[:4] - RECT.intrinsics[:4]) / RECT.intrinsics[:4]
    assert rel.max() < 1e-6
    assert result.log["rms_px"] < 1e-4  # float32 inputs
    assert result.log["opencv_version"] == cv2.__version__
    # OpenCV does not report it; the log does: k1..k6 are (near) unidentifiable from planes.
    rank = result.log["rank"]
    print(rank)
    assert rank["n_free"] == 12 and (rank["rank"] < 12 or rank["condition"] > 1e8)
    assert get_calibrator("opencv").calibrate(obs).log["rank"]["rank"] == 9


def test_refine_reports_rational_rank_deficiency():
    """k1..k6 of the rational model: d/dk4 = -(d/dk1 + k1 d/dk2 + k2 d/dk3) when k4..k6 = 0."""
    obs, rvecs, tvecs = views(RECT, sigma=0.5, seed=1)
    free = free_mask(MODEL.param_names, ["fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3",
                                         "k4", "k5", "k6"])
    res = refine(MODEL, MODEL.params_of(RECT), free, obs.object_points, obs.image_points,
                 rvecs, tvecs)
    info = res.jacobian_rank_info
    print(info)
    assert info["rank"] < info["n_free"] == 12
    assert set(info["unidentifiable"]) >= {"k1", "k4"}
    assert not set(info["unidentifiable"]) & {"fx", "fy", "cx", "cy"}
    std = dict(zip(MODEL.param_names, res.param_std))
    assert np.isinf(std["k4"]) and np.isfinite(std["fx"]) and np.isnan(std["skew"])


# ------------------------------------------------------------------------ noise and optima
@pytest.mark.parametrize("camera", [RECT, WIDE], ids=["rect", "wide"])
def test_bouguet_agrees_with_opencv_on_noisy_views(camera):
    """Same model on both sides: k1, k2, p1, p2 free, k3 = 0 (CALIB_FIX_K3), skew 0 (OpenCV's
    pinhole calibration never estimates it). Measured: 2e-8 (rect) and 7e-8 (wide) relative."""
    obs, _, _ = views(camera, sigma=0.5, seed=1)
    ours = get_calibrator("bouguet").calibrate(obs)
    ref = get_calibrator("opencv", flags=cv2.CALIB_FIX_K3).calibrate(obs)
    rel = np.abs(ours.camera.intrinsics[:4] - ref.camera.intrinsics[:4]) / ref.camera.intrinsics[:4]
    print(f"bouguet vs opencv on {camera.name}: relative {rel}, rms {ours.log['rms_px']:.6f} "
          f"vs {ref.log['rms_px']:.6f}")
    assert rel.max() < 1e-4
    assert np.abs(ours.camera.dist[:4] - ref.camera.dist[:4]).max() < 1e-4


def test_bouguet_recompute_extrinsic_escapes_a_flipped_initial_pose():
    """On these views the single-focal init (~950 px for fx = 600, fy = 450) puts one view's pose
    in the mirrored-tilt basin; without the toolbox's recompute_extrinsic the optimization stays
    in that local minimum."""
    obs, _, _ = views(WIDE, seed=1)
    stuck = get_calibrator("bouguet", recompute_extrinsic=False).calibrate(obs)
    ok = get_calibrator("bouguet").calibrate(obs)
    assert stuck.log["rms_px"] > 0.1
    assert ok.log["views_reinitialized"] and ok.log["rms_px"] < 1e-9


CRB_FREE = ["fx", "fy", "cx", "cy", "skew", "k1", "k2"]


def crb_ratios(sigma, trials, seed):
    """Empirical std of Zhang's estimates over noisy trials / Cramer-Rao std, per CRB_FREE."""
    rng = np.random.default_rng(seed)
    board, rvecs, tvecs = synthetic_views(RECT_K1K2, 20, rng)
    free = free_mask(MODEL.param_names, CRB_FREE)
    info = intrinsic_information(MODEL, MODEL.params_of(RECT_K1K2), free, [board] * 20,
                                 rvecs, tvecs)
    bound = np.sqrt(np.diag(np.linalg.inv(info))) * sigma
    estimates, reported = [], []
    for _ in range(trials):
        result = get_calibrator("zhang").calibrate(observe(RECT_K1K2, board, rvecs, tvecs,
                                                           sigma, rng))
        estimates.append(MODEL.params_of(result.camera)[free])
        reported.append([result.log["param_std"][n] for n in CRB_FREE])
    ratio = np.std(estimates, axis=0, ddof=1) / bound
    print(f"sigma {sigma}: empirical / CRB std " + ", ".join(
        f"{n} {r:.3f}" for n, r in zip(CRB_FREE, ratio)))
    return ratio, np.mean(reported, axis=0) / bound


def chi_band(trials, p=1e-3):
    """Two-sided (1 - p) band of (sample std / true std) for Gaussian samples: chi^2(trials-1)."""
    q = chi2.ppf([p / 2, 1 - p / 2], trials - 1) / (trials - 1)
    return np.sqrt(q)


@pytest.mark.parametrize("sigma", [0.1, 1.0])
def test_cramer_rao_bound_is_reached(sigma):
    """50 trials. A std estimated from 50 samples scatters by ~10 %, so the 20 % of the slow test
    would be a 2-sigma band here (3 of 10 seeds tried failed it, all passed the band used); the
    band is the 99.9 % one of the chi^2 distribution instead, [0.68, 1.34]. The reported param_std
    (residual variance x inverse information at the estimate) has no such scatter: within 5 %."""
    ratio, reported = crb_ratios(sigma, trials=50, seed=int(10 * sigma))
    lo, hi = chi_band(50)
    assert np.all((lo < ratio) & (ratio < hi))
    assert np.all(np.abs(reported - 1) < 0.05)


@pytest.mark.slow
@pytest.mark.parametrize("sigma", [0.1, 1.0])
def test_cramer_rao_bound_is_reached_within_20_percent(sigma):
    """200 trials: the 99.9 % chi^2 band is [0.84, 1.17], inside the 20 % asked of the estimator."""
    ratio, _ = crb_ratios(sigma, trials=200, seed=100 + int(10 * sigma))
    assert np.all(np.abs(ratio - 1) < 0.2)
