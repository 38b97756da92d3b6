"""Diagnostics without ground truth: they fire on planted faults (a bad view, displaced corners,
a lens model too simple) and stay quiet on clean Gaussian noise, at their nominal rates.

Observations are exact projections (camera.py) of test_calibrate's 8 x 11 board with Gaussian
noise of SIGMA px per coordinate, calibrated with the ``opencv`` method (k1, k2, p1, p2, k3).
"""

import json

import cv2
import numpy as np
import pytest
from scipy.stats import binom, kstest

from test_calibrate import observe, synthetic_views

from stereo_bench.calibrate import Observations, get_calibrator
from stereo_bench.core.camera import Camera
from stereo_bench.calibrate.diagnostics import (coverage, diagnose, heldout, neighbour_pairs,
                                                point_outliers, residual_randomness, view_outliers)

CAM = Camera("diag", 640, 480, 520, 520, 322, 238, 0, [0.1, -0.05, 0.001, -0.001, 0.0])
OPENCV = get_calibrator("opencv")
SIGMA = 0.3


def noisy(seed, camera=CAM, n_views=20):
    rng = np.random.default_rng(seed)
    board, rv, tv = synthetic_views(camera, n_views, rng)
    return observe(camera, board, rv, tv, SIGMA, rng), rng


def replaced(obs, image_points):
    return Observations(obs.object_points, image_points, obs.image_size, obs.view_ids,
                        obs.camera_name)


@pytest.fixture(scope="module")
def clean():
    """20 clean calibrations (seeds 0..19) and their randomness tests (499 simulations: p-values
    in steps of 0.002 are fine enough to test their uniformity): the null's sample."""
    runs = []
    for seed in range(20):
        obs, _ = noisy(seed)
        fit = OPENCV.calibrate(obs)
        runs.append((obs, fit, residual_randomness(fit.camera, obs, fit.rvecs, fit.tvecs,
                                                   OPENCV.model_parameters, n_sim=499,
                                                   seed=seed)))
    return runs


def test_clean_noise_raises_no_flags(clean):
    """Views: the modified z-score cut at 3.5 (scale floored at the noise spread) flags none of
    400 clean views (without the floor: 2; with it, none of 4000 more, largest z 3.45).
    Points: the threshold is set so that N Gaussian residuals exceed it with probability 1 %
    altogether; calibrations with any flagged point must stay inside the binomial 99.9 % bound
    of 20 runs at 1 % (3). Measured: 1 of these 20, 2 of 200 more (seeds 100-299)."""
    view_flags = sum(len(view_outliers(fit.camera, obs, fit.rvecs, fit.tvecs)["flagged"])
                     for obs, fit, _ in clean)
    assert view_flags == 0
    runs_with_points = 0
    for obs, fit, _ in clean:
        points = point_outliers(fit.camera, obs, fit.rvecs, fit.tvecs)
        assert points["sigma_px"] == pytest.approx(SIGMA, rel=0.1)
        runs_with_points += bool(points["flagged"])
    assert runs_with_points <= binom.ppf(0.999, len(clean), 0.01)


def test_randomness_p_values_are_uniform_on_clean_noise(clean):
    """400 per-view p-values: uniform (Kolmogorov-Smirnov) and flagged at the nominal 5 % (a
    binomial 99.9 % band, 7-36). Fitted residuals of neighbouring points are anti-correlated
    (statistic about -0.03); the null simulated through the fit knows it, a plain permutation
    test does not (it flagged 0.5 % of 200 clean views at 5 %: ten times too conservative).
    Measured: 13 of these 400 at 5 % (3 %), none at 1 %; 4.5 % and 0.7 % of 1200 views (60
    seeds, 999 simulations), and 2 of those 60 cameras at 5 %."""
    p = np.array([v["p_value"] for _, _, rr in clean for v in rr["views"]])
    assert len(p) == 400
    assert kstest(p, "uniform").pvalue > 0.001
    lo, hi = binom.ppf([5e-4, 1 - 5e-4], len(p), 0.05)
    assert lo <= np.sum(p < 0.05) <= hi
    assert all(-0.06 < rr["null_mean"] < -0.01 for _, _, rr in clean)
    camera_p = np.array([rr["p_value"] for _, _, rr in clean])
    assert np.sum(camera_p < 0.01) <= binom.ppf(1 - 1e-3, len(camera_p), 0.01)
    assert kstest(camera_p, "uniform").pvalue > 0.001


