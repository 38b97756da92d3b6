"""The saddle fit that measures checkerboard and ChArUco corners from the board's own content
(the package notes), and the local board -> image geometry it is laid out with.
"""

from __future__ import annotations

import math

import cv2
import numba
import numpy as np


MAX_WINDOW_PX = 30.0  # half-extent cap of the saddle fit's window along a grid axis


_SADDLE_MARGIN = 3  # px a saddle window may move before its gradient patch is re-cut


# ----------------------------------------------------------------------------- local geometry
# Both fits below solve one small least-squares problem per point over its neighbours; they are
# compiled loops over the pairs of points (as N x N numpy arrays with batched pseudo-inverses and
# SVDs they cost 2.4 ms of the 640 x 480 checkerboard's 9.4 ms a frame; compiled, 0.1 ms). Each
# point's sums run over its neighbours in index order; the results equal those of lstsq and
# matrix_rank on each point alone to rounding (tests/detect/test_batched.py).
_EPS = float(np.finfo(float).eps)


def _leave_one_out(object_xy: np.ndarray, points: np.ndarray, radius_mm: float) -> np.ndarray:
    """(N,) how far each point lies from where its neighbours (within ``radius_mm``, the point
    itself left out) put it by an affine fit, in board mm; NaN where it cannot be predicted
    (fewer than three neighbours). The fit is lstsq's: its minimum-norm answer where the
    neighbours are on a line."""
    return _leave_one_out_fits(np.ascontiguousarray(object_xy, np.float64),
                               np.ascontiguousarray(points, np.float64), float(radius_mm))


@numba.njit(cache=True, nogil=True)
def _neighbours(object_xy, points, i, radius, near):
    """How many points are point i's neighbours, their indices in ``near``: seen (finite), not
    i, within ``radius`` board mm of it; 0 when point i is not seen itself."""
    if not (np.isfinite(points[i, 0]) and np.isfinite(points[i, 1])):
        return 0
    k = 0
    for j in range(len(points)):
        if j == i or not (np.isfinite(points[j, 0]) and np.isfinite(points[j, 1])):
            continue
        dx, dy = object_xy[j, 0] - object_xy[i, 0], object_xy[j, 1] - object_xy[i, 1]
        if math.sqrt(dx * dx + dy * dy) <= radius:
            near[k] = j
            k += 1
    return k


@numba.njit(cache=True, nogil=True)
def _leave_one_out_fits(object_xy, points, radius):
    n = len(points)
    out = np.full(n, np.nan)
    near = np.empty(n, np.int64)
    for i in range(n):
        count = _neighbours(object_xy, points, i, radius, near)
        if count < 3:  # an affine map needs three
            continue
        # Normal equations of [offset x, offset y, 1] -> px (rows: d/dx, d/dy, value at i).
        normal, rhs = np.zeros((3, 3)), np.zeros((3, 2))
        for m in range(count):
            j = near[m]
            x = (object_xy[j, 0] - object_xy[i, 0], object_xy[j, 1] - object_xy[i, 1], 1.0)
            for a in range(3):
                for b in range(3):
                    normal[a, b] += x[a] * x[b]
                rhs[a, 0] += x[a] * points[j, 0]
                rhs[a, 1] += x[a] * points[j, 1]
        sol = _pseudo_inverse_3x3(normal) @ rhs
        lx, ly = sol[2, 0] - points[i, 0], sol[2, 1] - points[i, 1]
        out[i] = math.sqrt(lx * lx + ly * ly) / _spectral_norm(sol[0, 0], sol[0, 1], sol[1, 0],
                                                                sol[1, 1])
    return out


