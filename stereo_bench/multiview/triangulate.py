"""N-view triangulation of 3D points from pixels seen by calibrated cameras.

All functions take ``cameras`` (C ``Camera`` objects, cam_from_world) and ``pixels`` of shape
``(C, ..., 2)`` (OpenCV pixel centres, NaN = not seen), optionally ``weights`` ``(C, ...)``
(finite, >= 0; 0 = not seen), and return world points ``(..., 3)`` in mm, NaN where fewer than two
views remain. Weights scale each view's residual, so its cost is ``sum_c (w_c r_c)^2`` in every
method. Pixels are unprojected exactly with ``Camera.unproject`` (Newton to 1e-10 px): OpenCV's
``undistortPoints`` with default criteria is off by up to 1 px on a wide-angle lens (TRAPS.md).
Every observed pixel must therefore be invertible through its camera; mask the others with NaN.

* :func:`triangulate_dlt` — the linear (DLT) system of Hartley & Zisserman, *Multiple View
  Geometry*, 2nd ed., Sec. 12.2, on undistorted normalized points. Each row ``x P3 - P1`` is scaled
  by ``w fx / |x r3 - r1|`` (``fy`` for the y row): ``/ |.|`` turns its residual into the distance
  (mm) from the point to the plane through the camera centre that images the line ``x = const``,
  and ``fx`` turns that into about depth x pixel error, so that a 3000 px and a 600 px focal
  length are weighted by their pixel noise rather than equally (on the paper's mixed pair this
  brings the DLT's reprojection error from 2.5x to within 0.1 % of the optimum's).
  It is solved in the inhomogeneous form ``X = (x, y, z, 1)`` through the
  3x3 normal equations ("Linear-LS" of Hartley & Sturm, "Triangulation", CVIU 1997): that form
  is affine invariant (the SVD "Linear-Eigen" form is not even invariant to moving the world
  origin, which shifts its answer unless the world frame is conditioned first), and a batched
  closed 3x3 solve is several times faster than ``np.linalg.svd`` on ``(M, 2C, 4)`` (see
  benchmarks/triangulation_speed.py). Squaring the condition number costs nothing measurable
  here: the 3x3 systems of real rigs have condition numbers below ~1e4.
* :func:`triangulate_midpoint` — the point closest to all rays in the least-squares sense
  (generalized midpoint; Hartley & Sturm 1997, Sec. 5.3), a 3x3 solve as well.
* :func:`refine_points` — minimizes the reprojection error (the maximum-likelihood estimate under
  Gaussian pixel noise) per point by Gauss-Newton with Levenberg-Marquardt damping, vectorized
  across points, with the analytic point Jacobians of ``camera.project_with_jacobians`` and an
  optional robust loss (Huber or Cauchy on each view's pixel error).
* :func:`triangulate_robust` — greedy leave-one-view-out outlier rejection (below).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from ..core.camera import Camera, project_with_jacobians

LOSSES = ("linear", "huber", "cauchy")
_BLOCK = 1 << 13  # points per block of the DLT
METHODS = ("dlt", "midpoint", "refined", "robust")


# ----------------------------------------------------------------------------------------------
# Input handling
# ----------------------------------------------------------------------------------------------

def _flatten(cameras: Sequence[Camera], pixels, weights):
    """-> pixels (C, P, 2), weights (C, P) with 0 wherever unseen, batch shape (...)."""
    uv = np.asarray(pixels, dtype=np.float64)
    C = len(cameras)
    if uv.ndim < 2 or uv.shape[0] != C or uv.shape[-1] != 2:
        raise ValueError(f"pixels: expected shape (C={C}, ..., 2), got {uv.shape}")
    shape = uv.shape[1:-1]
    uv = uv.reshape(C, -1, 2)
    if weights is None:
        w = np.ones(uv.shape[:2])
    else:
        w = np.asarray(weights, dtype=np.float64)
        if w.shape != (C,) + shape:
            raise ValueError(f"weights: expected shape {(C,) + shape}, got {w.shape}")
        if not np.all(np.isfinite(w) & (w >= 0)):
            raise ValueError("weights: expected finite values >= 0 (0 = not seen)")
        w = w.reshape(C, -1)
    w = np.where(np.isfinite(uv[..., 0]) & np.isfinite(uv[..., 1]), w, 0.0)
    return uv, w, shape


def _unproject(cameras: Sequence[Camera], uv: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Undistorted normalized coordinates (C, P, 2) of the seen pixels; 0 elsewhere (weight 0)."""
    xy = np.empty(uv.shape)
    for c, cam in enumerate(cameras):
        # Unseen pixels become the principal point, whose ray is exactly (0, 0) (Newton's start)
        # and has weight 0: cheaper than gathering the seen pixels and scattering their rays.
        xy[c] = cam.unproject(np.where((w[c] > 0)[:, None], uv[c], (cam.cx, cam.cy)))
    return xy


