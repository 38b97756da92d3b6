"""Triangulation against ground truth, scipy's least_squares and its own invariances.

The rig mixes the paper's rectilinear and wide-angle cameras (k1 = 0.5), toed in to 600 mm.
"""

import numpy as np
import pytest
from scipy.optimize import least_squares

from stereo_bench.core.camera import Camera
from stereo_bench.core.poses import look_at_rotation, matrix_to_rodrigues
from stereo_bench.multiview.triangulate import (refine_points, reprojection_errors, triangulate,
                                                triangulate_dlt, triangulate_midpoint,
                                                triangulate_robust)

RECT = Camera("rect", 4096, 3072, 3000, 3000, 2048, 1536, 0, [0.05, 0.02, 0.001, 0, 0, 0, 0, 0])
WIDE = Camera("wide", 640, 480, 600, 450, 320, 240, 0, [0.5, 0.1, 0.03, 0, 0, 0, 0, 0])


def placed(cam, position):
    R = look_at_rotation(np.array(position, float), np.array([0.0, 0, 600]), np.array([0, -1.0, 0]))
    return cam.with_params(rvec=matrix_to_rodrigues(R), tvec=-R @ np.array(position, float))


CAMS = [placed(RECT, (-75, 0, 0)), placed(WIDE, (75, 0, 0)), placed(WIDE, (0, -100, 0)),
        placed(RECT, (0, 100, 0))]


def scene(noise_px=0.0, shape=(30, 24), seed=0):
    """True points (..., 3) and their pixels (C, ..., 2) in every camera."""
    rng = np.random.default_rng(seed)
    X = rng.uniform([-100, -80, 450], [100, 80, 800], shape + (3,))
    uv = np.stack([cam.project(X) for cam in CAMS])
    for c, cam in enumerate(CAMS):  # the wide-angle corners are used: a real test of unproject
        assert np.all((uv[c] >= 0) & (uv[c] <= [cam.width - 1, cam.height - 1]))
    return X, uv + rng.normal(0, noise_px, uv.shape)


@pytest.mark.parametrize("method", ["dlt", "midpoint", "refined", "robust"])
def test_noise_free_pixels_give_the_true_points(method):
    X, uv = scene()
    Y = triangulate(CAMS, uv, method=method)
    assert Y.shape == X.shape
    assert np.abs(Y - X).max() < 1e-6  # mm; measured ~1e-9 (linear), ~1e-12 (refined)
    # Any two cameras, including the two wide-angle ones alone.
    assert np.abs(triangulate(CAMS[1:3], uv[1:3], method=method) - X).max() < 1e-6


@pytest.mark.parametrize("method", ["dlt", "midpoint", "refined", "robust"])
def test_wide_lenses_triangulate_through_their_rays(method):
    """Fisheye and omnidirectional cameras (a GoPro-like studio's): points up to ~80 degrees
    off a camera's axis, unprojected through each lens's exact rays, come back exact."""
    fisheye = Camera("kb", 1920, 1080, 880, 880, 959.5, 539.5, 0, [0.04, -0.01, 0.003, -5e-4],
                     model="kannala_brandt")
    mei = Camera("mei", 1280, 960, 600, 600, 639.5, 479.5, 0, [0.9, -0.15, 0.03, 2e-4, -3e-4],
                 model="mei")
    cams = [placed(fisheye, (-150, 0, 0)), placed(mei, (150, 0, 0)),
            placed(fisheye, (0, -150, 100))]
    X = np.random.default_rng(3).uniform([-900, -500, 150], [900, 500, 900], (400, 3))
    Pc = np.stack([cam.world_to_cam(X) for cam in cams])
    off_axis = np.degrees(np.arccos(Pc[..., 2] / np.linalg.norm(Pc, axis=-1)))
    keep = (off_axis < 80).all(0)
    assert off_axis[:, keep].max() > 70
    uv = np.stack([cam.project(X[keep]) for cam in cams])
    assert np.abs(triangulate(cams, uv, method=method) - X[keep]).max() < 1e-6


@pytest.mark.parametrize("method", ["dlt", "midpoint", "refined"])
def test_missing_views_and_zero_weights(method):
    X, uv = scene()
    uv[0, 0] = np.nan  # frame 0: camera 0 missing
    w = np.ones(uv.shape[:-1])
    w[1:3, 1] = 0  # frame 1: cameras 1 and 2 weighted out
    uv[:3, 2, :5] = np.nan  # frame 2, joints 0..4: one view left -> NaN
    Y = triangulate(CAMS, uv, w, method=method)
    assert np.isnan(Y[2, :5]).all() and np.isfinite(Y[2, 5:]).all()
    ok = np.isfinite(Y)
    assert np.abs(Y[ok] - X[ok]).max() < 1e-6
    # Missing views are exactly the views of the cameras left out.
    same = triangulate([CAMS[0], CAMS[3]], uv[[0, 3], 1], method=method)
    assert np.allclose(Y[1], same, rtol=0, atol=1e-12)


