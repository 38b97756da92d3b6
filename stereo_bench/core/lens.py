"""Lens models: how a ray in the camera frame becomes a point of the image plane, and back.

A camera is a lens model (a name and its parameters, ``Camera.model`` and ``Camera.dist``)
followed by the same affine map to pixels for every model, ``u = fx mx + skew my + cx``,
``v = fy my + cy``. Each model maps a camera-frame point P = (X, Y, Z) to image-plane
coordinates m = (mx, my), with its Jacobians over P and over its parameters, and maps m back to
the unit ray exactly; each says where it is valid (which rays it projects one to one and which
image-plane points have a ray), so a renderer paints the black surround of a circular fisheye
image and a metric never compares pixels a lens cannot see.

    opencv         OpenCV's pinhole model [k1, k2, p1, p2, k3, k4, k5, k6] on (X/Z, Y/Z)
                   (distortion.py); rays in front of the camera only, up to the radial fold.
    kannala_brandt Kannala & Brandt 2006 (OpenCV's cv2.fisheye, Kalibr's pinhole-equi, COLMAP's
                   OPENCV_FISHEYE) [k1, k2, k3, k4]: theta = angle to the axis,
                   theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8),
                   m = theta_d (X, Y) / sqrt(X^2 + Y^2); valid while theta_d increases, up to
                   180 degrees off axis (cv2.fisheye's atan(r) stops at 90).
    mei            Mei & Rives 2007, the unified omnidirectional model with radial-tangential
                   distortion (OpenCV's cv2.omnidir, Kalibr's omni-radtan) [xi, k1, k2, p1, p2]:
                   the unit ray (xs, ys, zs) projected from (0, 0, -xi) onto the plane z = 1,
                   then OpenCV's distortion with k1, k2, p1, p2.
    double_sphere  Usenko, Demmel & Cremers 2018 [xi, alpha]: two unit spheres xi apart, then
                   a projection from alpha / (1 - alpha) behind the second sphere's centre.

The model is data: every stage downstream projects and unprojects through ``Camera`` and never
asks which model it holds, except an exchange format, which says which models it carries.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from .distortion import distort_with_jacobians, radial_fold_radius, undistort_to

DIST_NAMES = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")


@dataclass(frozen=True)
class LensModel:
    """A lens model of the family: ``project(P (N,3), params, jacobians)`` -> (m (N,2), valid
    (N,), d m/d P (N,2,3), d m/d params (N,2,k)) (Jacobians None unless asked);
    ``unproject(m (N,2), params)`` -> (unit rays (N,3), valid (N,)); ``padded``: the parameter
    vector is padded with zeros to ``len(param_names)`` (OpenCV's model accepts 4, 5 or 8)."""

    name: str
    param_names: tuple[str, ...]
    project: Callable
    unproject: Callable
    description: str
    padded: bool = False


# ----------------------------------------------------------------------------------------------
# OpenCV's pinhole model (the distortion of distortion.py on X/Z, Y/Z)
# ----------------------------------------------------------------------------------------------

def _opencv_project(P, params, jacobians=True):
    Z = P[:, 2]
    valid = Z > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_z = 1.0 / Z
        xy = P[:, :2] * inv_z[:, None]
        m, Jxy, Jd = distort_with_jacobians(xy, params, wrt_dist=jacobians)
    valid &= np.linalg.norm(xy, axis=1) < radial_fold_radius(params)
    if not jacobians:
        return m, valid, None, None
    J = np.empty((len(P), 2, 3))
    J[:, :, 0] = Jxy[:, :, 0] * inv_z[:, None]
    J[:, :, 1] = Jxy[:, :, 1] * inv_z[:, None]
    J[:, :, 2] = -(J[:, :, 0] * xy[:, 0, None] + J[:, :, 1] * xy[:, 1, None])
    return m, valid, J, Jd


def _opencv_unproject(m, params):
    xy, ok = undistort_to(m, params, 1e-14, 50, None, radial_fold_radius(params))
    rays = np.concatenate([xy, np.ones((len(xy), 1))], 1)
    return rays / np.linalg.norm(rays, axis=1, keepdims=True), ok


# ----------------------------------------------------------------------------------------------
# Kannala-Brandt (OpenCV fisheye)
# ----------------------------------------------------------------------------------------------

def _kb_poly(theta, k):
    """theta_d and d theta_d / d theta."""
    t2 = theta * theta
    k1, k2, k3, k4 = k
    poly = 1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))
    slope = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
    return theta * poly, slope