def _solve3(A: np.ndarray, b: np.ndarray, usable: np.ndarray) -> np.ndarray:
    """Solve the symmetric 3x3 systems A X = b, given as the 6 entries (A00, A01, A02, A11,
    A12, A22) each (P,) and b (3, P); -> (P, 3), NaN where unusable or singular.

    Singular: all rays parallel (e.g. one camera seen twice), detected by det(A) relative to
    the cube of its mean eigenvalue. Cramer's rule with the adjugate, written out: a batched
    np.linalg.solve of (P, 3, 3) costs several times more, and for these symmetric positive
    definite systems (condition numbers below ~1e4) the adjugate loses nothing measurable.
    """
    a00, a01, a02, a11, a12, a22 = A
    c00, c01, c02 = a11 * a22 - a12 * a12, a02 * a12 - a01 * a22, a01 * a12 - a02 * a11
    c11, c12, c22 = a00 * a22 - a02 * a02, a01 * a02 - a00 * a12, a00 * a11 - a01 * a01
    det = a00 * c00 + a01 * c01 + a02 * c02
    scale = (a00 + a11 + a22) / 3
    ok = usable & (det > 1e-12 * scale**3)
    inv = np.where(ok, 1.0, np.nan) / np.where(ok, det, 1.0)
    X = np.empty((len(det), 3))
    X[:, 0] = (c00 * b[0] + c01 * b[1] + c02 * b[2]) * inv
    X[:, 1] = (c01 * b[0] + c11 * b[1] + c12 * b[2]) * inv
    X[:, 2] = (c02 * b[0] + c12 * b[1] + c22 * b[2]) * inv
    return X


_UPPER = ([0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2])  # the 6 entries of a symmetric 3x3 matrix


# ----------------------------------------------------------------------------------------------
# Linear methods
# ----------------------------------------------------------------------------------------------

def _dlt_matrices(cameras: Sequence[Camera]) -> np.ndarray:
    """(9, 6C) constant part of the DLT's normal equations: see :func:`_dlt`."""
    G = np.empty((len(cameras), 2, 3, 9))
    for c, cam in enumerate(cameras):
        R, t = cam.R, cam.tvec
        for i in (0, 1):
            # A and b = -sum s^2 a d, per coefficient: the x^2, x and 1 terms.
            G[c, i, 0] = np.r_[np.outer(R[2], R[2])[_UPPER], -R[2] * t[2]]
            cross = np.outer(R[2], R[i])
            G[c, i, 1] = np.r_[-(cross + cross.T)[_UPPER], R[2] * t[i] + R[i] * t[2]]
            G[c, i, 2] = np.r_[np.outer(R[i], R[i])[_UPPER], -R[i] * t[i]]
    return G.reshape(-1, 9).T