@pytest.mark.parametrize("method", ["dlt", "midpoint", "refined"])
def test_a_weight_counts_like_repeated_views(method):
    # Cost sum_c (w_c r_c)^2: a view with weight sqrt(2) is the same view observed twice.
    _, uv = scene(noise_px=1.0, shape=(50,))
    w = np.ones(uv.shape[:-1])
    w[1] = np.sqrt(2)
    twice = triangulate(CAMS + [CAMS[1]], np.concatenate([uv, uv[1:2]]), method=method)
    assert np.allclose(triangulate(CAMS, uv, w, method=method), twice, rtol=0, atol=1e-8)
    # Scaling all of a point's weights changes nothing.
    assert np.allclose(triangulate(CAMS, uv, 3 * w, method=method), twice, rtol=0, atol=1e-8)


def test_refined_is_no_worse_than_linear_and_is_the_least_squares_optimum():
    X, uv = scene(noise_px=0.5)
    dlt, mid = triangulate_dlt(CAMS, uv), triangulate_midpoint(CAMS, uv)
    ref = refine_points(CAMS, uv, dlt)
    cost = {k: np.sum(reprojection_errors(CAMS, Y, uv) ** 2, axis=0)
            for k, Y in (("dlt", dlt), ("mid", mid), ("ref", ref))}
    assert np.all(cost["ref"] <= cost["dlt"] * (1 + 1e-12))
    assert np.all(cost["ref"] <= cost["mid"] * (1 + 1e-12))
    assert np.sqrt(cost["ref"].mean() / 4) < np.sqrt(cost["mid"].mean() / 4)  # RMS, not only <=
    # scipy, started at the truth, finds the same optimum.
    for j in range(5):
        def fun(p, j=j):
            return np.concatenate([c.project(p) - uv[i, 0, j] for i, c in enumerate(CAMS)])
        sol = least_squares(fun, X[0, j], xtol=1e-15, ftol=1e-15, gtol=1e-15)
        assert np.abs(sol.x - ref[0, j]).max() < 1e-6


@pytest.mark.parametrize("loss", ["huber", "cauchy"])
def test_robust_losses_reach_the_optimum_of_their_cost(loss):
    X, uv = scene(noise_px=0.5, shape=(5,))
    uv[1] += [40.0, -30.0]  # a gross outlier in one view of every point
    ref = triangulate(CAMS, uv, loss=loss, loss_scale_px=2.0)
    for j in range(5):
        def fun(p, j=j):  # the loss applies to each view's pixel error |r_c|: one residual each
            return np.linalg.norm(np.stack([c.project(p) for c in CAMS]) - uv[:, j], axis=-1)
        sol = least_squares(fun, ref[j], loss=loss, f_scale=2.0, xtol=1e-15, ftol=1e-15,
                            gtol=1e-15)
        assert np.abs(sol.x - ref[j]).max() < 1e-5
    if loss == "cauchy":  # redescending: the outlier loses its pull
        without = triangulate(CAMS, uv, np.array([1.0, 0, 1, 1])[:, None] * np.ones(5))
        assert np.linalg.norm(ref - without, axis=-1).max() < 0.25  # mm
        assert np.linalg.norm(triangulate(CAMS, uv) - X, axis=-1).min() > 5.0  # pulled away


def test_robust_option_rejects_a_planted_outlier_view():
    X, uv = scene(noise_px=0.3, shape=(200,), seed=1)
    rng = np.random.default_rng(2)
    bad = rng.integers(0, 4, 200)  # one outlier view per point, in a random camera
    uv[bad, np.arange(200)] += rng.choice([-1, 1], (200, 2)) * rng.uniform(15, 60, (200, 2))
    Y, inliers = triangulate_robust(CAMS, uv, threshold_px=5.0)
    expected = np.ones((4, 200), bool)
    expected[bad, np.arange(200)] = False
    assert np.array_equal(inliers, expected)
    # As good as triangulating the clean views alone.
    clean = refine_points(CAMS, uv, triangulate_dlt(CAMS, uv, expected * 1.0), expected * 1.0)
    assert np.abs(Y - clean).max() < 1e-6
    assert np.linalg.norm(Y - X, axis=-1).max() < 5.0  # 3 views at 0.3 px: up to 3.4 mm
    assert np.linalg.norm(triangulate(CAMS, uv) - X, axis=-1).max() > 20.0  # it mattered


def test_degenerate_and_bad_input():
    X, uv = scene(shape=(3,))
    # The same camera twice: parallel rays, no intersection.
    assert np.isnan(triangulate_dlt([CAMS[0], CAMS[0]], uv[[0, 0]])).all()
    with pytest.raises(ValueError, match="pixels"):
        triangulate_dlt(CAMS, uv[:3])
    with pytest.raises(ValueError, match="weights"):
        triangulate_dlt(CAMS, uv, -np.ones((4, 3)))
    with pytest.raises(ValueError, match="loss"):
        refine_points(CAMS, uv, X, loss="l1")
    with pytest.raises(ValueError, match="method"):
        triangulate(CAMS, uv, method="svd")
