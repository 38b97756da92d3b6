"""Tsai's calibration against its own model, finite differences and an OpenCV-model camera."""

import numpy as np
import pytest

from stereo_bench.calibrate import get_calibrator
from stereo_bench.calibrate.base import Observations
from stereo_bench.calibrate.tsai import (TsaiCalibrator, TsaiModel, TsaiUnreachableError,
                                         distortion_ratio, initial_estimate, radial_alignment_pose,
                                         tsai_to_opencv)
from stereo_bench.core.camera import Camera
from stereo_bench.core.poses import rodrigues_to_matrix

# 8 x 11 inner corners, 15 mm apart, origin at the first corner as OpenCV's detectors put it.
BOARD = np.concatenate([np.stack(np.meshgrid(np.arange(8.0), np.arange(11.0)), -1)
                        .reshape(-1, 2) * 15.0, np.zeros((88, 1))], 1)
RECTILINEAR = Camera("rect", 4096, 3072, 3000, 3000, 2048, 1536, 0,
                     np.array([0.05, 0.02, 0.001, 0, 0, 0, 0, 0]))


def tsai_params(w, h, f, sx, K):
    """[f, sx, cx, cy, kappa1] with the principal point at the image centre; K = kappa1 f^2."""
    return np.array([f, sx, (w - 1) / 2, (h - 1) / 2, K / f**2])


def make_views(rng, project, size, fy, n=30):
    """n cam_from_board poses, tilted 11-40 degrees, whose corners all land inside the image.

    project(rvec, tvec) -> (88, 2) pixels. The board fills 35-60 % of the image height and
    wanders over the image so that the corners reach its edges.
    """
    w, h = size
    rvecs, tvecs = [], []
    while len(rvecs) < n:
        axis = rng.normal(size=3) * [1, 1, 0.3]
        r = axis / np.linalg.norm(axis) * rng.uniform(0.2, 0.7)
        z = fy * 150.0 / (h * rng.uniform(0.35, 0.6))
        centre = rodrigues_to_matrix(r) @ BOARD.mean(0)
        t = np.array([rng.uniform(-0.35, 0.35) * w / fy * z, rng.uniform(-0.35, 0.35) * h / fy * z,
                      z]) - centre
        uv = project(r, t)
        if np.all(uv >= 0) and np.all(uv <= [w - 1, h - 1]):
            rvecs.append(r)
            tvecs.append(t)
    return np.array(rvecs), np.array(tvecs)


def tsai_observations(params, size, seed, n=30):
    model = TsaiModel(strict=False)  # a pose reaching beyond a fold projects to NaN: rejected
    project = lambda r, t: model.project(params, BOARD @ rodrigues_to_matrix(r).T + t)[0]
    rvecs, tvecs = make_views(np.random.default_rng(seed), project, size, params[0], n)
    obs = Observations([BOARD] * n, [project(r, t) for r, t in zip(rvecs, tvecs)], size,
                       list(range(n)), "tsai-truth")
    return obs, rvecs, tvecs


def test_distortion_ratio_solves_the_cubic_and_refuses_the_fold():
    ru = np.linspace(0.0, 490.0, 1001)  # up to 99 % of the fold radius for kappa1 < 0
    for kappa1 in (6e-7, -6e-7):
        rho, _, _ = distortion_ratio(ru**2, kappa1)
        rd = rho * ru
        assert np.max(np.abs(rd * (1 + kappa1 * rd**2) - ru)) < 1e-12 * 490
        # The monotone branch: r_d increases with r_u.
        assert np.all(np.diff(rd) > 0)
    fold_ru = 2 / 3 / np.sqrt(3 * 6e-7)  # 496.9 px: the largest r_u that kappa1 = -6e-7 reaches
    with pytest.raises(TsaiUnreachableError, match="folds"):
        distortion_ratio(np.array([100.0, 1.01 * fold_ru]) ** 2, -6e-7)
    rho, _, _ = distortion_ratio(np.array([100.0, 1.01 * fold_ru]) ** 2, -6e-7, strict=False)
    assert np.isfinite(rho[0]) and np.isnan(rho[1])