@numba.njit(cache=True, nogil=True)
def _pseudo_inverse_3x3(m):
    """The pseudo-inverse of a symmetric positive semi-definite 3 x 3 matrix with lstsq's
    cut-off (3 eps of the largest singular value): its adjugate over its determinant when it is
    well conditioned (the smallest eigenvalue above 1e-6 of the largest, as det / trace^3
    bounds it from below), else from its SVD (the neighbours on a line)."""
    adj = np.empty((3, 3))
    for a in range(3):
        for b in range(3):
            r0, r1 = (b + 1) % 3, (b + 2) % 3
            c0, c1 = (a + 1) % 3, (a + 2) % 3
            adj[a, b] = m[r0, c0] * m[r1, c1] - m[r0, c1] * m[r1, c0]
    det = m[0, 0] * adj[0, 0] + m[0, 1] * adj[1, 0] + m[0, 2] * adj[2, 0]
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    if trace > 0 and det > 1e-6 * trace ** 3:
        return adj / det
    return np.ascontiguousarray(np.linalg.pinv(m, 3 * _EPS))


@numba.njit(cache=True, nogil=True)
def _spectral_norm(a, b, c, d):
    """The largest singular value of [[a, b], [c, d]]: the root of the largest eigenvalue of
    its Gram matrix, in closed form."""
    p, q, r = a * a + c * c, a * b + c * d, b * b + d * d
    return math.sqrt(0.5 * (p + r) + math.hypot(0.5 * (p - r), q))


def drop_grid_outliers(object_xy: np.ndarray, points: np.ndarray, step_mm: float) -> np.ndarray:
    """Points (N, 2) with corners that break the local grid set to NaN.

    cornerSubPix can converge to a wrong corner in noisy images (5-6 px off, on the wide
    camera's noisy renders). Predicted from its neighbours, a true corner of any paper rig's
    trajectory lies within 0.044 step; the worst corner beyond 0.15 step is dropped and the rest
    re-checked, then dropped corners that fit the remaining grid come back (an outlier can make a
    good neighbour look worse than itself).
    """
    points = points.copy()
    dropped = {}
    while True:
        misfit = _leave_one_out(object_xy, points, 1.5 * step_mm)
        if not np.any(misfit > 0.15 * step_mm):
            break
        worst = int(np.nanargmax(misfit))
        dropped[worst] = points[worst].copy()
        points[worst] = np.nan
    for i, p in dropped.items():
        trial = points.copy()
        trial[i] = p
        if _leave_one_out(object_xy, trial, 1.5 * step_mm)[i] <= 0.15 * step_mm:
            points = trial
    return points


def local_affines(object_xy: np.ndarray, points: np.ndarray, radius_mm: float):
    """Board-mm -> px linear maps at each point, fitted to its neighbours within ``radius_mm``.

    Least squares on the differences to the point itself.  Returns (N, 2, 2) maps (NaN where the
    point is missing or has fewer than two non-collinear neighbours) and (N,) misfits: the largest
    residual of a neighbour, expressed in board mm (residual px / the map's largest stretch).
    """
    return _local_affine_fits(np.ascontiguousarray(object_xy, np.float64),
                              np.ascontiguousarray(points, np.float64), float(radius_mm))