def _dlt(cameras: Sequence[Camera], xy: np.ndarray, w: np.ndarray, G=None) -> np.ndarray:
    """DLT on normalized coordinates xy (C, P, 2) with weights w (C, P) -> (P, 3).

    Row i of camera c is a = x_i R_2 - R_i (its rotation part) with right-hand side
    d = x_i t_2 - t_i, scaled by s = w f_i / |a|; since R is orthonormal |a|^2 = 1 + x_i^2, and
    s^2 a a^T = s^2 x_i^2 R_2 R_2^T - s^2 x_i (R_2 R_i^T + R_i R_2^T) + s^2 R_i R_i^T (likewise
    s^2 a d). So the normal equations are one product of per-point coefficients
    (s^2 x^2, s^2 x, s^2) with constant per-camera matrices: a (9, 6C) x (6C, P) BLAS product
    instead of 2C rounds of outer products. ``G``: :func:`_dlt_matrices` of the cameras.
    """
    C, P = xy.shape[:2]
    coef = np.empty((C, 2, 3, P))
    for c, cam in enumerate(cameras):
        w2 = w[c] * w[c]
        for i, f in ((0, cam.fx), (1, cam.fy)):
            x = xy[c, :, i]
            s2 = coef[c, i, 2]
            np.divide(w2 * (f * f), 1.0 + x * x, out=s2)
            np.multiply(s2, x, out=coef[c, i, 1])
            np.multiply(coef[c, i, 1], x, out=coef[c, i, 0])
    Ab = (_dlt_matrices(cameras) if G is None else G) @ coef.reshape(-1, P)
    return _solve3(Ab[:6], Ab[6:], np.count_nonzero(w > 0, axis=0) >= 2)


def triangulate_dlt(cameras: Sequence[Camera], pixels, weights=None) -> np.ndarray:
    """Linear triangulation, pixels (C, ..., 2) -> world points (..., 3); see the module notes."""
    uv, w, shape = _flatten(cameras, pixels, weights)
    G = _dlt_matrices(cameras)
    X = np.empty((uv.shape[1], 3))
    for a in range(0, len(X), _BLOCK):  # block by block, so that every pass stays in cache
        b = slice(a, a + _BLOCK)
        X[b] = _dlt(cameras, _unproject(cameras, uv[:, b], w[:, b]), w[:, b], G)
    return X.reshape(shape + (3,))


def triangulate_midpoint(cameras: Sequence[Camera], pixels, weights=None) -> np.ndarray:
    """The point minimizing sum_c (w_c * distance to ray c)^2, pixels (C, ..., 2) -> (..., 3)."""
    uv, w, shape = _flatten(cameras, pixels, weights)
    xy = _unproject(cameras, uv, w)
    P = xy.shape[1]
    A, b = np.zeros((P, 3, 3)), np.zeros((P, 3))
    for c, cam in enumerate(cameras):
        d = np.concatenate([xy[c], np.ones((P, 1))], -1) @ cam.R  # world ray directions R^T x
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        Q = np.eye(3) - d[:, :, None] * d[:, None, :]  # projector orthogonal to the ray
        Q *= (w[c] ** 2)[:, None, None]
        A += Q
        b += Q @ cam.center
    return _solve3(A[:, _UPPER[0], _UPPER[1]].T, b.T,
                   np.count_nonzero(w > 0, axis=0) >= 2).reshape(shape + (3,))


# ----------------------------------------------------------------------------------------------
# Reprojection error and nonlinear refinement
# ----------------------------------------------------------------------------------------------

def reprojection_errors(cameras: Sequence[Camera], points, pixels) -> np.ndarray:
    """Distance (px) between each observed pixel and its point's projection, (C, ...).

    NaN where the pixel or the point is NaN.
    """
    uv = np.asarray(pixels, dtype=np.float64)
    X = np.asarray(points, dtype=np.float64)
    if uv.shape[1:-1] != X.shape[:-1]:
        raise ValueError(f"points {X.shape} and pixels {uv.shape} disagree: expected "
                         f"points (..., 3) and pixels (C, ..., 2)")
    return np.stack([np.linalg.norm(cam.project(X) - uv[c], axis=-1)
                     for c, cam in enumerate(cameras)])


def _loss(e2: np.ndarray, loss: str, scale: float):
    """rho, rho' and rho'' of the loss at squared pixel errors e2 (scipy's least_squares forms)."""
    z = e2 / scale**2
    if loss == "linear":
        return e2, np.ones_like(e2), np.zeros_like(e2)
    if loss == "huber":
        big = z > 1
        sz = np.sqrt(np.where(big, z, 1.0))
        return (scale**2 * np.where(big, 2 * sz - 1, z), np.where(big, 1 / sz, 1.0),
                np.where(big, -0.5 / sz**3, 0.0) / scale**2)
    return scale**2 * np.log1p(z), 1 / (1 + z), -1 / (1 + z) ** 2 / scale**2  # cauchy