@pytest.mark.parametrize("kappa1", [6e-7, -6e-7])
def test_model_jacobians_match_finite_differences(kappa1):
    rng = np.random.default_rng(3)
    params = np.array([500.0, 1.02, 321.0, 238.0, kappa1])
    pts = np.stack([rng.uniform(-0.5, 0.5, 50), rng.uniform(-0.4, 0.4, 50), np.ones(50)], -1)
    pts *= rng.uniform(200, 800, (50, 1))
    model = TsaiModel()
    _, Jp, Jx = model.project(params, pts)

    def central(fun, x, j, h):
        e = np.zeros_like(x)
        e[j] = h
        return (fun(x + e) - fun(x - e)) / (2 * h)

    fd_p = np.stack([central(lambda p: model.project(p, pts)[0], params, j,
                             1e-6 * abs(params[j])) for j in range(5)], -1)
    fd_x = np.stack([np.stack([central(lambda q: model.project(params, q[None])[0][0], p, j,
                                       1e-6 * np.abs(p).max()) for p in pts])
                     for j in range(3)], -1)
    for J, fd in ((Jp, fd_p), (Jx, fd_x)):
        scale = np.abs(J).max(axis=(0, 1))  # relative to each column's size
        assert np.all(np.abs(J - fd).max(axis=(0, 1)) <= 1e-6 * scale)


@pytest.mark.parametrize("K", [0.0, 0.15])
def test_radial_alignment_is_exact(K):
    """RAC and the linear f, Tz are exact without distortion; the RAC is exact with it too."""
    params = tsai_params(640, 480, 500.0, 1.0, K)
    obs, rvecs, tvecs = tsai_observations(params, (640, 480), seed=1, n=20)
    # Put one board origin on the camera's x-z plane: Ty = 0 breaks a RAC solved at the origin.
    R0 = rodrigues_to_matrix(rvecs[0])
    tvecs[0, 1] = 0.0
    obs.image_points[0] = TsaiModel().project(params, BOARD @ R0.T + tvecs[0])[0]

    for xy, uv, r, t in zip(obs.object_points, obs.image_points, rvecs, tvecs):
        R, tx, ty = radial_alignment_pose(xy[:, :2], uv - params[2:4])
        R_true = rodrigues_to_matrix(r)
        assert np.abs(R[:2, :2] - R_true[:2, :2]).max() < 1e-12  # the part the RAC fixes
        assert np.abs([tx - t[0], ty - t[1]]).max() < 1e-10 * np.linalg.norm(t)
    if K == 0.0:  # with the f > 0 branch choice and stage 2, the whole pose and f are exact
        params0, rv0, tv0 = initial_estimate(obs, 1.0)
        assert abs(params0[0] - 500.0) < 1e-9 * 500
        assert np.abs(rv0 - rvecs).max() < 1e-12
        assert np.abs(tv0 - tvecs).max() < 1e-10 * np.abs(tvecs).max()


@pytest.mark.parametrize("size, f, sx, K", [
    ((640, 480), 500.0, 1.0, 0.15),      # barrel, as the TV lenses of Tsai's era
    ((640, 480), 500.0, 1.02, 0.15),     # plus a 2 % horizontal scale error (frame grabber)
    ((4096, 3072), 3000.0, 1.02, -0.05),  # pincushion of SynthCal's rectilinear lens (k1 = 0.05)
])
def test_recovers_tsai_model_exactly(size, f, sx, K):
    params = tsai_params(*size, f, sx, K)
    obs, rvecs, tvecs = tsai_observations(params, size, seed=2)
    res = TsaiCalibrator().calibrate(obs)
    est = np.array([res.log["tsai"][n] for n in ("f", "sx", "kappa1")])
    rel = np.abs(est / params[[0, 1, 4]] - 1)
    print(f"\n{size} f={f} sx={sx} K={K}: rel. errors f, sx, kappa1 = {rel}, "
          f"rvec {np.abs(res.rvecs - rvecs).max():.2e} rad, "
          f"tvec {np.abs(res.tvecs - tvecs).max():.2e} mm, rms {res.log['rms_px']:.2e} px, "
          f"{res.log['iterations']} iterations, {res.log['time_s']:.3f} s")
    assert np.all(rel < 1e-6)
    assert np.abs(res.rvecs - rvecs).max() < 1e-6
    assert np.abs(res.tvecs - tvecs).max() < 1e-6 * np.abs(tvecs).max()
    assert res.camera.fx == pytest.approx(sx * f, rel=1e-6)
    assert res.camera.fy == pytest.approx(f, rel=1e-6)