@numba.njit(cache=True, nogil=True)
def _local_affine_fits(object_xy, points, radius):
    n = len(points)
    affines = np.full((n, 2, 2), np.nan)
    misfit = np.full(n, np.nan)
    near = np.empty(n, np.int64)
    for i in range(n):
        k = _neighbours(object_xy, points, i, radius, near)
        # The offsets' Gram matrix [[a, b], [b, c]], and its determinant as the sum of the
        # squared cross products of pairs (Lagrange's identity), free of the cancellation of
        # a c - b^2: collinear neighbours give rounding-sized singular values, as in an SVD.
        a = b = c = det = 0.0
        r00 = r01 = r10 = r11 = 0.0
        for m in range(k):
            j = near[m]
            dx, dy = object_xy[j, 0] - object_xy[i, 0], object_xy[j, 1] - object_xy[i, 1]
            ex, ey = points[j, 0] - points[i, 0], points[j, 1] - points[i, 1]
            a += dx * dx
            b += dx * dy
            c += dy * dy
            r00 += dx * ex
            r01 += dx * ey
            r10 += dy * ex
            r11 += dy * ey
            for m2 in range(m):
                j2 = near[m2]
                cross = (dx * (object_xy[j2, 1] - object_xy[i, 1])
                         - dy * (object_xy[j2, 0] - object_xy[i, 0]))
                det += cross * cross
        largest = 0.5 * (a + c) + math.hypot(0.5 * (a - c), b)
        # Rank 2 as matrix_rank decides it: the smaller singular value above the larger times
        # the larger dimension of the N x 2 offsets times eps.
        if not (largest > 0 and math.sqrt(det / largest) > math.sqrt(largest) * max(n, 2) * _EPS):
            continue
        # A^T = Gram^-1 [offsets^T image offsets]; A maps board mm to px.
        inv00, inv01, inv11 = c / det, -b / det, a / det
        t00, t01 = inv00 * r00 + inv01 * r10, inv00 * r01 + inv01 * r11
        t10, t11 = inv01 * r00 + inv11 * r10, inv01 * r01 + inv11 * r11
        affines[i, 0, 0], affines[i, 0, 1], affines[i, 1, 0], affines[i, 1, 1] = t00, t10, t01, t11
        worst = 0.0
        for m in range(k):
            j = near[m]
            dx, dy = object_xy[j, 0] - object_xy[i, 0], object_xy[j, 1] - object_xy[i, 1]
            rx = dx * t00 + dy * t10 - (points[j, 0] - points[i, 0])
            ry = dx * t01 + dy * t11 - (points[j, 1] - points[i, 1])
            worst = max(worst, math.sqrt(rx * rx + ry * ry))
        misfit[i] = worst / _spectral_norm(t00, t10, t01, t11)
    return affines, misfit


def nearest_mm(object_xy: np.ndarray) -> float:
    """Distance from a board's first feature point to its nearest neighbour (the lattice step)."""
    return float(np.min(np.linalg.norm(object_xy[1:] - object_xy[0], axis=1)))


# ----------------------------------------------------------------------------- saddle points
class _Blurred:
    """``gray`` blurred with ``sigma`` px (float32) over the boxes a fit asks for (``box``).

    Each box is blurred alone with the kernel's reach of context on every side inside the
    image, so its values are those of the whole image blurred (both reflect at the image's own
    border), to float32 rounding (2 ulp, tests/detect/test_batched.py): blurring a few boxes costs
    little where the whole 4096 x 3072 frame cost more than the fit itself.  A 30 x 30 box
    blurred alone costs about as much as ``BOX_COST_PX`` pixels of a whole blur (10 us, mostly
    the call's own: measured against a 640 x 480 frame's 1 ms), so where the ``boxes`` expected
    would cost more than the whole image (a checkerboard's 126 on the 640 x 480 camera) the
    whole image is blurred once and the boxes are cut from it.
    """

    BOX_COST_PX = 3_000

    def __init__(self, gray, sigma: float, boxes: int):
        self.gray, self.sigma = gray, sigma
        self.whole = (cv2.GaussianBlur(gray.astype(np.float32), (0, 0), sigma)
                      if gray.size <= boxes * self.BOX_COST_PX else None)

    def box(self, x0: int, y0: int, x1: int, y1: int):
        """The blurred box [x0, x1) x [y0, y1) cut to the image, and the cut box's top-left
        pixel (x, y); None if the box misses the image."""
        height, width = self.gray.shape
        bx0, by0, bx1, by1 = max(x0, 0), max(y0, 0), min(x1, width), min(y1, height)
        if bx1 <= bx0 or by1 <= by0:
            return None
        if self.whole is not None:
            return self.whole[by0:by1, bx0:bx1], (bx0, by0)
        context = math.ceil(4 * self.sigma) + 1  # OpenCV's float kernel reaches round(4 sigma)
        sx0, sy0 = max(bx0 - context, 0), max(by0 - context, 0)
        sx1, sy1 = min(bx1 + context, width), min(by1 + context, height)
        blurred = cv2.GaussianBlur(self.gray[sy0:sy1, sx0:sx1].astype(np.float32), (0, 0),
                                   self.sigma)
        return blurred[by0 - sy0:by1 - sy0, bx0 - sx0:bx1 - sx0], (bx0, by0)