def refine_points(
    cameras: Sequence[Camera],
    pixels,
    points,
    weights=None,
    loss: str = "linear",
    loss_scale_px: float = 2.0,
    max_iterations: int = 30,
    xtol_mm: float = 1e-12,
) -> np.ndarray:
    """Minimize sum_c w_c^2 rho(|project_c(X) - uv_c|^2) per point, starting from ``points``.

    pixels (C, ..., 2), points (..., 3) -> refined (..., 3); NaN where fewer than two views or
    no finite start. ``loss`` is 'linear' (least squares), 'huber' or 'cauchy' with the inlier
    scale ``loss_scale_px``, applied to each view's pixel error |r_c|. Each point runs its own
    Levenberg-Marquardt (Marquardt's diagonal scaling, step accepted only if the cost falls, so
    a poor start cannot diverge) until its step is below ``xtol_mm * (1 + |X|)``.
    """
    if loss not in LOSSES:
        raise ValueError(f"loss: expected one of {LOSSES}, got {loss!r}")
    uv, w, shape = _flatten(cameras, pixels, weights)
    X = np.array(points, dtype=np.float64).reshape(-1, 3)
    if X.shape[0] != uv.shape[1]:
        raise ValueError(f"points: expected shape {shape + (3,)}, got {np.shape(points)}")
    usable = (np.count_nonzero(w > 0, axis=0) >= 2) & np.all(np.isfinite(X), axis=1)
    X[~usable] = np.nan

    def evaluate(idx, Xs):
        """Cost (K,), gradient (K,3) and Gauss-Newton matrix (K,3,3) at points Xs of idx."""
        cost, g, H = np.zeros(len(idx)), np.zeros((len(idx), 3)), np.zeros((len(idx), 3, 3))
        for c, cam in enumerate(cameras):
            proj, jac = project_with_jacobians(Xs, cam.intrinsics, cam.dist, cam.rvec, cam.tvec,
                                                model=cam.model)
            wc = w[c, idx]
            r = np.where(wc[:, None] > 0, proj - uv[c, idx], 0.0)
            e2 = np.sum(r * r, axis=-1)
            rho, d1, d2 = _loss(e2, loss, loss_scale_px)
            J = jac["point"]
            Jr = np.einsum("kij,ki->kj", J, r)
            # Hessian of rho(|r|^2) (Gauss-Newton in r): J^T (rho' I + 2 rho'' r r^T) J, with
            # the curvature along r clipped at 0 as scipy does (Triggs et al., "Bundle
            # adjustment - a modern synthesis", 2000, robustified least squares): IRLS alone
            # (rho' only) converges only linearly in Huber's flat valleys.
            curv = np.maximum(2 * d2, -d1 / np.maximum(e2, 1e-300))
            cost += wc**2 * rho
            g += (wc**2 * d1)[:, None] * Jr
            H += ((wc**2 * d1)[:, None, None] * np.einsum("kij,kil->kjl", J, J)
                  + (wc**2 * curv)[:, None, None] * Jr[:, :, None] * Jr[:, None, :])
        return cost, g, H

    idx = np.flatnonzero(usable)
    cost, g, H = evaluate(idx, X[idx])
    lam = np.full(len(idx), 1e-4)
    for _ in range(max_iterations):
        if len(idx) == 0:
            break
        D = np.diagonal(H, axis1=1, axis2=2)
        A = H + lam[:, None, None] * D[:, None, :] * np.eye(3)
        # A point whose views give no curvature along some direction (a camera that projects
        # it with a zero Jacobian) has no step to take: it stays where the DLT put it, and the
        # others go on (one singular system would otherwise fail the whole batch).
        solvable = np.abs(np.linalg.det(A)) > 0
        if not solvable.all():
            idx, cost, g, H, lam, A = (a[solvable] for a in (idx, cost, g, H, lam, A))
            if len(idx) == 0:
                break
        step = -np.linalg.solve(A, g[..., None])[..., 0]
        Xn = X[idx] + step
        cn, gn, Hn = evaluate(idx, Xn)
        # Accept ties at rounding level, so a point already at its optimum stops at once.
        better = cn <= cost * (1 + 1e-12)
        X[idx[better]] = Xn[better]
        cost = np.where(better, cn, cost)
        g = np.where(better[:, None], gn, g)
        H = np.where(better[:, None, None], Hn, H)
        lam = np.where(better, lam * 0.1, lam * 10)
        small = np.linalg.norm(step, axis=1) <= xtol_mm * (1 + np.linalg.norm(Xn, axis=1))
        # Done: converged, or the damping says no descent is left to find.
        keep = ~((better & small) | (lam > 1e8))
        idx, cost, g, H, lam = idx[keep], cost[keep], g[keep], H[keep], lam[keep]
    return X.reshape(shape + (3,))