def test_view_parallel_to_the_image_is_harmless():
    """Alone, a fronto-parallel view cannot separate f from Tz nor pick the f > 0 branch."""
    params = tsai_params(640, 480, 500.0, 1.0, 0.15)
    obs, rvecs, tvecs = tsai_observations(params, (640, 480), seed=7, n=10)
    rvecs[0] = 0.0
    obs.image_points[0] = TsaiModel().project(params, BOARD + tvecs[0])[0]
    res = TsaiCalibrator().calibrate(obs)
    assert res.log["tsai"]["f"] == pytest.approx(500.0, rel=1e-9)
    assert np.abs(res.rvecs - rvecs).max() < 1e-9


def test_free_principal_point_and_known_sx():
    params = tsai_params(640, 480, 500.0, 1.02, 0.15)
    params[2:4] += [6.0, -4.0]
    obs, _, _ = tsai_observations(params, (640, 480), seed=4)
    free = TsaiCalibrator(free_principal_point=True).calibrate(obs)
    assert np.allclose([free.log["tsai"][n] for n in ("f", "sx", "cx", "cy", "kappa1")], params,
                       rtol=1e-6, atol=0)
    fixed = TsaiCalibrator(sx=1.02).calibrate(obs)  # centre held 7 px off: a biased fit
    assert fixed.log["tsai"]["sx"] == 1.02 and fixed.log["rms_px"] > 1e3 * free.log["rms_px"]


@pytest.mark.parametrize("name, size, f, sx, K, bounded", [
    ("wide 640x480, f=450, TV-lens barrel", (640, 480), 450.0, 1.0, 0.1, True),
    ("wide 640x480, f=500, TV-lens barrel", (640, 480), 500.0, 1.0, 0.1, True),
    ("wide 640x480, f=600, TV-lens barrel", (640, 480), 600.0, 1.0, 0.1, True),
    ("rectilinear 4096x3072, f=3000, Tsai's fit of SynthCal's lens", (4096, 3072), 3000.0, 1.0,
     -0.055, True),
    ("wide 640x480, f=450, sx=4/3, Tsai's fit of SynthCal's lens", (640, 480), 450.0, 4 / 3,
     -0.31, False),
])
def test_conversion_to_opencv(name, size, f, sx, K, bounded):
    """Tsai's exact map against the fitted OpenCV coefficients, over the whole image.

    Bounds: the least-squares fit can be no worse in RMS than the truncated series
    (-K, 3K^2, -12K^3), which holds for any kappa1; and the RMS must stay 7x below the 0.035 px
    corner floor of rendered images (TRAPS.md) and the maximum (at the extreme corners, where
    few corners are seen) below that floor, so the conversion cannot move the benchmark's pixel
    metrics. k1..k3 alone leave px-sized residuals for SynthCal's wide lens (Tsai's K ~ -0.31),
    so there the rational model is fitted (``bounded`` False marks that case).
    """
    params = tsai_params(*size, f, sx, K)
    cam, rep = tsai_to_opencv(params, *size)
    # Exact check of the residual: distorted pixel -> Tsai's undistorted ray -> OpenCV pixel.
    w, h = size
    uv = np.stack(np.meshgrid(np.linspace(0, w - 1, 161), np.linspace(0, h - 1, 161)), -1)
    uv = uv.reshape(-1, 2)
    pd = (uv - params[2:4]) / [sx, 1.0]
    xy = pd * (1 + params[4] * np.sum(pd**2, 1))[:, None] / f
    err = np.linalg.norm(cam.normalized_to_pixels(xy) - uv, axis=1)
    series = Camera("s", w, h, sx * f, f, *params[2:4], 0.0,
                    np.array([rep.series_k[0], rep.series_k[1], 0, 0, rep.series_k[2]]))
    err_series = np.linalg.norm(series.normalized_to_pixels(xy) - uv, axis=1)
    print(f"\n{name}: K = {K}: conversion max {rep.max_px:.4g} px, RMS {rep.rms_px:.4g} px "
          f"(series: max {err_series.max():.4g}, RMS {np.sqrt(np.mean(err_series**2)):.4g}); "
          f"k1..k3 = {cam.dist[[0, 1, 4]]}, series {np.array(rep.series_k)}")
    assert rep.max_px == pytest.approx(err.max(), rel=1e-9)
    assert rep.rms_px == pytest.approx(np.sqrt(np.mean(err**2)), rel=1e-9)
    assert rep.rms_px <= np.sqrt(np.mean(err_series**2))
    # The r^2 coefficient of num/den is k1 - k4; it equals -K to first order (next term O(K^2)).
    assert abs((cam.dist[0] - cam.dist[5]) / -K - 1) < abs(K)
    assert rep.rms_px < 0.005 and rep.max_px < 0.035
    assert bounded or np.any(cam.dist[5:] != 0)