def test_a_bad_view_is_flagged():
    """One view with 3 sigma more noise (3.2 sigma in all): its modified z-score is far above
    3.5, and no other view is flagged."""
    obs, rng = noisy(5)
    image = list(obs.image_points)
    image[7] = image[7] + rng.normal(0.0, 3 * SIGMA, image[7].shape)
    bad = replaced(obs, image)
    fit = OPENCV.calibrate(bad)
    out = view_outliers(fit.camera, bad, fit.rvecs, fit.tvecs)
    assert out["flagged"] == [7]
    assert out["modified_z"][7] > 10 and out["rms_px"][7] > 2.5 * out["median_px"]
    json.dumps(out, allow_nan=False)


def test_displaced_corners_are_flagged_and_only_they():
    obs, _ = noisy(6)
    image = [p.copy() for p in obs.image_points]
    planted = {(3, 5): [2.0, -1.5], (3, 40): [-1.8, -1.8], (12, 60): [2.5, 0.0]}
    for (v, i), shift in planted.items():
        image[v][i] += shift
    bad = replaced(obs, image)
    fit = OPENCV.calibrate(bad)
    out = point_outliers(fit.camera, bad, fit.rvecs, fit.tvecs)
    assert {(f["view_id"], f["index"]) for f in out["flagged"]} == set(planted)
    assert out["flagged"][0]["residual_px"] > 2.0 > out["threshold_px"]
    assert out["flagged"][0]["image_point"] == image[12][60].tolist()


def test_a_lens_model_too_simple_leaves_correlated_residuals(clean):
    """k1 = 0.05 fitted with no distortion at all: the residuals are smooth over each board
    (statistic 0.2 against a null of -0.03) and the camera and most views are flagged; the same
    data with k1 free are not flagged (and neither is the clean reference fit)."""
    camera = Camera("k1", 640, 480, 520, 520, 322, 238, 0, [0.05])
    obs, _ = noisy(3, camera)
    pinhole = get_calibrator("opencv", flags=cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2
                             | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST)
    fit = pinhole.calibrate(obs)
    assert not np.any(fit.camera.dist)
    out = residual_randomness(fit.camera, obs, fit.rvecs, fit.tvecs, ("fx", "fy", "cx", "cy"))
    assert out["flagged"] and out["p_value"] <= 0.002 and out["statistic"] > 0.1
    assert len(out["flagged_views"]) >= 10
    radial = get_calibrator("opencv-radial2")
    fit = radial.calibrate(obs)
    out = residual_randomness(fit.camera, obs, fit.rvecs, fit.tvecs, radial.model_parameters)
    assert not out["flagged"] and len(out["flagged_views"]) <= 2
    json.dumps(out, allow_nan=False)


def test_neighbour_pairs_of_a_grid():
    """8-neighbourhood of an 11 x 8 grid: 10*8 + 11*7 edges and 2 * 10*7 diagonals."""
    x, y = np.meshgrid(np.arange(11) * 15.0, np.arange(8) * 15.0)
    board = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], -1)
    pairs = neighbour_pairs(board)
    assert len(pairs) == 10 * 8 + 11 * 7 + 2 * 10 * 7
    d = np.linalg.norm(board[pairs[:, 0]] - board[pairs[:, 1]], axis=1)
    assert np.all(d < 15 * 1.5) and np.all(pairs[:, 0] < pairs[:, 1])