def _print_extents(blurred: _Blurred, q, A, axis, sign, square_mm, perp_mm,
                   samples: int = 40) -> np.ndarray:
    """How far (board mm, up to one square) the print visibly goes on from corners ``q`` (n, 2)
    px along grid axis ``axis`` (n,) (0: x, 1: y) in direction ``sign`` (n,) (+-1), each through
    its local board -> image map ``A`` (n, 2, 2), seen in the image ``blurred``.

    Beyond an edge corner lie the two outer squares on either side of the grid line through it,
    one black and one white as long as the print goes on.  Their grey levels are sampled (bilinear)
    at ``perp_mm`` on either side of that line, from 0.15 square (clear of the other line's blur)
    out to one square; the print ends where their contrast falls below half its value near the
    corner (beyond it both samples see the same surround, or the same occluder).  Samples off the
    image are NaN, which ends the print there.  Each corner's samples are read from its own
    blurred box; the rest is done for all corners at once.
    """
    t = np.linspace(0.15, 1.0, samples)
    n = len(q)
    rows = np.arange(n)
    step = (sign[:, None] * t) * square_mm  # (n, samples) board mm along the axis
    along = q[:, None, :] + step[:, :, None] * A[rows, :, axis][:, None, :]
    side = (perp_mm * A[rows, :, 1 - axis])[:, None, :]
    xy = np.concatenate([along + side, along - side], axis=1)  # (n, 2 samples, 2)
    lo = np.floor(xy.min(axis=1)).astype(int) - 1
    hi = np.ceil(xy.max(axis=1)).astype(int) + 2
    if blurred.whole is not None:
        # A small image's boxes are views of its whole blur: ``blurred.box``'s cut, and every
        # corner's samples in one compiled pass (a remap a corner cost 0.8 ms of the 640 x 480
        # checkerboard's 6 ms a frame).
        start = np.maximum(lo, 0)
        end = np.minimum(hi, blurred.gray.shape[::-1])
        inside = np.all(end > start, axis=1)
        values = _bilinear_in_boxes(blurred.whole, start, end, inside,
                                    (xy - start[:, None, :]).astype(np.float32))
    else:  # each box blurred alone, read by the same kernel
        values = np.full(xy.shape[:2], np.nan, np.float32)
        inside = np.zeros(n, bool)
        for r in range(n):
            box = blurred.box(lo[r, 0], lo[r, 1], hi[r, 0], hi[r, 1])
            if box is None:
                continue
            patch, origin = box
            values[r] = _bilinear_in_boxes(
                np.ascontiguousarray(patch), np.zeros((1, 2), np.int64),
                np.array([patch.shape[::-1]], np.int64), np.ones(1, np.bool_),
                (xy[r] - origin).astype(np.float32)[None])[0]
            inside[r] = True
    contrast = np.abs(values[:, :samples] - values[:, samples:])
    reference = np.median(contrast[:, t <= 0.3], axis=1)
    ended = ~(contrast >= 0.5 * reference[:, None])
    first = np.where(ended.any(axis=1), ended.argmax(axis=1), samples)
    extent = np.where(first < samples, t[np.minimum(first, samples - 1)] * square_mm, square_mm)
    return np.where(inside & (reference > 0), extent, 0.0)