@functools.lru_cache(maxsize=256)
def kb_max_theta(k: tuple) -> float:
    """Largest angle off axis (rad, at most pi) up to which theta_d increases strictly: the
    lens's field of view, beyond which a pixel would have two rays."""
    theta = np.linspace(0.0, math.pi, 100001)
    slope = _kb_poly(theta, k)[1]
    bad = np.flatnonzero(~(slope > 0))
    return float(theta[bad[0]]) if len(bad) else math.pi


def _kb_project(P, params, jacobians=True):
    k = tuple(float(c) for c in params)
    X, Y, Z = P[:, 0], P[:, 1], P[:, 2]
    r = np.hypot(X, Y)
    rho2 = r * r + Z * Z
    theta = np.arctan2(r, Z)
    td, slope = _kb_poly(theta, k)
    on_axis = r == 0
    r_safe = np.where(on_axis, 1.0, r)
    # g = theta_d / r; on the axis its limit is 1 / Z.
    g = np.where(on_axis, 1.0 / np.where(Z == 0, 1.0, Z), td / r_safe)
    m = np.stack([g * X, g * Y], -1)
    valid = (theta < kb_max_theta(k)) & (rho2 > 0)
    if not jacobians:
        return m, valid, None, None
    # d g / d X = X c with c = (theta_d' Z / rho^2 - g) / r^2; on the axis c's limit is
    # (2 k1 - 2/3) / Z^3 (series of theta = atan(r / Z)).
    with np.errstate(divide="ignore", invalid="ignore"):
        c = np.where(on_axis, (2 * k[0] - 2.0 / 3.0) / Z**3,
                     (slope * Z / rho2 - g) / (r_safe * r_safe))
    J = np.empty((len(P), 2, 3))
    J[:, 0, 0] = g + c * X * X
    J[:, 0, 1] = c * X * Y
    J[:, 1, 0] = J[:, 0, 1]
    J[:, 1, 1] = g + c * Y * Y
    J[:, 0, 2] = -X * slope / rho2
    J[:, 1, 2] = -Y * slope / rho2
    ux, uy = np.where(on_axis, 0.0, X / r_safe), np.where(on_axis, 0.0, Y / r_safe)
    Jk = np.empty((len(P), 2, 4))
    power = theta ** 3
    for i in range(4):
        Jk[:, 0, i], Jk[:, 1, i] = power * ux, power * uy
        power = power * theta * theta
    return m, valid, J, Jk


def _kb_unproject(m, params):
    k = tuple(float(c) for c in params)
    td = np.hypot(m[:, 0], m[:, 1])
    theta_max = kb_max_theta(k)
    td_max = _kb_poly(np.array(theta_max), k)[0]
    valid = td < td_max
    # Newton on theta_d(theta) = td, monotone on [0, theta_max]: from theta = td (exact for the
    # equidistant lens), kept inside the interval.
    theta = np.minimum(td, theta_max)
    for _ in range(50):
        f, slope = _kb_poly(theta, k)
        step = (f - td) / np.where(slope > 0, slope, 1.0)
        theta = np.clip(theta - step, 0.0, theta_max)
        if np.all(np.abs(step[valid]) < 1e-15 * (1 + theta[valid])):
            break
    f = _kb_poly(theta, k)[0]
    valid &= np.abs(f - td) < 1e-12 * (1 + td)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(td > 0, np.sin(theta) / td, 1.0)
    return np.stack([m[:, 0] * s, m[:, 1] * s, np.cos(theta)], -1), valid