def test_coverage_of_known_layouts():
    """Features on the left half of a 640 x 480 image, as two boards: counts, cell share, the
    hull of all features and the union of the two views' hulls, checked by hand."""
    u, v = np.meshgrid(np.arange(0.0, 320.0, 16.0), np.arange(0.0, 480.0, 16.0))
    left = np.stack([u.ravel(), v.ravel()], -1)  # 20 x 30 points, u in [0, 304], v in [0, 464]
    top, bottom = left[left[:, 1] < 240], left[left[:, 1] >= 240]
    board = np.column_stack([left, np.zeros(len(left))])
    obs = Observations([board[left[:, 1] < 240], board[left[:, 1] >= 240]], [top, bottom],
                       (640, 480), [0, 1])
    out = coverage(obs, grid=(10, 8))
    json.dumps(out, allow_nan=False)
    counts = np.array(out["counts"])
    assert counts.shape == (8, 10) and counts.sum() == len(left) and out["outside"] == 0
    assert out["cell_fraction"] == 0.5 and np.all(counts[:, :5] > 0)
    assert out["hull_fraction"] == pytest.approx(304 * 464 / (640 * 480))
    # two hulls 304 x 224 px; rasterized at 1 px: within a pixel of each edge
    assert out["board_fraction"] == pytest.approx(2 * 304 * 224 / (640 * 480), rel=0.02)
    assert out["board_fraction"] < out["hull_fraction"]


def test_heldout_error_exceeds_in_sample_and_stays_near_the_noise():
    """On Gaussian noise the held-out RMS is the noise plus what the trained intrinsics miss,
    the in-sample RMS the noise minus what the fit absorbed: held-out > in-sample on the same
    points, both within 5 % of sqrt(2) sigma (the RMS of a 2D residual). Measured: 0.4178 vs
    0.4163 px (ratio 1.0036) against 0.4243."""
    obs, _ = noisy(5)
    out = heldout("opencv", obs, k=5, seed=0)
    json.dumps(out, allow_nan=False)
    assert out["folds"] == 5 and out["note"] == "" and not out["fold_errors"]
    assert sorted(v["fold"] for v in out["views"]) == sorted(np.repeat(np.arange(5), 4))
    assert out["heldout_rms_px"] > out["in_sample_rms_px"]
    assert 1.0 < out["ratio"] < 1.05
    for rms in (out["heldout_rms_px"], out["in_sample_rms_px"], out["train_rms_px"]):
        assert abs(rms / (np.sqrt(2) * SIGMA) - 1) < 0.05
    per_view = np.array([[v["heldout_rms_px"], v["in_sample_rms_px"]] for v in out["views"]])
    assert np.mean(per_view[:, 0] > per_view[:, 1]) > 0.75


def test_heldout_with_few_views_uses_fewer_folds_and_refuses_too_few():
    obs, _ = noisy(5, n_views=4)
    out = heldout("opencv", obs, k=5)
    assert out["folds"] == 4 and "4 folds (leave one view out) instead of 5" in out["note"]
    assert all(v["heldout_rms_px"] is not None for v in out["views"])
    with pytest.raises(ValueError, match="k: 2 folds of 4 views leave fewer than 3"):
        heldout("opencv", obs, k=2)
    three = Observations(obs.object_points[:3], obs.image_points[:3], obs.image_size, [0, 1, 2])
    with pytest.raises(ValueError, match="3 views; held-out errors need at least 4"):
        heldout("opencv", three)
    with pytest.raises(ValueError, match="unknown calibration method"):
        heldout("matlab", obs)


def test_diagnose_bundles_the_checks_and_is_json(clean):
    obs, fit, _ = clean[0]
    out = diagnose(fit.camera, obs, fit.rvecs, fit.tvecs, OPENCV.model_parameters)
    assert set(out) == {"views", "points", "randomness", "coverage"}
    json.dumps(out, allow_nan=False)
    with pytest.raises(ValueError, match=r"tvecs: expected \(20, 3\)"):
        view_outliers(fit.camera, obs, fit.rvecs, fit.tvecs[:, :2])
    with pytest.raises(ValueError, match="alpha"):
        residual_randomness(fit.camera, obs, fit.rvecs, fit.tvecs, (), alpha=2)