@numba.njit(cache=True, nogil=True)
def _bilinear_in_boxes(image, start, end, inside, local):
    """(n, S) float32: ``image`` read bilinearly at ``local`` (n, S, 2) (x, y) px from each
    box's top-left ``start`` (n, 2), as cv2.remap (INTER_LINEAR, BORDER_CONSTANT NaN) reads
    the box [start, end) alone: NaN where a tap is off the box, and NaN rows where not
    ``inside``.  Each value is two lerps along x and one along y, each a fused multiply-add
    (OpenCV's, on this machine's instructions; done here in float64, where the float32 product
    is exact): equal to cv2.remap's bit for bit (tests/detect/test_batched.py), and the same on
    every machine.  Both ways ``_print_extents`` cuts its boxes read them with it."""
    n, samples = local.shape[0], local.shape[1]
    out = np.full((n, samples), np.nan, np.float32)
    for r in range(n):
        if not inside[r]:
            continue
        width, height = end[r, 0] - start[r, 0], end[r, 1] - start[r, 1]
        for s in range(samples):
            x, y = local[r, s, 0], local[r, s, 1]
            fx, fy = np.floor(x), np.floor(y)
            if not (0 <= fx and fx + 1 < width and 0 <= fy and fy + 1 < height):
                continue  # also NaN coordinates
            col, row = start[r, 0] + int(fx), start[r, 1] + int(fy)
            a, b = np.float64(x - fx), np.float64(y - fy)
            p00, p01 = image[row, col], image[row, col + 1]
            p10, p11 = image[row + 1, col], image[row + 1, col + 1]
            top = np.float32(a * np.float64(p01 - p00) + np.float64(p00))
            bottom = np.float32(a * np.float64(p11 - p10) + np.float64(p10))
            out[r, s] = np.float32(b * np.float64(bottom - top) + np.float64(top))
    return out


