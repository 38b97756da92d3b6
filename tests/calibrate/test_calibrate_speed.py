"""The batched pieces that make calibration fast, against their one-view-at-a-time definitions,
OpenCV and finite differences: the homographies of all views at once (views of different point
counts padded), the per-view blocks of the normal equations, the left-increment rotation
Jacobian of the iterations, and the stopping rule at the cost's floor."""

import cv2
import numpy as np

from stereo_bench.calibrate.homography import apply_homography, fit_homographies, fit_homography
from stereo_bench.calibrate.refine import CameraModel, _Problem, _schur, free_mask, refine
from stereo_bench.core.camera import Camera
from stereo_bench.core.poses import rodrigues_to_matrix, matrix_to_rodrigues

from test_calibrate import synthetic_views

RECT = Camera("rect", 4096, 3072, 3000, 3000, 2048, 1536, 0, [0.05, 0.02, 0.001])
MODEL = CameraModel()


def uneven_views(n_views=12, sigma=0.5, seed=3):
    """Views of the 8 x 11 board with 20..88 of its points each, plus pixel noise."""
    rng = np.random.default_rng(seed)
    board, rvecs, tvecs = synthetic_views(RECT, n_views, rng)
    obj, img = [], []
    for k, (r, t) in enumerate(zip(rvecs, tvecs)):
        keep = np.sort(rng.choice(len(board), 20 + (k * 7) % 69, replace=False))
        uv = RECT.with_params(rvec=r, tvec=t).project(board[keep])
        obj.append(board[keep])
        img.append(uv + rng.normal(0.0, sigma, uv.shape))
    return obj, img, rvecs, tvecs


def test_batched_homographies_are_the_single_view_fits_and_opencvs():
    obj, img, _, _ = uneven_views()
    H = fit_homographies([o[:, :2] for o in obj], img)
    for o, p, h in zip(obj, img, H):
        one = fit_homography(o[:, :2], p)
        assert np.abs(h - one).max() < 1e-9 * np.abs(one).max()
        # cv2.findHomography (method 0: least squares, then Levenberg-Marquardt on the
        # reprojection error in the image) seeks the same minimum.
        ref, _ = cv2.findHomography(o[:, :2], p, 0)
        cost = lambda G: np.sum((apply_homography(G, o[:, :2]) - p) ** 2)
        assert cost(h) <= cost(ref) * (1 + 1e-9)
        assert np.abs(apply_homography(h, o[:, :2]) - apply_homography(ref, o[:, :2])).max() < 1e-3


def test_per_view_blocks_of_the_normal_equations_are_those_of_the_dense_jacobian():
    obj, img, rvecs, tvecs = uneven_views(n_views=5)
    problem = _Problem(MODEL, free_mask(MODEL.param_names, ("fx", "fy", "cx", "cy", "k1")),
                       obj, img)
    r, Ja, Jb = problem.residuals(MODEL.params_of(RECT), rvecs, tvecs, jacobians=True)
    U, V, W, ga, gb = problem.normal_equations(r, Ja, Jb)
    F, n = Ja.shape[-1], len(r)
    J = np.zeros((2 * n, F + 6 * len(obj)))
    J[:, :F] = Ja.reshape(2 * n, F)
    for v, (a, b) in enumerate(problem.bounds):
        J[2 * a:2 * b, F + 6 * v:F + 6 * v + 6] = Jb[a:b].reshape(-1, 6)
    JtJ, g = J.T @ J, J.T @ r.ravel()
    scale = np.abs(JtJ).max()
    assert np.abs(U - JtJ[:F, :F]).max() < 1e-12 * scale
    for v in range(len(obj)):
        block = slice(F + 6 * v, F + 6 * v + 6)
        assert np.abs(V[v] - JtJ[block, block]).max() < 1e-12 * scale
        assert np.abs(W[v] - JtJ[:F, block]).max() < 1e-12 * scale
        assert np.abs(gb[v] - g[block]).max() < 1e-12 * np.abs(g).max()
    assert np.abs(ga - g[:F]).max() < 1e-12 * np.abs(g).max()


def test_left_increment_jacobian_matches_finite_differences_and_keeps_the_schur_complement():
    obj, img, rvecs, tvecs = uneven_views(n_views=3)
    problem = _Problem(MODEL, np.ones(13, bool), obj, img)
    params = MODEL.params_of(RECT)
    r, Ja, Jb = problem.local_residuals(params, rvecs, tvecs)
    h = 1e-7
    R = rodrigues_to_matrix(rvecs)
    for j in range(3):
        w = np.zeros((3, 3))
        w[:, j] = h
        step = lambda s: problem.residuals(
            params, matrix_to_rodrigues(rodrigues_to_matrix(s * w) @ R), tvecs)
        fd = (step(1.0) - step(-1.0)) / (2 * h)
        assert np.abs(fd - Jb[:, :, j]).max() < 1e-6 * np.abs(fd).max(), j
    # Marginalizing the poses gives the same information on the intrinsics in either
    # parametrization of the rotations (so refine's param_std is what linearize's gives).
    S_local = _schur(*problem.normal_equations(r, Ja, Jb)[:3])[0]
    S_rvec = _schur(*problem.normal_equations(*problem.residuals(params, rvecs, tvecs, True))[:3])[0]
    d = np.sqrt(np.diag(S_rvec))
    assert np.abs((S_local - S_rvec) / np.outer(d, d)).max() < 1e-9


class CountingModel(CameraModel):
    def __init__(self):
        super().__init__()
        self.calls = 0

    def project(self, params, points_cam, jacobians=True):
        self.calls += 1
        return super().project(params, points_cam, jacobians)


def test_refine_stops_at_the_cost_floor_without_raising_the_damping_to_its_limit():
    """Once the cost is at its floating-point floor, the linear model predicts no decrease that
    rounding would let one see, and refine stops after one rejected trial: it used to raise the
    damping 10x per rejected trial up to 1e16, ~30 projections more. The point it stops at is a
    minimum: every column of the Jacobian is orthogonal to the residuals to 1e-7 (cosine)."""
    rng = np.random.default_rng(5)
    board, rvecs, tvecs = synthetic_views(RECT, 10, rng)
    img = [RECT.with_params(rvec=r, tvec=t).project(board) + rng.normal(0.0, 0.3, board[:, :2].shape)
           for r, t in zip(rvecs, tvecs)]
    model = CountingModel()
    free = free_mask(model.param_names, ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"))
    start = MODEL.params_of(RECT) * (1 + np.r_[2e-3, -2e-3, 1e-3, 1e-3, 0, 0.05, 0.05, 0.05,
                                                np.zeros(5)])
    res = refine(model, start, free, [board] * 10, img, rvecs + 1e-3, tvecs * 1.001, xtol=0.0)
    assert res.stop_reason == "no decrease (cost at its floor)"
    assert model.calls <= 2 * res.iterations + 2, (model.calls, res.iterations)
    problem = _Problem(MODEL, free, [board] * 10, img)
    r, Ja, Jb = problem.residuals(res.params, res.rvecs, res.tvecs, jacobians=True)
    U, V, _, ga, gb = problem.normal_equations(r, Ja, Jb)
    cosine = (np.r_[ga, gb.ravel()] / np.sqrt(np.r_[np.diag(U), V.diagonal(0, 1, 2).ravel()])
              / np.linalg.norm(r))
    assert np.abs(cosine).max() < 1e-7
