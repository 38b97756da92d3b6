"""Plane-to-image homographies: the first step of Zhang's and Bouguet's calibrations.

Normalized DLT (Hartley & Zisserman, "Multiple View Geometry", 2nd ed., algorithm 4.2: translate
each point set to its centroid and scale its mean distance to sqrt(2), solve A h = 0 by SVD,
undo the normalization), then the maximum-likelihood refinement of Zhang 2000, Appendix A:
minimize the reprojection error in the image over the 8 free entries of H (Levenberg-Marquardt).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares


def apply_homography(H: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Map points (N, 2) through H (3, 3)."""
    p = np.asarray(xy, dtype=np.float64) @ H[:, :2].T + H[:, 2]
    return p[:, :2] / p[:, 2:]


def _normalizing_transform(xy: np.ndarray) -> np.ndarray:
    """Similarity taking the points to centroid 0 and mean distance sqrt(2) (Hartley)."""
    c = xy.mean(axis=0)
    s = np.sqrt(2.0) / np.mean(np.linalg.norm(xy - c, axis=1))
    return np.array([[s, 0.0, -s * c[0]], [0.0, s, -s * c[1]], [0.0, 0.0, 1.0]])


def _dlt(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    x, y = src[:, 0], src[:, 1]
    u, v = dst[:, 0], dst[:, 1]
    one, zero = np.ones_like(x), np.zeros_like(x)
    A = np.concatenate([
        np.stack([x, y, one, zero, zero, zero, -u * x, -u * y, -u], -1),
        np.stack([zero, zero, zero, x, y, one, -v * x, -v * y, -v], -1),
    ])
    return np.linalg.svd(A, full_matrices=False)[2][-1].reshape(3, 3)


def _refine(H: np.ndarray, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Zhang's Appendix A: least squares on image residuals, H[2, 2] fixed at 1 (the gauge)."""
    X = np.column_stack([src, np.ones(len(src))])

    def residuals(h):
        Hh = np.append(h, 1.0).reshape(3, 3)
        return (apply_homography(Hh, src) - dst).ravel()

    def jacobian(h):
        Hh = np.append(h, 1.0).reshape(3, 3)
        w = X @ Hh[2]
        uv = (X @ Hh[:2].T) / w[:, None]
        J = np.zeros((len(src), 2, 8))
        J[:, 0, 0:3] = X / w[:, None]
        J[:, 1, 3:6] = X / w[:, None]
        J[:, :, 6:8] = -uv[:, :, None] * (X[:, None, :2] / w[:, None, None])
        return J.reshape(-1, 8)

    h = least_squares(residuals, (H / H[2, 2]).ravel()[:8], jac=jacobian, method="lm",
                      x_scale="jac", xtol=1e-15, ftol=1e-15, gtol=1e-15).x
    return np.append(h, 1.0).reshape(3, 3)


def fit_homography(src: np.ndarray, dst: np.ndarray, refine: bool = True) -> np.ndarray:
    """H (3, 3), H[2, 2] = 1, with dst ~ H src, from N >= 4 correspondences (N, 2).

    For a board seen by a camera, H ~ K [r1 r2 t] and H[2, 2] ~ t_z: the positive gauge is also the
    sign that puts the board origin in front of the camera.

    The refinement runs in Hartley-normalized coordinates: the image normalization is a
    similarity, so the least-squares problem is the same up to a constant factor, and the eight
    entries of H get comparable scales.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 2 or len(src) < 4:
        raise ValueError(f"fit_homography: expected two (N, 2) arrays with N >= 4, got "
                         f"{src.shape} and {dst.shape}")
    Ts, Td = _normalizing_transform(src), _normalizing_transform(dst)
    src_n, dst_n = apply_homography(Ts, src), apply_homography(Td, dst)
    Hn = _dlt(src_n, dst_n)
    if refine:
        Hn = _refine(Hn, src_n, dst_n)
    H = np.linalg.inv(Td) @ Hn @ Ts
    return H / H[2, 2]
