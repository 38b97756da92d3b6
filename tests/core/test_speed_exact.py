"""The fast unprojection and DLT against straightforward references computed here."""

import numpy as np
import pytest

from stereo_bench.core.camera import Camera
from stereo_bench.core.distortion import distort_with_jacobians, undistort_normalized
from stereo_bench.multiview.triangulate import triangulate_dlt, triangulate_midpoint

RECTILINEAR = Camera("rect", 4096, 3072, 3000, 3000, 2048, 1536, 0,
                     [0.05, 0.02, 0.001, 0, 0, 0, 0, 0])
WIDE = Camera("wide", 640, 480, 600, 450, 320, 240, 0, [0.5, 0.1, 0.03, 0, 0, 0, 0, 0])
RATIONAL = Camera("rational", 1920, 1080, 1000, 1010, 950, 545, 0.5,
                  [0.1, -0.05, 0.002, -0.001, 0.01, 0.05, 0.01, 0.002])


def reference_unproject(cam, uv, iterations=60):
    """Plain Newton from the distorted point, np.linalg.solve on the generic Jacobian."""
    xd = cam.pixels_to_distorted_normalized(uv)
    xy = xd.copy()
    for _ in range(iterations):
        f, J, _ = distort_with_jacobians(xy, cam.dist, wrt_dist=False)
        step = np.linalg.solve(J, (f - xd)[..., None])[..., 0]
        n = np.linalg.norm(step, axis=-1, keepdims=True)
        lim = 0.5 * (1 + np.linalg.norm(xy, axis=-1, keepdims=True))
        xy = xy - np.where(n > lim, step * lim / np.maximum(n, 1e-300), step)
    return xy


@pytest.mark.parametrize("cam", [RECTILINEAR, WIDE, RATIONAL], ids=lambda c: c.name)
def test_unproject_matches_reference_newton(cam):
    rng = np.random.default_rng(0)
    uv = rng.uniform([-1, -1], [cam.width, cam.height], (30000, 2))
    xy = cam.unproject(uv)
    ref = reference_unproject(cam, uv)
    # Both solve the same equation to 1e-10 px: they agree to that over the focal length.
    assert np.abs(xy - ref).max() < 2e-10 / min(cam.fx, cam.fy)
    assert np.abs(cam.normalized_to_pixels(xy) - uv).max() < 1e-10


def test_unproject_does_not_depend_on_the_batch():
    rng = np.random.default_rng(1)
    uv = rng.uniform([0, 0], [WIDE.width, WIDE.height], (20000, 2))
    together = WIDE.unproject(uv)
    for k in (0, 1, 8191, 8192, 19999):
        assert np.array_equal(WIDE.unproject(uv[k:k + 1])[0], together[k])
    assert np.array_equal(WIDE.unproject(uv[::-1]), together[::-1])


def test_undistort_flags_non_finite_and_folded_points():
    cam = Camera("fold", 1000, 800, 300, 300, 500, 400, 0, [-0.4, 0, 0, 0, 0, 0, 0, 0])
    xd = cam.pixels_to_distorted_normalized(np.array([[500, 400], [600, 450], [np.nan, 3.0]]))
    xy, ok = undistort_normalized(xd, cam.dist, tol=1e-14)
    assert ok[0] and ok[1] and not ok[2]
    assert np.all(np.isnan(xy[2]))
    assert np.abs(distort_with_jacobians(xy[:2], cam.dist)[0] - xd[:2]).max() < 1e-14
    # The radial map r (1 - 0.4 r^2) peaks at rd = 0.608 (r = 1/sqrt(1.2)): the pixel at
    # rd = 0.667 has no ray, the one at rd = 0.6 has exactly one.
    assert not cam.invertible(np.array([700.0, 400.0]))
    assert cam.invertible(np.array([680.0, 400.0]))


def ring(n=4):
    from stereo_bench.core.poses import look_at_rotation, matrix_to_rodrigues
    cams = []
    for k in range(n):
        a = 2 * np.pi * k / n
        pos = np.array([3000 * np.cos(a), 3000 * np.sin(a), 900.0 + 100 * k])
        R = look_at_rotation(pos, np.array([0, 0, 900.0]), np.array([0, 0, 1.0]))
        base = (RECTILINEAR, WIDE, RATIONAL, WIDE)[k % 4]
        cams.append(base.with_params(rvec=matrix_to_rodrigues(R), tvec=-R @ pos))
    return cams


def reference_dlt(cams, uv, w):
    """Hartley & Zisserman's weighted DLT rows, explicit outer products and np.linalg.solve."""
    P = uv.shape[1]
    A, b = np.zeros((P, 3, 3)), np.zeros((P, 3))
    for c, cam in enumerate(cams):
        seen = w[c] > 0
        xy = np.zeros((P, 2))
        xy[seen] = cam.unproject(uv[c, seen])
        for i, f in ((0, cam.fx), (1, cam.fy)):
            a = xy[:, i, None] * cam.R[2] - cam.R[i]
            d = xy[:, i] * cam.tvec[2] - cam.tvec[i]
            s = w[c] * f / np.linalg.norm(a, axis=-1)
            a, d = a * s[:, None], d * s
            A += a[:, :, None] * a[:, None, :]
            b -= a * d[:, None]
    X = np.full((P, 3), np.nan)
    two = np.count_nonzero(w > 0, axis=0) >= 2
    X[two] = np.linalg.solve(A[two], b[two][..., None])[..., 0]
    return X


def test_dlt_matches_reference_with_weights_and_missing_views():
    rng = np.random.default_rng(2)
    cams = ring()
    X = rng.uniform([-500, -500, 200], [500, 500, 1600], (20000, 3))
    uv = np.stack([cam.project(X) for cam in cams]) + rng.normal(0, 0.7, (4, len(X), 2))
    w = rng.uniform(0.2, 2.0, (4, len(X)))
    drop = rng.random((4, len(X))) < 0.2
    uv[drop] = np.nan
    w[drop] = 0
    two = np.count_nonzero(~drop, axis=0) >= 2
    ours = triangulate_dlt(cams, uv, w)
    ref = reference_dlt(cams, np.nan_to_num(uv), w)
    assert np.array_equal(np.isnan(ours[:, 0]), ~two)
    assert np.abs(ours[two] - ref[two]).max() < 1e-8 * np.abs(ref[two]).max()


def test_closed_form_solve_flags_parallel_rays():
    cam = ring(1)[0]
    X = np.array([[0.0, 0, 900], [100, 50, 1000]])
    uv = np.stack([cam.project(X), cam.project(X)])  # one camera twice: parallel rays
    for method in (triangulate_dlt, triangulate_midpoint):
        assert np.all(np.isnan(method([cam, cam], uv)))
