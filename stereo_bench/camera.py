"""The camera model: the single source of truth for projection in SynthCal.

Pinhole camera with OpenCV's distortion model and conventions:

* pixel coordinates put the centre of the top-left pixel at (0, 0);
* ``cam_from_world`` maps world points into the camera frame, ``p_cam = R @ p_world + t``,
  with ``R`` stored as a Rodrigues vector ``rvec`` and ``t`` as ``tvec`` (millimetres);
* distortion coefficients in OpenCV's order ``[k1, k2, p1, p2, k3, k4, k5, k6]``, applied to
  normalized undistorted coordinates (x, y) = (X/Z, Y/Z)::

      r2 = x^2 + y^2
      radial = (1 + k1 r2 + k2 r2^2 + k3 r2^3) / (1 + k4 r2 + k5 r2^2 + k6 r2^3)
      xd = x radial + 2 p1 x y + p2 (r2 + 2 x^2)
      yd = y radial + p1 (r2 + 2 y^2) + 2 p2 x y
      u = fx xd + skew yd + cx,   v = fy yd + cy

Every projection function has its analytic Jacobian beside it (tested against finite
differences). Unprojection inverts the distortion by Newton's method to 1e-10 px and refuses
distortions that are not invertible over the image (a fold of the radial map inside it).
"""

from __future__ import annotations

import functools
import math

from dataclasses import dataclass, field, replace

import numpy as np

from .rundir import read_json, write_json

DIST_NAMES = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
INTRINSIC_NAMES = ("fx", "fy", "cx", "cy", "skew")
POSE_NAMES = ("rx", "ry", "rz", "tx", "ty", "tz")


class DistortionNotInvertibleError(ValueError):
    """The distortion map folds over inside the image, so a pixel has no unique ray."""


# ----------------------------------------------------------------------------------------------
# Rotations (Rodrigues vectors)
# ----------------------------------------------------------------------------------------------

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


def compose(R_ab: np.ndarray, t_ab: np.ndarray, R_bc: np.ndarray, t_bc: np.ndarray):
    """a_from_c = a_from_b o b_from_c for (R, t) pairs."""
    return R_ab @ R_bc, R_ab @ t_bc + t_ab


def invert(R: np.ndarray, t: np.ndarray):
    """b_from_a from a_from_b given as (R, t)."""
    Rt = np.swapaxes(R, -1, -2)
    return Rt, -(Rt @ t[..., None])[..., 0]


# ----------------------------------------------------------------------------------------------
# Distortion
# ----------------------------------------------------------------------------------------------