def refine_saddles(gray, points: np.ndarray, object_xy: np.ndarray, square_mm: float,
                    sigma: float, band_mm: float | None = None, reach: float = 0.5,
                    iterations: int = 20) -> np.ndarray:
    """Re-measure corners (N, 2) px with a saddle fit that only sees the board's own squares.

    cornerSubPix (Förstner & Gülch 1987) finds the point q that every gradient g at pixels p in a
    window is orthogonal to, least squares: (sum w g g^T) q = sum w g g^T p.  Its square window
    of half a square reaches, at an edge corner of a sheared view, the surround beside the outer
    squares when the print has no margin or is cut into them (OpenCV's sample stereo images:
    3-6 corners of an end column 1.5-9 px off), or an occluder beside the board.  Here the
    window is a parallelogram in board units, through the local board -> image map fitted to the
    neighbouring corners (``local_affines``): |u|, |v| within ``reach`` square of the corner, and
    ``guard`` px (3 sigma + 2: the blur and the gradient's stencil) short of the next grid line
    or, where there is no neighbouring corner, of where the print is seen to end
    (``_print_extents``).  Both extents are taken symmetric (the shorter side rules), so the
    window stays point-symmetric about q, as a saddle is; where the image border cuts it, only
    pixels whose mirror through q is inside count.  The weights, cos^2 along u times along v,
    fall to zero at the window's sides, so no pixel jumps in or out as q moves.  ``band_mm``
    keeps only pixels within that distance of the two edge lines (ChArUco: the markers' borders
    stay out).  Gradients are central differences on a copy blurred with ``sigma`` px.
    On clean renders of the wide camera (tests/detect/test_detect.py's views) this measured the
    checkerboard to 0.010 px mean (cornerSubPix with the old window: 0.013) and ChArUco to
    0.020 px (0.028) with ``reach`` 0.8 (its cross of bands holds few pixels).  A corner
    without a local map keeps its estimate; one whose fit fails, does not converge or moves by
    more than a quarter square is NaN (not measured).
    """
    affines, _ = local_affines(object_xy, points, 1.5 * square_mm)
    guard = 3.0 * sigma + 2.0
    perp_mm = band_mm if band_mm is not None else 0.3 * square_mm
    height, width = gray.shape
    refined = points.copy()
    seen = np.flatnonzero(np.isfinite(affines[:, 0, 0]))
    A = affines[seen]
    A_inv = np.linalg.inv(A)
    # Where a corner has no found neighbour, how far the print is seen to go on.
    cells = np.round(object_xy / square_mm).astype(int)
    corner = cells.min(axis=0) - 1  # a cell of margin on every side
    known = np.zeros(tuple(cells.max(axis=0) - corner + 2), bool)
    known[tuple((cells[np.isfinite(points).all(axis=1)] - corner).T)] = True
    m, k, sign = (a.ravel() for a in np.meshgrid(np.arange(len(seen)), [0, 1], [-1, 1],
                                                 indexing="ij"))
    neighbour = cells[seen[m]] - corner
    neighbour[np.arange(len(m)), k] += sign
    edge = ~known[tuple(neighbour.T)]
    m, k, sign = m[edge], k[edge], sign[edge]
    blurred = _Blurred(gray, sigma, len(m) + len(seen))  # a box per edge and per corner
    extent = np.full((len(seen), 2), square_mm)
    np.minimum.at(extent, (m, k), _print_extents(blurred, points[seen[m]], A[m], k, sign,
                                                square_mm, perp_mm))
    px_per_mm = np.linalg.norm(A, axis=1)  # (M, 2): px per board mm along u and v
    lim = np.minimum(reach * square_mm, extent - guard * np.linalg.norm(A_inv, axis=2))
    # Windows wider than MAX_WINDOW_PX px add nothing measurable but time (large images).
    lim = np.minimum(lim, MAX_WINDOW_PX / px_per_mm)
    fits = np.all(lim * px_per_mm >= 1.5, axis=1)
    refined[seen[~fits]] = np.nan
    seen, A_inv, lim = seen[fits], A_inv[fits], lim[fits]
    half = np.einsum("mij,mj->mi", np.abs(A[fits]), lim)  # px half-extents of the bounding box
    start = points[seen]
    q, steps, ok = start.copy(), np.zeros(len(seen), int), np.zeros(len(seen), bool)
    # Each corner iterates on a blurred patch that holds its window with _SADDLE_MARGIN px to
    # spare; a corner whose window moves out gets a new patch and goes on.
    pending = np.arange(len(seen))
    band = np.inf if band_mm is None else band_mm  # inf: every pixel is near an edge line
    while len(pending):
        origin = np.floor(q[pending] - half[pending]).astype(np.int64) - _SADDLE_MARGIN
        size = int((np.ceil(q[pending] + half[pending]) + 1 - origin).max()) + _SADDLE_MARGIN
        patches = _blurred_patches(blurred, origin, size)
        pending = _saddle_fit(patches, np.arange(len(pending)), origin, size, pending, q, half,
                              A_inv, lim, band, width, height, steps, ok, iterations)
    moved = np.linalg.norm(np.einsum("mij,mj->mi", A_inv, q - start), axis=1)
    refined[seen] = np.where((ok & (moved < 0.25 * square_mm))[:, None], q, np.nan)
    return refined


def _blurred_patches(blurred: _Blurred, origin: np.ndarray, size: int) -> np.ndarray:
    """(M, size + 2, size + 2) float64: the image ``blurred`` over the squares of ``size`` px
    whose top-left pixels are ``origin`` (M, 2) (x, y), with one pixel more on every side for
    the gradient's central differences; zero off the image.  Blurred once however often the
    window moves within its square."""
    if blurred.whole is not None:
        return _cut_patches(blurred.whole, np.ascontiguousarray(origin, np.int64), size)
    patches = np.zeros((len(origin), size + 2, size + 2))
    for k, (x, y) in enumerate(origin):
        box = blurred.box(x - 1, y - 1, x + size + 1, y + size + 1)
        if box is not None:
            patch, (bx, by) = box
            patches[k, by - y + 1:by - y + 1 + patch.shape[0],
                    bx - x + 1:bx - x + 1 + patch.shape[1]] = patch
    return patches


@numba.njit(cache=True, nogil=True)
def _cut_patches(whole, origin, size):
    """``_blurred_patches`` cut from the whole image blurred, in one pass (0.35 ms a 640 x 480
    checkerboard frame, where a slice and a copy a corner took 0.67)."""
    height, width = whole.shape
    patches = np.zeros((len(origin), size + 2, size + 2))
    for k in range(len(origin)):
        for r in range(size + 2):
            y = origin[k, 1] - 1 + r
            if y < 0 or y >= height:
                continue
            for c in range(size + 2):
                x = origin[k, 0] - 1 + c
                if 0 <= x < width:
                    patches[k, r, c] = whole[y, x]
    return patches