# ----------------------------------------------------------------------------------------------
# Outlier rejection
# ----------------------------------------------------------------------------------------------

def triangulate_robust(
    cameras: Sequence[Camera],
    pixels,
    weights=None,
    threshold_px: float = 5.0,
    refine: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Triangulate while rejecting outlier views -> (points (..., 3), inlier views (C, ...) bool).

    Per point: triangulate (DLT) with all its views; while the largest reprojection error exceeds
    ``threshold_px`` and three or more views remain, drop one view: the one whose removal leaves
    the smallest largest reprojection error among the others (an outlier drags the DLT point
    towards itself, so the view with the largest error need not be the bad one). With two views
    left an outlier cannot be attributed: the point is kept with both, and its reprojection error
    (``reprojection_errors``) shows it. Finally the point is refined on its inliers (if
    ``refine``). At most C - 2 rounds of C DLT solves on the affected points; meant for small C.
    """
    uv, w, shape = _flatten(cameras, pixels, weights)
    xy = _unproject(cameras, uv, w)
    w = w.copy()

    def max_error(X, ww, idx):
        e = np.stack([np.linalg.norm(cam.project(X) - uv[c, idx], axis=-1)
                      for c, cam in enumerate(cameras)])
        return np.max(np.where(ww > 0, e, -np.inf), axis=0)

    X = _dlt(cameras, xy, w)
    idx = np.flatnonzero(np.count_nonzero(w > 0, axis=0) >= 3)
    for _ in range(len(cameras) - 2):
        idx = idx[max_error(X[idx], w[:, idx], idx) > threshold_px]
        if len(idx) == 0:
            break
        trials = np.full((len(cameras), len(idx)), np.inf)
        for v in range(len(cameras)):
            wv = w[:, idx].copy()
            wv[v] = 0
            err = max_error(_dlt(cameras, xy[:, idx], wv), wv, idx)
            trials[v] = np.where((w[v, idx] > 0) & ~np.isnan(err), err, np.inf)  # NaN: degenerate
        w[np.argmin(trials, axis=0), idx] = 0
        X[idx] = _dlt(cameras, xy[:, idx], w[:, idx])
        idx = idx[np.count_nonzero(w[:, idx] > 0, axis=0) >= 3]
    if refine:
        X = refine_points(cameras, uv, X, w)
    return X.reshape(shape + (3,)), (w > 0).reshape((len(cameras),) + shape)


def triangulate(cameras: Sequence[Camera], pixels, weights=None, method: str = "refined",
                **options) -> np.ndarray:
    """Triangulate with one of METHODS by name: 'dlt', 'midpoint', 'refined' (DLT, then
    :func:`refine_points` with ``options``) or 'robust' (:func:`triangulate_robust`'s points)."""
    if method == "dlt":
        return triangulate_dlt(cameras, pixels, weights)
    if method == "midpoint":
        return triangulate_midpoint(cameras, pixels, weights)
    if method == "refined":
        return refine_points(cameras, pixels, triangulate_dlt(cameras, pixels, weights), weights,
                             **options)
    if method == "robust":
        return triangulate_robust(cameras, pixels, weights, **options)[0]
    raise ValueError(f"method: expected one of {METHODS}, got {method!r}")
