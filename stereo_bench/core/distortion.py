"""OpenCV's distortion model ``[k1, k2, p1, p2, k3, k4, k5, k6]`` on normalized coordinates:
the forward map with its Jacobians, where the radial profile folds, and the exact inverse.

The inverse is Newton's method run to convergence (TRAPS.md: cv2.undistortPoints with default
criteria is off by up to 1 px on a wide-angle lens), started from a tabulated inverse of the
radial profile, in chunks that keep the temporaries in cache; a point beyond the fold has no
unique ray (``DistortionNotInvertibleError``).
"""

from __future__ import annotations

import functools
import math


import numpy as np


class DistortionNotInvertibleError(ValueError):
    """The distortion map folds over inside the image, so a pixel has no unique ray."""


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
    return undistort_to(xd, dist, tol, max_iter)


def undistort_to(points, dist, tol, max_iter, to_normalized=None, fold=math.inf):
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