# The fit's per-pixel work, compiled: one pass over each window per step, with no window-sized
# arrays (in numpy, the gradient moments and the weights over every window cost most of a
# 12 MP checkerboard's detection), and each corner's steps in one loop (driven from numpy, a
# step of all corners at once cost 1.8 ms of the 640 x 480 checkerboard's 9 ms a frame in
# array bookkeeping).  Each pixel's gradient, phases, masks and weight are computed as defined
# in ``_window_sums``, term by term; the sums are taken in pixel order.
@numba.njit(cache=True, nogil=True)
def _saddle_fit(patches, rows, origin, size, corners, q, half, A_inv, lim, band_mm, width,
                height, steps, ok, iterations):
    """Iterate the saddle fit of ``corners`` (indices into ``q`` (M, 2), ``half`` (M, 2) px
    half-extents of each window's bounding box, ``A_inv`` (M, 2, 2) px -> board mm, ``lim``
    (M, 2) the window's half-extents in mm, ``steps`` and ``ok`` (M,), all updated in place):
    corner ``corners[r]``'s square of ``size`` px is ``patches[rows[r]]`` (``_blurred_patches``)
    with top-left pixel ``origin[r]``.  A step moves q by the solution of
    (sum w g g^T) shift = sum w g g^T (p - q); a corner stops when a step is under 1e-4 px
    (``ok``), after ``iterations`` steps, when its normal matrix cannot be solved (condition
    over 1e6) or its window leaves the image.  Returns the corners whose window left their
    square, to go on with new patches."""
    half_pi = 0.5 * np.pi
    moved_out = np.empty(len(corners), np.int64)
    n_out = 0
    for r in range(len(corners)):
        c = corners[r]
        patch, ox, oy = patches[rows[r]], origin[r, 0], origin[r, 1]
        while True:
            x0 = int(max(math.floor(q[c, 0] - half[c, 0]), 1.0))
            y0 = int(max(math.floor(q[c, 1] - half[c, 1]), 1.0))
            x1 = int(min(math.ceil(q[c, 0] + half[c, 0]) + 1, width - 1))
            y1 = int(min(math.ceil(q[c, 1] + half[c, 1]) + 1, height - 1))
            if x1 <= x0 or y1 <= y0:
                break  # the window left the image: not measured
            if x0 < ox or y0 < oy or x1 > ox + size or y1 > oy + size:
                moved_out[n_out] = c
                n_out += 1
                break
            qx, qy = q[c, 0], q[c, 1]
            # Only pixels whose mirror image through q is in the image too: a window cut by
            # the image border stays point-symmetric, as the saddle is.
            mx, my = min(qx, (width - 1) - qx), min(qy, (height - 1) - qy)
            # The weight's phases, pi/2 at the window's sides: theta = pi/2 (A_inv p) / lim.
            s00, s01 = half_pi * A_inv[c, 0, 0] / lim[c, 0], half_pi * A_inv[c, 0, 1] / lim[c, 0]
            s10, s11 = half_pi * A_inv[c, 1, 0] / lim[c, 1], half_pi * A_inv[c, 1, 1] / lim[c, 1]
            band0, band1 = half_pi * band_mm / lim[c, 0], half_pi * band_mm / lim[c, 1]
            a, b, cc, rx, ry = _window_sums(patch, ox, oy, x0, y0, x1, y1, qx, qy, mx, my,
                                            s00, s01, s10, s11, band0, band1)
            # sum w g g^T (p - q), the pixel p relative to the square's top-left.
            rx -= a * (qx - ox) + b * (qy - oy)
            ry -= b * (qx - ox) + cc * (qy - oy)
            steps[c] += 1
            # The normal matrix [[a, b], [b, cc]] is symmetric and positive semi-definite: its
            # condition number is its eigenvalues' ratio, in closed form.
            largest = 0.5 * (a + cc) + math.hypot(0.5 * (a - cc), b)
            det = a * cc - b * b
            if not (largest > 0 and (det / largest) * 1e6 >= largest):
                break
            dx, dy = (cc * rx - b * ry) / det, (a * ry - b * rx) / det
            q[c, 0] += dx
            q[c, 1] += dy
            ok[c] = math.sqrt(dx * dx + dy * dy) < 1e-4
            if ok[c] or steps[c] >= iterations:
                break
    return moved_out[:n_out]