# ----------------------------------------------------------------------------------------------
# Mei's unified omnidirectional model (OpenCV omnidir)
# ----------------------------------------------------------------------------------------------

def _radtan(params):
    """OpenCV's 8 coefficients holding Mei's k1, k2, p1, p2."""
    return np.concatenate([np.asarray(params[1:5], dtype=np.float64), np.zeros(4)])


def _mei_project(P, params, jacobians=True):
    xi = float(params[0])
    norm = np.linalg.norm(P, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        S = P / norm[:, None]
        w = S[:, 2] + xi
        xy = S[:, :2] / w[:, None]
        m, Jxy, Jd = distort_with_jacobians(xy, _radtan(params), wrt_dist=jacobians)
    # Seen once: the ray leaves the sphere towards the plane (zs > -xi, and for xi > 1 the
    # nearer of the two sphere points, zs > -1 / xi), inside the distortion's fold.
    valid = (norm > 0) & (S[:, 2] > -min(xi, 1.0 / xi if xi > 0 else math.inf))
    valid &= np.linalg.norm(xy, axis=1) < radial_fold_radius(_radtan(params))
    if not jacobians:
        return m, valid, None, None
    n = len(P)
    # d xy / d S, then d S / d P = (I - S S^T) / |P|.
    A = np.zeros((n, 2, 3))
    A[:, 0, 0] = 1 / w
    A[:, 1, 1] = 1 / w
    A[:, 0, 2] = -xy[:, 0] / w
    A[:, 1, 2] = -xy[:, 1] / w
    dS = (np.eye(3)[None] - S[:, :, None] * S[:, None, :]) / norm[:, None, None]
    J = Jxy @ (A @ dS)
    Jp = np.empty((n, 2, 5))
    Jp[:, :, 0] = (Jxy @ (-xy / w[:, None])[:, :, None])[:, :, 0]
    Jp[:, :, 1:] = Jd[:, :, :4]
    return m, valid, J, Jp


def _mei_unproject(m, params):
    xi = float(params[0])
    radtan = _radtan(params)
    xy, ok = undistort_to(m, radtan, 1e-14, 50, None, radial_fold_radius(radtan))
    r2 = np.sum(xy * xy, axis=1)
    disc = 1 + (1 - xi * xi) * r2
    ok &= disc >= 0
    eta = (xi + np.sqrt(np.maximum(disc, 0.0))) / (r2 + 1)
    rays = np.stack([eta * xy[:, 0], eta * xy[:, 1], eta - xi], -1)
    # The ray must come back to the same pixel (the nearer sphere point when xi > 1).
    ok &= rays[:, 2] > -min(xi, 1.0 / xi if xi > 0 else math.inf)
    return rays / np.linalg.norm(rays, axis=1, keepdims=True), ok


# ----------------------------------------------------------------------------------------------
# Double sphere
# ----------------------------------------------------------------------------------------------

def _ds_limit(xi, alpha):
    """w2 of Usenko et al. (eq. 43): a point is projected if Z > -w2 |P|."""
    w1 = alpha / (1 - alpha) if alpha <= 0.5 else (1 - alpha) / alpha
    return (w1 + xi) / math.sqrt(2 * w1 * xi + xi * xi + 1)


def _ds_project(P, params, jacobians=True):
    xi, alpha = (float(p) for p in params)
    X, Y, Z = P[:, 0], P[:, 1], P[:, 2]
    d1 = np.linalg.norm(P, axis=1)
    zeta = xi * d1 + Z
    d2 = np.sqrt(X * X + Y * Y + zeta * zeta)
    den = alpha * d2 + (1 - alpha) * zeta
    with np.errstate(divide="ignore", invalid="ignore"):
        m = np.stack([X / den, Y / den], -1)
    valid = (d1 > 0) & (Z > -_ds_limit(xi, alpha) * d1) & (den > 0)
    if not jacobians:
        return m, valid, None, None
    with np.errstate(divide="ignore", invalid="ignore"):
        dd1 = P / d1[:, None]
        dzeta = xi * dd1
        dzeta[:, 2] += 1
        dd2 = (np.stack([X, Y, np.zeros_like(X)], -1) + zeta[:, None] * dzeta) / d2[:, None]
        dden = alpha * dd2 + (1 - alpha) * dzeta
        inv = 1 / den
        J = -(m[:, :, None] * inv[:, None, None]) * dden[:, None, :]
        J[:, 0, 0] += inv
        J[:, 1, 1] += inv
        dden_xi = alpha * zeta * d1 / d2 + (1 - alpha) * d1
        dden_alpha = d2 - zeta
        Jp = np.stack([-m * (dden_xi * inv)[:, None], -m * (dden_alpha * inv)[:, None]], -1)
    return m, valid, J, Jp


def _ds_unproject(m, params):
    xi, alpha = (float(p) for p in params)
    r2 = np.sum(m * m, axis=1)
    inner = 1 - (2 * alpha - 1) * r2
    ok = inner >= 0
    mz = (1 - alpha * alpha * r2) / (alpha * np.sqrt(np.maximum(inner, 0.0)) + 1 - alpha)
    disc = mz * mz + (1 - xi * xi) * r2
    ok &= disc >= 0
    scale = (mz * xi + np.sqrt(np.maximum(disc, 0.0))) / (mz * mz + r2)
    rays = np.stack([scale * m[:, 0], scale * m[:, 1], scale * mz - xi], -1)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    ok &= rays[:, 2] > -_ds_limit(xi, alpha)
    return rays, ok


LENS_MODELS: dict[str, LensModel] = {
    "opencv": LensModel("opencv", DIST_NAMES, _opencv_project, _opencv_unproject,
                        "OpenCV pinhole, k1 k2 p1 p2 k3 k4 k5 k6", padded=True),
    "kannala_brandt": LensModel("kannala_brandt", ("k1", "k2", "k3", "k4"), _kb_project,
                                _kb_unproject, "Kannala-Brandt fisheye (cv2.fisheye), k1 k2 k3 k4"),
    "mei": LensModel("mei", ("xi", "k1", "k2", "p1", "p2"), _mei_project, _mei_unproject,
                     "Mei unified omnidirectional (cv2.omnidir), xi k1 k2 p1 p2"),
    "double_sphere": LensModel("double_sphere", ("xi", "alpha"), _ds_project, _ds_unproject,
                               "double sphere (Usenko 2018), xi alpha"),
}


def lens_model(name: str) -> LensModel:
    if name not in LENS_MODELS:
        raise ValueError(f"unknown lens model {name!r}; lens models: "
                         f"{', '.join(f'{m.name} ({m.description})' for m in LENS_MODELS.values())}")
    return LENS_MODELS[name]


def lens_parameters(name: str, values, where: str) -> np.ndarray:
    """The model's parameter vector from ``values`` (padded where the model allows), checked."""
    model = lens_model(name)
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    n = len(model.param_names)
    if v.size > n or (v.size < n and not model.padded):
        raise ValueError(f"{where}: the {name} lens has {n} parameters "
                         f"{list(model.param_names)}, got {v.size}")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{where}: lens parameters must be finite, got {v.tolist()}")
    if name == "mei" and not v[0] >= 0:
        raise ValueError(f"{where}: xi must be >= 0, got {v[0]}")
    if name == "double_sphere" and not -1 < v[0] < 1:  # the range Usenko et al. give
        raise ValueError(f"{where}: xi must lie in (-1, 1), got {v[0]}")
    if name == "double_sphere" and not 0 < v[1] < 1:
        raise ValueError(f"{where}: alpha must lie in (0, 1), got {v[1]}")
    return np.concatenate([v, np.zeros(n - v.size)])