def distort(xy: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Apply OpenCV distortion to normalized points (..., 2) -> distorted normalized (..., 2)."""
    return distort_with_jacobians(xy, dist, wrt_dist=False)[0]


def distort_with_jacobians(xy: np.ndarray, dist: np.ndarray, wrt_dist: bool = True):
    """Distort normalized points and return (xd (...,2), d xd/d xy (...,2,2), d xd/d dist
    (...,2,8) or None when ``wrt_dist`` is False, which Newton's unprojection does not need)."""
    xy = np.asarray(xy, dtype=np.float64)
    k1, k2, p1, p2, k3, k4, k5, k6 = np.asarray(dist, dtype=np.float64)
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    r4, r6 = r2 * r2, r2 * r2 * r2
    num = 1 + k1 * r2 + k2 * r4 + k3 * r6
    den = 1 + k4 * r2 + k5 * r4 + k6 * r6
    radial = num / den
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y

    dnum = k1 + 2 * k2 * r2 + 3 * k3 * r4
    dden = k4 + 2 * k5 * r2 + 3 * k6 * r4
    drad_dr2 = (dnum * den - num * dden) / (den * den)
    J = np.empty(xy.shape[:-1] + (2, 2))
    J[..., 0, 0] = radial + x * drad_dr2 * 2 * x + 2 * p1 * y + 6 * p2 * x
    J[..., 0, 1] = x * drad_dr2 * 2 * y + 2 * p1 * x + 2 * p2 * y
    J[..., 1, 0] = y * drad_dr2 * 2 * x + 2 * p1 * x + 2 * p2 * y
    J[..., 1, 1] = radial + y * drad_dr2 * 2 * y + 6 * p1 * y + 2 * p2 * x

    if not wrt_dist:
        return np.stack([xd, yd], -1), J, None
    Jd = np.zeros(xy.shape[:-1] + (2, 8))
    for i, rp in ((0, r2), (1, r4), (4, r6)):  # k1, k2, k3 enter the numerator
        Jd[..., 0, i] = x * rp / den
        Jd[..., 1, i] = y * rp / den
    for i, rp in ((5, r2), (6, r4), (7, r6)):  # k4, k5, k6 enter the denominator
        Jd[..., 0, i] = -x * radial * rp / den
        Jd[..., 1, i] = -y * radial * rp / den
    Jd[..., 0, 2] = 2 * x * y
    Jd[..., 1, 2] = r2 + 2 * y * y
    Jd[..., 0, 3] = r2 + 2 * x * x
    Jd[..., 1, 3] = 2 * x * y
    return np.stack([xd, yd], -1), J, Jd


def radial_fold_radius(dist: np.ndarray, r_max: float = 20.0) -> float:
    """Smallest undistorted radius where the radial map r -> r * radial(r) stops increasing.

    Beyond it the distortion folds back and pixels have more than one ray. Returns ``inf`` if
    the map increases up to ``r_max`` (normalized units; 20 is ~87 degrees off axis) and the
    radial factor stays positive. Cached per coefficients: every unprojection asks, and the
    scan over 200,001 radii took 13 ms (a studio's per-view poses called it thousands of times).
    """
    dist = tuple(float(d) for d in np.ravel(dist))
    if not all(map(math.isfinite, dist)):
        return 0.0  # no coefficients, no valid region (NaN never equals itself: no caching)
    return _radial_profile(dist, float(r_max))[0]


_START_BITS = 45  # float64 bits below the 7 top mantissa bits: 128 start nodes per octave
_START_LOW = float(2.0**-24)  # rd^2 of the first start node (the start there is 1 to 1e-8)


@functools.lru_cache(maxsize=128)
def _radial_profile(dist: tuple, r_max: float) -> tuple[float, int, np.ndarray, np.ndarray]:
    """(fold radius, first node, 1 / radial at the nodes, slopes) for the coefficients.

    One scan of the radial map serves the fold test and the start of Newton's unprojection:
    rd increases strictly up to the fold, so 1 / radial is a function of rd^2 there, tabulated
    at 128 nodes per octave of rd^2 (the float64 bit pattern of rd^2 shifted right by
    ``_START_BITS`` is the node index: a lookup is integer arithmetic, where np.interp's binary
    search costs ~100 ns a point) from 2^-24 to the fold, linear in rd^2 between nodes (error
    below 1e-6 relative on the paper's lenses). ~8k nodes, 128 KiB per coefficient set.
    """
    k1, k2, _, _, k3, k4, k5, k6 = dist
    r = np.linspace(0.0, r_max, 200001)
    r2 = r * r
    num = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    den = 1 + k4 * r2 + k5 * r2**2 + k6 * r2**3
    rd = r * num / den
    bad = (np.diff(rd) <= 0) | (den[1:] <= 0) | (num[1:] <= 0)
    first_bad = int(np.argmax(bad)) if np.any(bad) else len(r) - 1
    fold = float(r[1:][first_bad]) if np.any(bad) else float("inf")
    # Samples 0..first_bad have strictly increasing rd (the first non-increase is after them).
    rd, inv_radial = rd[:first_bad + 1], np.append(1.0, den[1:first_bad + 1] / num[1:first_bad + 1])
    lo = int(np.array(_START_LOW).view(np.int64)) >> _START_BITS
    hi = max(int(np.array(rd[-1] ** 2).view(np.int64)) >> _START_BITS, lo) + 1
    nodes = (np.arange(lo, hi + 1, dtype=np.int64) << _START_BITS).view(np.float64)
    g = np.interp(np.sqrt(nodes), rd, inv_radial)
    return fold, lo, g, np.append(np.diff(g) / np.diff(nodes), 0.0)


_CHUNK = 1 << 13  # points per pass of the unprojection: its temporaries stay in the L2 cache


def undistort_normalized(
    xd: np.ndarray, dist: np.ndarray, tol: float = 1e-13, max_iter: int = 50
) -> tuple[np.ndarray, np.ndarray]:
    """Invert :func:`distort` by Newton's method.

    Returns (xy (...,2), converged mask (...)). ``tol`` is in normalized units (1e-13 is
    about 1e-10 px for focal lengths up to 1000 px; callers in pixels use :func:`unproject`):
    a point is converged when both components of ``distort(xy) - xd`` are below it, checked at
    the returned ``xy`` itself. The start inverts the radial part up to interpolation (a table
    of the radial map, which is monotone up to the fold), so Newton, quadratic from there for
    every lens whose radial map is monotone over the image, needs 1-3 steps; converged points
    leave the iteration. Steps that would jump far (beyond the fold) are damped.
    """
    return _undistort(xd, dist, tol, max_iter)


def _undistort(points, dist, tol, max_iter, to_normalized=None, fold=math.inf):
    """:func:`undistort_normalized` of ``to_normalized(points)`` (identity if None), chunk by
    chunk so that every pass stays in cache; converged also requires |xy| < ``fold``."""
    points = np.asarray(points, dtype=np.float64)
    shape = points.shape[:-1]
    flat = points.reshape(-1, 2)
    xy = np.empty(flat.shape)
    ok = np.zeros(len(flat), dtype=bool)
    coeffs = tuple(float(d) for d in np.ravel(dist))
    # Non-finite coefficients have no radial profile (and converge nowhere).
    profile = _radial_profile(coeffs, 20.0)[1:] if all(map(math.isfinite, coeffs)) else None
    for a in range(0, len(flat), _CHUNK):
        target = flat[a:a + _CHUNK] if to_normalized is None else to_normalized(flat[a:a + _CHUNK])
        _newton_chunk(target, coeffs, profile, tol, max_iter, fold * fold, xy[a:a + _CHUNK],
                      ok[a:a + _CHUNK])
    return xy.reshape(shape + (2,)), ok.reshape(shape)


def _horner(r2: np.ndarray, coeffs) -> np.ndarray:
    """c0 + c1 r2 + c2 r2^2 + ... by Horner's rule, without the passes of zero leading terms."""
    c = list(coeffs)
    while len(c) > 1 and c[-1] == 0:
        c.pop()
    if len(c) == 1:
        return np.full_like(r2, c[0])
    acc = r2 * c[-1]
    for ci in reversed(c[1:-1]):
        acc += ci
        acc *= r2
    acc += c[0]
    return acc


def _newton_chunk(target, coeffs, profile, tol, max_iter, fold2, out, converged) -> None:
    """Newton's iteration for one chunk of distorted points (n, 2) into ``out`` / ``converged``.

    Written out on separate x and y arrays with scalar coefficients (the residual and the
    symmetric 2x2 Jacobian of :func:`distort_with_jacobians`, solved by Cramer's rule), terms
    of zero coefficients skipped: about a quarter of the array passes of the generic form.
    """
    k1, k2, p1, p2, k3, k4, k5, k6 = coeffs
    gx, gy = target[:, 0].copy(), target[:, 1].copy()
    finite = np.isfinite(gx) & np.isfinite(gy)
    if not np.all(finite):  # never converge: out of the iteration at once
        out[~finite] = np.nan
        converged[~finite] = False
        keep = np.flatnonzero(finite)
        if len(keep):
            _newton_chunk(target[keep], coeffs, profile, tol, max_iter, fold2, out_k := out[keep],
                          conv_k := converged[keep])
            out[keep], converged[keep] = out_k, conv_k
        return
    if not any(coeffs):
        out[:] = target
        converged[:] = gx * gx + gy * gy < fold2
        return
    rd2 = gx * gx + gy * gy
    if profile is None:
        s = 1.0
    else:
        # The start: 1 / radial at rd^2 from the table of its bit pattern (_radial_profile);
        # below the first node and beyond the last (the fold) the ends serve.
        lo, g, slope = profile
        i = (rd2.view(np.int64) >> _START_BITS) - lo
        np.clip(i, 0, len(g) - 1, out=i)
        node = (i + lo) << _START_BITS
        rd2 -= node.view(np.float64)
        s = g.take(i)
        s += rd2 * slope.take(i)
    x, y = gx * s, gy * s
    rational = bool(k4 or k5 or k6)
    num_c, den_c = (1.0, k1, k2, k3), (1.0, k4, k5, k6)
    dnum_c, dden_c = (2 * k1, 4 * k2, 6 * k3), (2 * k4, 4 * k5, 6 * k6)  # 2 d/d r2
    idx = None  # indices of the active points in the chunk; None: all of them
    for _ in range(max_iter):
        x2, y2, xy = x * x, y * y, x * y
        r2 = x2 + y2
        radial = _horner(r2, num_c)
        if rational:
            inv_den = 1.0 / _horner(r2, den_c)
            radial *= inv_den
        fx, fy = x * radial, y * radial
        fx -= gx
        fy -= gy
        if p1:
            fx += (2 * p1) * xy
            fy += p1 * (r2 + 2 * y2)
        if p2:
            fx += p2 * (r2 + 2 * x2)
            fy += (2 * p2) * xy
        done = np.abs(fx) < tol
        done &= np.abs(fy) < tol
        n_done = np.count_nonzero(done)
        if n_done:
            if idx is None:
                idx = np.arange(len(x))
            hit = idx[done]
            out[hit, 0], out[hit, 1] = x[done], y[done]
            converged[hit] = r2[done] < fold2
            if n_done == len(x):
                return
            keep = ~done
            idx, x, y, gx, gy = idx[keep], x[keep], y[keep], gx[keep], gy[keep]
            x2, y2, xy, r2, radial, fx, fy = (a[keep] for a in (x2, y2, xy, r2, radial, fx, fy))
            if rational:
                inv_den = inv_den[keep]
        # t = 2 d radial / d r2 (the chain rule through r2 = x^2 + y^2 gives the 2).
        t = _horner(r2, dnum_c)
        if rational:
            t -= radial * _horner(r2, dden_c)
            t *= inv_den
        j00, j11, j01 = radial + t * x2, radial + t * y2, t * xy  # the Jacobian is symmetric
        if p1:
            j00 += (2 * p1) * y
            j01 += (2 * p1) * x
            j11 += (6 * p1) * y
        if p2:
            j00 += (6 * p2) * x
            j01 += (2 * p2) * y
            j11 += (2 * p2) * x
        det = j00 * j11
        det -= j01 * j01
        nx, ny = j11 * fx, j00 * fy
        nx -= j01 * fy
        ny -= j01 * fx
        with np.errstate(divide="ignore", invalid="ignore"):
            sx, sy = nx / det, ny / det
        # Damp steps that would jump far (far outside the valid region Newton can overshoot);
        # a step under 0.35 per component is below the limit 0.5 (1 + |xy|) for every point.
        # A (near) singular Jacobian gives a huge or NaN step, so it is caught here too.
        if not max(np.max(np.abs(sx)), np.max(np.abs(sy))) <= 0.35:
            tiny = np.abs(det) < 1e-300
            if np.any(tiny):
                sx[tiny], sy[tiny] = nx[tiny] / 1e-300, ny[tiny] / 1e-300
            n = np.hypot(sx, sy)
            lim = 0.5 * (1.0 + np.sqrt(r2))
            scale = np.where(n > lim, lim / np.maximum(n, 1e-300), 1.0)
            sx *= scale
            sy *= scale
        x -= sx
        y -= sy
    if idx is None:
        idx = slice(None)
    out[idx, 0], out[idx, 1] = x, y


# ----------------------------------------------------------------------------------------------
# Projection with Jacobians
# ----------------------------------------------------------------------------------------------

def project_points(
    points: np.ndarray,
    intrinsics: np.ndarray,
    dist: np.ndarray,
    rvec: np.ndarray,
    tvec: np.ndarray,
) -> np.ndarray:
    """Project 3D points (N,3) through pose (rvec, tvec) and intrinsics [fx, fy, cx, cy, skew]."""
    return project_with_jacobians(points, intrinsics, dist, rvec, tvec, jacobians=False)[0]


def project_cam_with_jacobians(points_cam: np.ndarray, intrinsics: np.ndarray, dist: np.ndarray,
                               jacobians: bool = True):
    """Project points already in the camera frame (N,3): pixels (N,2) plus, if asked, a dict of
    Jacobians ``point`` (N,2,3) over the camera-frame point, ``intrinsics`` (N,2,5) and ``dist``
    (N,2,8). What a calibration's inner loop needs (its board points are put in the camera frame
    by its own pose step); ``project_with_jacobians`` adds the pose. The 2x2 and 2x3 products
    are written out entry by entry: small broadcast matrix products cost more than the math."""
    Pc = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
    fx, fy, cx, cy, s = np.asarray(intrinsics, dtype=np.float64)
    inv_z = 1.0 / Pc[:, 2]
    xy = Pc[:, :2] * inv_z[:, None]
    xd, Jxy, Jdist = distort_with_jacobians(xy, dist, wrt_dist=jacobians)
    uv = np.stack([fx * xd[:, 0] + s * xd[:, 1] + cx, fy * xd[:, 1] + cy], -1)
    if not jacobians:
        return uv, None
    N = len(Pc)
    Ji = np.zeros((N, 2, 5))
    Ji[:, 0, 0] = xd[:, 0]
    Ji[:, 1, 1] = xd[:, 1]
    Ji[:, 0, 2] = 1.0
    Ji[:, 1, 3] = 1.0
    Ji[:, 0, 4] = xd[:, 1]
    # d xd / d Pc = Jxy @ [[1/z, 0, -x/z], [0, 1/z, -y/z]], then d uv / d xd = [[fx, s], [0, fy]].
    M = np.empty((N, 2, 3))
    M[:, :, 0] = Jxy[:, :, 0] * inv_z[:, None]
    M[:, :, 1] = Jxy[:, :, 1] * inv_z[:, None]
    M[:, :, 2] = -(M[:, :, 0] * xy[:, 0, None] + M[:, :, 1] * xy[:, 1, None])
    J_point = np.empty((N, 2, 3))
    J_point[:, 0] = fx * M[:, 0] + s * M[:, 1]
    J_point[:, 1] = fy * M[:, 1]
    J_dist = np.empty((N, 2, 8))
    J_dist[:, 0] = fx * Jdist[:, 0] + s * Jdist[:, 1]
    J_dist[:, 1] = fy * Jdist[:, 1]
    return uv, {"point": J_point, "intrinsics": Ji, "dist": J_dist}


def project_with_jacobians(
    points: np.ndarray,
    intrinsics: np.ndarray,
    dist: np.ndarray,
    rvec: np.ndarray,
    tvec: np.ndarray,
    jacobians: bool = True,
):
    """Project points (N,3) and return pixels (N,2) plus, if asked, a dict of Jacobians.

    Jacobians: ``point`` (N,2,3), ``intrinsics`` (N,2,5) over [fx, fy, cx, cy, skew],
    ``dist`` (N,2,8), ``pose`` (N,2,6) over [rvec, tvec].
    """
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    R = rodrigues_to_matrix(rvec)
    Pc = P @ R.T + np.asarray(tvec, dtype=np.float64)
    uv, J = project_cam_with_jacobians(Pc, intrinsics, dist, jacobians)
    if not jacobians:
        return uv, None
    J_uv_Pc = J["point"]
    J["pose"] = np.concatenate([J_uv_Pc @ rotate_jacobian(rvec, P), J_uv_Pc], axis=-1)
    J["point"] = J_uv_Pc @ R
    return uv, J


# ----------------------------------------------------------------------------------------------
# The Camera
# ----------------------------------------------------------------------------------------------

def _vec(values, n: int, name: str) -> np.ndarray:
    a = np.asarray(values, dtype=np.float64).reshape(-1)
    if a.shape != (n,) or not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: expected {n} finite numbers, got {values!r}")
    return a


@dataclass(frozen=True, eq=False)
class Camera:
    """A calibrated camera: image size, intrinsics, OpenCV distortion and cam_from_world."""

    name: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    skew: float = 0.0
    dist: np.ndarray = field(default_factory=lambda: np.zeros(8))
    rvec: np.ndarray = field(default_factory=lambda: np.zeros(3))  # cam_from_world rotation
    tvec: np.ndarray = field(default_factory=lambda: np.zeros(3))  # cam_from_world translation, mm

    def __post_init__(self):
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(f"camera {self.name!r}: image size must be positive, got "
                             f"{self.width}x{self.height}")
        if not (self.fx > 0 and self.fy > 0):
            raise ValueError(f"camera {self.name!r}: fx and fy must be positive, got "
                             f"{self.fx}, {self.fy}")
        d = np.asarray(self.dist, dtype=np.float64).reshape(-1)
        if d.size > 8:
            raise ValueError(f"camera {self.name!r}: dist has {d.size} coefficients, expected "
                             f"at most 8 {list(DIST_NAMES)}")
        object.__setattr__(self, "dist", np.concatenate([d, np.zeros(8 - d.size)]))
        object.__setattr__(self, "rvec", _vec(self.rvec, 3, f"camera {self.name!r}: rvec"))
        object.__setattr__(self, "tvec", _vec(self.tvec, 3, f"camera {self.name!r}: tvec"))
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        for k in ("fx", "fy", "cx", "cy", "skew"):
            object.__setattr__(self, k, float(getattr(self, k)))

    # --- parameter views --------------------------------------------------------------------
    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, self.skew, self.cx], [0.0, self.fy, self.cy], [0, 0, 1.0]])

    @property
    def intrinsics(self) -> np.ndarray:
        """[fx, fy, cx, cy, skew]."""
        return np.array([self.fx, self.fy, self.cx, self.cy, self.skew])

    @property
    def R(self) -> np.ndarray:
        """Rotation of cam_from_world."""
        return rodrigues_to_matrix(self.rvec)

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates (mm)."""
        return -self.R.T @ self.tvec

    @property
    def size(self) -> tuple[int, int]:
        return (self.width, self.height)

    def with_params(self, **changes) -> "Camera":
        return replace(self, **changes)

    @classmethod
    def from_K(cls, name, width, height, K, dist=(), rvec=(0, 0, 0), tvec=(0, 0, 0)):
        K = np.asarray(K, dtype=np.float64)
        return cls(name, width, height, K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1],
                   np.asarray(dist, dtype=np.float64), np.asarray(rvec), np.asarray(tvec))

    # --- geometry ---------------------------------------------------------------------------
    def world_to_cam(self, points: np.ndarray) -> np.ndarray:
        """World points (..., 3) -> camera-frame points (..., 3)."""
        return np.asarray(points, dtype=np.float64) @ self.R.T + self.tvec

    def project(self, points_world: np.ndarray) -> np.ndarray:
        """World points (..., 3) -> pixels (..., 2), with distortion."""
        P = np.asarray(points_world, dtype=np.float64)
        uv = project_points(P.reshape(-1, 3), self.intrinsics, self.dist, self.rvec, self.tvec)
        return uv.reshape(P.shape[:-1] + (2,))

    def project_cam(self, points_cam: np.ndarray) -> np.ndarray:
        """Camera-frame points (..., 3) -> pixels (..., 2)."""
        P = np.asarray(points_cam, dtype=np.float64)
        return self.normalized_to_pixels(P[..., :2] / P[..., 2:3])

    def normalized_to_pixels(self, xy: np.ndarray) -> np.ndarray:
        """Undistorted normalized coordinates (..., 2) -> distorted pixels (..., 2)."""
        xd = distort(xy, self.dist)
        return np.stack([self.fx * xd[..., 0] + self.skew * xd[..., 1] + self.cx,
                         self.fy * xd[..., 1] + self.cy], -1)

    def pixels_to_distorted_normalized(self, uv: np.ndarray) -> np.ndarray:
        uv = np.asarray(uv, dtype=np.float64)
        yd = (uv[..., 1] - self.cy) / self.fy
        xd = (uv[..., 0] - self.cx - self.skew * yd) / self.fx
        return np.stack([xd, yd], -1)

    def _undistorted(self, uv: np.ndarray, tol_px: float) -> tuple[np.ndarray, np.ndarray]:
        """(undistorted normalized xy (..., 2), valid (...)): valid where Newton's iteration
        converged inside the radial fold, i.e. where the pixel has exactly one ray."""
        return _undistort(uv, self.dist, tol_px / max(self.fx, self.fy), 50,
                          self.pixels_to_distorted_normalized, radial_fold_radius(self.dist))

    def invertible(self, uv: np.ndarray, tol_px: float = 1e-10) -> np.ndarray:
        """(...,) bool: the pixel (..., 2) has a unique ray (an estimated distortion can fold
        or have a pole inside the image, TRAPS.md)."""
        return self._undistorted(uv, tol_px)[1]

    def unproject(self, uv: np.ndarray, tol_px: float = 1e-10) -> np.ndarray:
        """Pixels (..., 2) -> undistorted normalized coordinates (..., 2) (rays (x, y, 1)).

        Newton's iteration to ``tol_px`` in pixels. Raises DistortionNotInvertibleError when a
        pixel lies beyond the fold of the radial distortion or the iteration does not converge.
        """
        xy, valid = self._undistorted(uv, tol_px)
        if not np.all(valid):
            bad = ~valid
            where = np.asarray(uv)[bad][0]
            raise DistortionNotInvertibleError(
                f"camera {self.name!r}: distortion {self.dist.tolist()} is not invertible at "
                f"pixel ({where[0]:.1f}, {where[1]:.1f}) ({int(bad.sum())} pixels): the radial "
                f"map folds at normalized radius {radial_fold_radius(self.dist):.4g}; reduce "
                f"|k| or the image size")
        return xy

    def unproject_rays(self, uv: np.ndarray) -> np.ndarray:
        """Pixels (..., 2) -> unit ray directions in the camera frame (..., 3)."""
        xy = self.unproject(uv)
        d = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], -1)
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def pixel_grid(self, step: int = 1) -> np.ndarray:
        """Pixel centres (H', W', 2) on a regular grid covering the image (OpenCV centres)."""
        u = np.arange(0, self.width, step, dtype=np.float64)
        v = np.arange(0, self.height, step, dtype=np.float64)
        return np.stack(np.meshgrid(u, v), -1)

    def check_invertible(self, step: int = 8) -> None:
        """Raise DistortionNotInvertibleError if any pixel (on a grid plus the border) has no ray."""
        border = np.concatenate([
            np.stack([np.arange(self.width), np.zeros(self.width)], -1),
            np.stack([np.arange(self.width), np.full(self.width, self.height - 1)], -1),
            np.stack([np.zeros(self.height), np.arange(self.height)], -1),
            np.stack([np.full(self.height, self.width - 1), np.arange(self.height)], -1),
        ])
        self.unproject(np.concatenate([self.pixel_grid(step).reshape(-1, 2), border]))

    # --- serialization ----------------------------------------------------------------------
    def to_dict(self) -> dict:
        return {
            "name": self.name, "width": self.width, "height": self.height,
            "fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy, "skew": self.skew,
            "dist": dict(zip(DIST_NAMES, self.dist.tolist())),
            "cam_from_world": {"rvec": self.rvec.tolist(), "tvec_mm": self.tvec.tolist()},
        }

    @classmethod
    def from_dict(cls, d: dict, source: str = "camera") -> "Camera":
        try:
            dist = d.get("dist", {})
            if isinstance(dist, dict):
                unknown = set(dist) - set(DIST_NAMES)
                if unknown:
                    raise ValueError(f"unknown distortion coefficients {sorted(unknown)}; "
                                     f"expected {list(DIST_NAMES)}")
                dist = [float(dist.get(k, 0.0)) for k in DIST_NAMES]
            pose = d.get("cam_from_world", {})
            return cls(str(d["name"]), int(d["width"]), int(d["height"]), float(d["fx"]),
                       float(d["fy"]), float(d["cx"]), float(d["cy"]), float(d.get("skew", 0.0)),
                       np.asarray(dist, dtype=np.float64), pose.get("rvec", [0, 0, 0]),
                       pose.get("tvec_mm", [0, 0, 0]))
        except KeyError as e:
            raise ValueError(f"{source}: missing field {e.args[0]!r}") from None
        except (TypeError, ValueError) as e:
            raise ValueError(f"{source}: {e}") from None

    def save_json(self, path) -> None:
        write_json(path, self.to_dict())

    @classmethod
    def load_json(cls, path) -> "Camera":
        try:
            d = read_json(path)
        except OSError as e:
            raise ValueError(f"{path}: cannot read camera JSON ({e})") from None
        return cls.from_dict(d, source=str(path))