def test_conversion_refuses_a_fold_inside_the_image():
    with pytest.raises(TsaiUnreachableError, match="inside the 640x480 image"):
        tsai_to_opencv(tsai_params(640, 480, 450.0, 1.0, -0.5), 640, 480)


def test_realistic_rectilinear_camera_with_noise():
    """OpenCV-model observations (k2, p1 and the 0.5 px off-centre principal point are outside
    Tsai's model) with 0.3 px noise: focal lengths within 1 %."""
    rng = np.random.default_rng(5)
    project = lambda r, t: RECTILINEAR.with_params(rvec=r, tvec=t).project(BOARD)
    rvecs, tvecs = make_views(rng, project, RECTILINEAR.size, RECTILINEAR.fy, n=30)
    img = [project(r, t) + rng.normal(0, 0.3, (88, 2)) for r, t in zip(rvecs, tvecs)]
    obs = Observations([BOARD] * 30, img, RECTILINEAR.size, list(range(30)), "rect")
    res = get_calibrator("tsai").calibrate(obs)
    cam, log = res.camera, res.log
    err_fx, err_fy = cam.fx / RECTILINEAR.fx - 1, cam.fy / RECTILINEAR.fy - 1
    grid = RECTILINEAR.pixel_grid(32).reshape(-1, 2)
    diff = np.linalg.norm(cam.normalized_to_pixels(RECTILINEAR.unproject(grid)) - grid, axis=1)
    print(f"\nrectilinear, 0.3 px noise: fx {err_fx:+.3%}, fy {err_fy:+.3%}, "
          f"K = {log['kappa1_f2']:.4f}, rms {log['rms_px']:.3f} px, "
          f"{log['iterations']} iterations, cost {log['initial_cost']:.4g} -> "
          f"{log['final_cost']:.4g}, {log['time_s']:.3f} s, conversion max "
          f"{log['opencv_conversion']['max_px']:.4f} px; projection difference to truth "
          f"mean {diff.mean():.2f} px, max {diff.max():.2f} px")
    assert abs(err_fx) < 0.01 and abs(err_fy) < 0.01
    assert log["method"] == "tsai" and log["final_cost"] < log["initial_cost"]
    assert 0.3 < log["rms_px"] < 0.6  # noise plus the unmodelled k2 and p1
    assert log["opencv_conversion"]["rms_px"] < 0.005
    assert res.rvecs.shape == res.tvecs.shape == (30, 3)


def test_degenerate_view_names_the_view():
    params = tsai_params(640, 480, 500.0, 1.0, 0.0)
    obs, _, _ = tsai_observations(params, (640, 480), seed=6, n=5)
    line = [0, 1, 2, 3, 4, 5, 6, 7]  # one board row: a line, rank-deficient for the RAC
    bad = Observations(obs.object_points[:4] + [BOARD[line]],
                       obs.image_points[:4] + [obs.image_points[4][line]], (640, 480),
                       [10, 11, 12, 13, 14])
    with pytest.raises(ValueError, match="view 14: radial alignment"):
        TsaiCalibrator().calibrate(bad)
