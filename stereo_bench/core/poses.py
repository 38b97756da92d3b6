"""Rotations and rigid transforms: Rodrigues vectors and matrices, their Jacobians, the look-at
rotation, composition and inversion of (R, t) pairs (named target_from_source, DESIGN.md) and
each camera's pose relative to a rig's first camera.
"""

from __future__ import annotations


import numpy as np


def skew_matrix(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices [v]x for v of shape (..., 3) -> (..., 3, 3)."""
    v = np.asarray(v, dtype=np.float64)
    z = np.zeros(v.shape[:-1])
    return np.stack(
        [
            np.stack([z, -v[..., 2], v[..., 1]], -1),
            np.stack([v[..., 2], z, -v[..., 0]], -1),
            np.stack([-v[..., 1], v[..., 0], z], -1),
        ],
        -2,
    )


def rodrigues_to_matrix(rvec: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) from Rodrigues vectors (..., 3) (exponential map)."""
    rvec = np.asarray(rvec, dtype=np.float64)
    theta = np.linalg.norm(rvec, axis=-1)[..., None, None]
    K = skew_matrix(rvec)
    small = theta < 1e-8
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    return np.eye(3) + a * K + b * (K @ K)


def matrix_to_rodrigues(R: np.ndarray) -> np.ndarray:
    """Rodrigues vectors (..., 3) from rotation matrices (..., 3, 3) (logarithm map).

    Uses the quaternion route, which is accurate near 0 and near pi alike.
    """
    R = np.asarray(R, dtype=np.float64)
    tr = np.trace(R, axis1=-2, axis2=-1)
    # Shepperd's method: pick the largest of 4 candidate quaternion components.
    cand = np.stack([tr, R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]], -1)
    k = np.argmax(cand, axis=-1)
    q = np.empty(R.shape[:-2] + (4,))
    for i in range(4):
        m = k == i
        if not np.any(m):
            continue
        Rm = R[m]
        if i == 0:
            w = np.sqrt(np.maximum(1.0 + np.trace(Rm, axis1=-2, axis2=-1), 0.0)) / 2
            q[m] = np.stack([w, (Rm[:, 2, 1] - Rm[:, 1, 2]) / (4 * w),
                             (Rm[:, 0, 2] - Rm[:, 2, 0]) / (4 * w),
                             (Rm[:, 1, 0] - Rm[:, 0, 1]) / (4 * w)], -1)
        else:
            a, b, c = i - 1, i % 3, (i + 1) % 3
            s = np.sqrt(np.maximum(1.0 + Rm[:, a, a] - Rm[:, b, b] - Rm[:, c, c], 0.0)) * 2
            comp = np.empty((Rm.shape[0], 4))
            comp[:, 0] = (Rm[:, c, b] - Rm[:, b, c]) / s
            comp[:, 1 + a] = s / 4
            comp[:, 1 + b] = (Rm[:, b, a] + Rm[:, a, b]) / s
            comp[:, 1 + c] = (Rm[:, c, a] + Rm[:, a, c]) / s
            q[m] = comp
    q = q * np.where(q[..., :1] < 0, -1.0, 1.0)
    vn = np.linalg.norm(q[..., 1:], axis=-1)
    angle = 2 * np.arctan2(vn, q[..., 0])
    scale = np.where(vn < 1e-12, 2.0, angle / np.where(vn < 1e-12, 1.0, vn))
    return q[..., 1:] * scale[..., None]


def nearest_rotation(M: np.ndarray) -> np.ndarray:
    """The rotation closest to M (..., 3, 3) in the Frobenius norm (SVD projection onto SO(3))."""
    U, _, Vt = np.linalg.svd(M)
    D = np.ones(U.shape[:-1])
    D[..., 2] = np.sign(np.linalg.det(U @ Vt))
    return (U * D[..., None, :]) @ Vt


def geodesic_distance(Ra: np.ndarray, Rb: np.ndarray) -> np.ndarray:
    """Rotation angle (rad) of Ra^T Rb for rotation matrices (..., 3, 3); through the log map,
    which stays accurate for tiny angles where the arccos of the trace loses them."""
    return np.linalg.norm(matrix_to_rodrigues(np.swapaxes(Ra, -1, -2) @ Rb), axis=-1)


def rotate_jacobian(rvec: np.ndarray, points: np.ndarray) -> np.ndarray:
    """d(R(rvec) @ p)/d rvec, shape (N, 3, 3), for one rvec (3,) and points (N, 3).

    Gallego & Yezzi, "A compact formula for the derivative of a 3-D rotation in exponential
    coordinates", JMIV 2015, eq. (8): d(R u)/dv = -R [u]x (v v^T + (R^T - I)[v]x) / |v|^2.
    """
    v = np.asarray(rvec, dtype=np.float64)
    R = rodrigues_to_matrix(v)
    Ux = skew_matrix(points)
    th2 = float(v @ v)
    if th2 < 1e-16:
        return -Ux  # d(Ru)/dv at v = 0 is -[u]x
    M = (np.outer(v, v) + (R.T - np.eye(3)) @ skew_matrix(v)) / th2
    return -(R @ Ux) @ M


def look_at_rotation(position: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """cam_from_world rotation of a camera at ``position`` looking at ``target``.

    The optical axis (+z) points at the target and ``up`` (a world direction) appears upward in
    the image, i.e. along -y of the camera (OpenCV's y points down).
    """
    z = np.asarray(target, dtype=np.float64) - np.asarray(position, dtype=np.float64)
    if np.linalg.norm(z) == 0:
        raise ValueError("look_at: target equals position")
    z /= np.linalg.norm(z)
    y = -(np.asarray(up, dtype=np.float64) - (np.asarray(up) @ z) * z)
    if np.linalg.norm(y) < 1e-9:
        raise ValueError("look_at: up is parallel to the viewing direction")
    y /= np.linalg.norm(y)
    return np.stack([np.cross(y, z), y, z])


def view_toward(direction: np.ndarray) -> np.ndarray:
    """view_from_cam (3, 3): the rotation taking the direction (3,) (camera frame) to the optical
    axis, about their common normal. A wide lens's rays past 90 degrees have no normalized
    coordinates (x/z, y/z) in the camera's frame; in this view they have, near its axis."""
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    turn = np.cross([0.0, 0.0, 1.0], d)
    angle = np.arctan2(np.linalg.norm(turn), d[2])
    return rodrigues_to_matrix(turn / max(np.linalg.norm(turn), 1e-300) * angle).T


def compose(R_ab: np.ndarray, t_ab: np.ndarray, R_bc: np.ndarray, t_bc: np.ndarray):
    """a_from_c = a_from_b o b_from_c for (R, t) pairs."""
    return R_ab @ R_bc, R_ab @ t_bc + t_ab


def invert(R: np.ndarray, t: np.ndarray):
    """b_from_a from a_from_b given as (R, t)."""
    Rt = np.swapaxes(R, -1, -2)
    return Rt, -(Rt @ t[..., None])[..., 0]


def cam_from_cam0(cameras) -> tuple[np.ndarray, np.ndarray]:
    """Each camera's pose relative to the first, from their cam_from_world: (R (C,3,3), t (C,3))."""
    R = np.stack([cam.R for cam in cameras])
    t = np.stack([cam.tvec for cam in cameras])
    return compose(R, t, *invert(R[0], t[0]))