@numba.njit(cache=True, nogil=True)
def _window_sums(patch, ox, oy, x0, y0, x1, y1, qx, qy, mx, my, s00, s01, s10, s11, band0,
                 band1):
    """The sums over one window [x0, x1) x [y0, y1) of w [gx gx, gx gy, gy gy,
    gx (gx x + gy y), gy (gx x + gy y)]: (gx, gy) the central differences of the blurred
    ``patch`` (top-left pixel (ox, oy), one pixel of border), (x, y) the pixel relative to
    (ox, oy), w = (cos theta_u cos theta_v)^2 with theta_a = tx_a + ty_a, tx_a = s_a0 (x - qx)
    and ty_a = s_a1 (y - qy) (cos of the sum as cos ty cos tx - sin ty sin tx, the row's and the
    column's factors); pixels with |theta_a| > pi/2, or farther from q than (mx, my) (whose
    mirror through q is off the image), have no weight, nor those where neither |theta_a| is
    within ``band_a`` (near neither edge line; inf: no band)."""
    half_pi = 0.5 * np.pi
    # The columns' phases, their cosines and sines and the mirror rule, once per step.
    tx0, tx1 = np.empty(x1 - x0), np.empty(x1 - x0)
    c0, n0, c1, n1 = np.empty(x1 - x0), np.empty(x1 - x0), np.empty(x1 - x0), np.empty(x1 - x0)
    mirror_x = np.empty(x1 - x0, np.bool_)
    for k in range(x1 - x0):
        dx = x0 + k - qx
        tx0[k], tx1[k] = s00 * dx, s10 * dx
        c0[k], n0[k] = math.cos(tx0[k]), math.sin(tx0[k])
        c1[k], n1[k] = math.cos(tx1[k]), math.sin(tx1[k])
        mirror_x[k] = abs(dx) <= mx
    g00 = g01 = g11 = g0p = g1p = 0.0
    for y in range(y0, y1):
        dy = y - qy
        if not abs(dy) <= my:
            continue
        ty0, ty1 = s01 * dy, s11 * dy
        cy0, ny0, cy1, ny1 = math.cos(ty0), -math.sin(ty0), math.cos(ty1), -math.sin(ty1)
        py = y - oy
        for x in range(x0, x1):
            k = x - x0
            if not mirror_x[k]:
                continue
            a, b = tx0[k], tx1[k]
            if not (a <= half_pi - ty0 and a >= -half_pi - ty0
                    and b <= half_pi - ty1 and b >= -half_pi - ty1):
                continue
            if not ((a <= band0 - ty0 and a >= -band0 - ty0)
                    or (b <= band1 - ty1 and b >= -band1 - ty1)):
                continue
            w = (cy0 * c0[k] + ny0 * n0[k]) * (cy1 * c1[k] + ny1 * n1[k])
            w *= w
            px = x - ox
            gx = 0.5 * (patch[py + 1, px + 2] - patch[py + 1, px])
            gy = 0.5 * (patch[py + 2, px + 1] - patch[py, px + 1])
            gp = gx * px + gy * py
            g00 += w * (gx * gx)
            g01 += w * (gx * gy)
            g11 += w * (gy * gy)
            g0p += w * (gx * gp)
            g1p += w * (gy * gp)
    return g00, g01, g11, g0p, g1p
