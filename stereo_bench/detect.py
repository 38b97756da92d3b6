"""Pattern detection: find a board's feature points in an image, in ``object_points()`` order.

This is the measuring instrument of the benchmark, so it works as a careful user would: OpenCV's
detectors find the board, the board's own appearance (never the ground truth) fixes the order, and
the points are then measured as precisely as the image allows.

* Checkerboard, ``"classic"`` (default): findChessboardCorners, then every corner re-measured by
  the saddle fit below.  ``"sb"``: findChessboardCornersSB with CALIB_CB_ACCURACY and its own
  subpixel result (OpenCV 5.0 returns it in reverse order).  On clean renders of the paper's
  wide-angle camera classic is about 4x more accurate (see benchmarks/detection_accuracy.py); SB
  is kept to measure what the choice costs.
* Circle grids, ``"grid"``: findCirclesGrid (retried with CALIB_CB_CLUSTERING, which copes with
  stronger perspective) with a blob detector sized from the image and the board; the returned
  grid must be locally affine (a mis-ordered grid is rejected), and every centre is re-measured at
  full resolution as the darkness centroid of its disc, with windows sized by the discs' diameter
  as measured in the image (the pattern's ``diameter_mm`` is only the first guess;
  ``measure_disc_diameter`` measures it over a set of images).  A disc cut by the image border,
  or without paper around it inside the board's outline, whose centroid would be biased, becomes
  a NaN row.  That is the centroid of the imaged ellipse, which is not the image of the circle's
  centre under perspective: the bias is what circle boards really cost, and it is kept, not
  corrected.
* ChArUco, ``"charuco"``: cv2.aruco.CharucoDetector, then each corner re-measured by the saddle
  fit restricted to the square edges, which keeps the markers out of it.  Partial boards are
  allowed (unseen corners are NaN rows); fewer than ``MIN_CHARUCO_CORNERS`` corners count as not
  found.

Saddle fit (``_refine_saddles``, both corner boards).  Real boards have no white quiet zone: they
are printed or cut to (or into) their outer squares and lie on a dark frame or in a hand.  A
corner is measured only from image content known to be the board's: a Förstner fit over a
window laid out on the grid (through the local board -> image map of its neighbours), short of
the next grid line and, beside the outer squares, of where the image shows the print to end.
On OpenCV's sample stereo images (benchmarks/real_detection.py) the opencv method's RPE is
0.173 / 0.172 px on these corners, against 0.655 / 0.811 with cornerSubPix and a window of half a
square, and 0.408 / 0.458 with OpenCV's own pipeline (whose 11 x 11 window is pulled on 12-13
corners per camera too); tests/test_detect_margin.py renders the failure for all four boards.

Orientation.  The 9 x 12 checkerboard is not 180-degree symmetric in colour (the square diagonally
beyond corner 0 is black, the one beyond the last corner white), so its order is read from the
image whatever the roll.  ChArUco ids and the asymmetric grid (odd row count) are unambiguous.  A
symmetric circle grid has no cue at all: its orientation is defined only up to its symmetry (180
degrees, and 90 degrees when square) and is fixed by convention: the row direction (point 0 ->
point 1) is the one closest to the image's +x axis, i.e. point 0 is the grid corner nearest the
image's top-left.  The order is right for views rolled less than 90 degrees from upright (45 for
the square 10 x 10 grid) and turned beyond; ``detection_errors`` counts such flips against the
truth.

Search and measurement.  The search runs on a copy whose longest side is at most
``SEARCH_MAX_SIDE`` px (findChessboardCornersSB takes > 20 s on 4096 x 3072; ChArUco's markers of a
small image are searched on a copy enlarged to ``CHARUCO_MIN_SEARCH_SIDE``), and every point is
then measured on the full image: the saddle fit for checkerboard corners (SB's included when the
copy was shrunk); for ChArUco the markers found on the copy, scaled back, go to CharucoDetector, which
interpolates the corners on the full image before the saddle fit; circle centres are always
re-measured at full resolution (a centroid needs only a window, which the scaled-back estimate
places to well under a pixel).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from .patterns import AsymmetricCircles, Charuco, Checkerboard, Pattern, SymmetricCircles
from .rundir import read_arrays, write_npz

SEARCH_MAX_SIDE = 1600
CHARUCO_MIN_SEARCH_SIDE = 1920  # markers of small images are searched on an enlarged copy
MIN_CHARUCO_CORNERS = 6
CHARUCO_SIGMA = 0.8
# The cross of edge bands holds few pixels: longer arms than the checkerboard's (0.5 square)
# took the wide camera's mean error from 0.071 px to 0.058 (24 clean frames: 8 of them).
CHARUCO_REACH = 0.8
DISC_GUARD_PX = 2.0
MAX_WINDOW_PX = 30.0  # half-extent cap of the saddle fit's window along a grid axis
_SADDLE_MARGIN = 3  # px a saddle window may move before its gradient patch is re-cut
METHODS = {
    "checkerboard": ("classic", "sb"),
    "symmetric_circles": ("grid",),
    "asymmetric_circles": ("grid",),
    "charuco": ("charuco",),
}


@dataclass(frozen=True, eq=False)
class Detection:
    """One image's result: ``points`` (N, 2) float64 px in ``object_points()`` order, NaN rows for
    points not seen; ``ids`` (N,) the board's feature ids; ``error`` says why ``found`` is False."""

    points: np.ndarray
    ids: np.ndarray
    found: bool
    error: str | None = None


def _failed(pattern: Pattern, reason: str) -> Detection:
    n = len(pattern.ids())
    return Detection(np.full((n, 2), np.nan), pattern.ids(), False, reason)


def resolve_method(pattern: Pattern, method: str | None) -> str:
    """The method name to use for ``pattern`` (its first method when None); raises on a bad name."""
    methods = METHODS.get(pattern.kind)
    if methods is None:
        raise ValueError(f"no detector for pattern kind {pattern.kind!r}; known: {list(METHODS)}")
    if method is None:
        return methods[0]
    if method not in methods:
        raise ValueError(f"detection method {method!r} does not apply to {pattern.kind}; "
                         f"expected one of {list(methods)}")
    return method


def detect(image: np.ndarray, pattern: Pattern, method: str | None = None) -> Detection:
    """Detect ``pattern`` in an 8-bit grayscale (H, W) or BGR (H, W, 3) image.

    A board that is not found gives ``found=False`` with the reason; bad input raises ValueError.
    """
    method = resolve_method(pattern, method)
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.shape[2:] not in ((), (3,)):
        raise ValueError(f"detect: expected an 8-bit (H, W) or (H, W, 3) image, got "
                         f"{image.dtype} {image.shape}")
    gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
    # The detectors look for dark features on a light board: an inverted board is searched in
    # the inverted image, and a board not found as described is also tried in the other
    # polarity (an inverted board nobody said was inverted; a print seen against the light).
    first = 255 - gray if pattern.inverted else gray
    found = _detect_in(first, pattern, method)
    if found.found:
        return found
    other = _detect_in(255 - first, pattern, method)
    if other.found or pattern.kind != "charuco":
        return other if other.found else found
    # A one-sided ChArUco print seen from behind (through thin paper or acrylic) is its mirror
    # image, whose markers read as no id; mirrored back, each corner keeps its id, so it is the
    # same board point. A chessboard or circle grid mirrored is found in the image as it is.
    for polarity in (first, 255 - first):
        back = _detect_in(np.ascontiguousarray(polarity[:, ::-1]), pattern, method)
        if back.found:
            points = back.points.copy()
            points[:, 0] = gray.shape[1] - 1 - points[:, 0]  # pixel centres: x -> W - 1 - x
            return Detection(points, back.ids, True)
    return found


def _detect_in(gray, pattern: Pattern, method: str) -> Detection:
    try:
        if pattern.kind == "checkerboard":
            return _detect_checkerboard(gray, _SearchImage.of(gray), pattern, method)
        if pattern.kind == "charuco":
            return _detect_charuco(gray, _SearchImage.of(gray, CHARUCO_MIN_SEARCH_SIDE), pattern)
        return _detect_circles(gray, _SearchImage.of(gray), pattern)
    except cv2.error as e:  # OpenCV asserts on some degenerate candidate sets: a failed frame
        return _failed(pattern, f"OpenCV error: {e.err or e}")


# ----------------------------------------------------------------------------- search image
@dataclass(frozen=True)
class _SearchImage:
    """The rescaled copy the detectors search, and the map back to full resolution."""

    image: np.ndarray
    scale: tuple[float, float]  # (sx, sy): search px per full-resolution px

    @classmethod
    def of(cls, gray: np.ndarray, min_side: int = 0) -> "_SearchImage":
        """A copy shrunk to ``SEARCH_MAX_SIDE`` if the image is longer, else enlarged to
        ``min_side`` if shorter (the identity otherwise)."""
        height, width = gray.shape
        longest = max(height, width)
        s = SEARCH_MAX_SIDE / longest if longest > SEARCH_MAX_SIDE else max(min_side / longest, 1.0)
        if s == 1.0:
            return cls(gray, (1.0, 1.0))
        size = (round(width * s), round(height * s))
        # INTER_AREA averages whole source pixels (no aliasing of sharp edges when shrinking);
        # cubic interpolation keeps edges steep when enlarging.
        small = cv2.resize(gray, size, interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_CUBIC)
        return cls(small, (size[0] / width, size[1] / height))

    @property
    def downscaled(self) -> bool:
        return self.scale[0] < 1.0

    def to_full(self, points: np.ndarray) -> np.ndarray:
        """Search-image px (..., 2) -> full-resolution px, both with OpenCV's pixel centres."""
        return (np.asarray(points, np.float64) + 0.5) / np.array(self.scale) - 0.5


# ----------------------------------------------------------------------------- local geometry
def _leave_one_out(object_xy: np.ndarray, points: np.ndarray, radius_mm: float) -> np.ndarray:
    """(N,) how far each point lies from where its neighbours (within ``radius_mm``, the point
    itself left out) put it by an affine fit, in board mm; NaN where it cannot be predicted."""
    out = np.full(len(points), np.nan)
    seen = np.isfinite(points).all(axis=1)
    near = np.linalg.norm(object_xy[:, None] - object_xy[None], axis=-1) <= radius_mm
    for i in np.flatnonzero(seen):
        nb = np.flatnonzero(near[i] & seen)
        nb = nb[nb != i]
        if len(nb) < 3:  # an affine map needs three (a board corner has exactly three)
            continue
        X = np.column_stack([object_xy[nb] - object_xy[i], np.ones(len(nb))])
        sol = np.linalg.lstsq(X, points[nb], rcond=None)[0]  # rows: d/dx, d/dy, value at i
        out[i] = np.linalg.norm(sol[2] - points[i]) / np.linalg.norm(sol[:2], 2)
    return out


def _drop_grid_outliers(object_xy: np.ndarray, points: np.ndarray, step_mm: float) -> np.ndarray:
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


def _local_affines(object_xy: np.ndarray, points: np.ndarray, radius_mm: float):
    """Board-mm -> px linear maps at each point, fitted to its neighbours within ``radius_mm``.

    Least squares on the differences to the point itself.  Returns (N, 2, 2) maps (NaN where the
    point is missing or has fewer than two non-collinear neighbours) and (N,) misfits: the largest
    residual of a neighbour, expressed in board mm (residual px / the map's largest stretch).
    """
    affines = np.full((len(points), 2, 2), np.nan)
    misfit = np.full(len(points), np.nan)
    seen = np.isfinite(points).all(axis=1)
    for i in np.flatnonzero(seen):
        near = seen & (np.linalg.norm(object_xy - object_xy[i], axis=1) <= radius_mm)
        near[i] = False
        d_obj, d_img = object_xy[near] - object_xy[i], points[near] - points[i]
        if len(d_obj) < 2 or np.linalg.matrix_rank(d_obj) < 2:
            continue
        A = np.linalg.lstsq(d_obj, d_img, rcond=None)[0].T
        affines[i] = A
        misfit[i] = np.linalg.norm(d_obj @ A.T - d_img, axis=1).max() / np.linalg.norm(A, 2)
    return affines, misfit


def _nearest_mm(object_xy: np.ndarray) -> float:
    """Distance from a board's first feature point to its nearest neighbour (the lattice step)."""
    return float(np.min(np.linalg.norm(object_xy[1:] - object_xy[0], axis=1)))


# ----------------------------------------------------------------------------- saddle points
def _blurred_box(gray, x0: int, y0: int, x1: int, y1: int, sigma: float):
    """``gray`` blurred with ``sigma`` px (float32) over the box [x0, x1) x [y0, y1) cut to the
    image, and the cut box's top-left pixel (x, y); None if the box misses the image.

    The copy blurred carries the kernel's reach of context on every side inside the image, so the
    values are those of the whole image blurred (both reflect at the image's own border): blurring
    a few windows costs little where the whole 4096 x 3072 frame cost more than the fit itself.
    """
    height, width = gray.shape
    bx0, by0, bx1, by1 = max(x0, 0), max(y0, 0), min(x1, width), min(y1, height)
    if bx1 <= bx0 or by1 <= by0:
        return None
    context = math.ceil(4 * sigma) + 1  # OpenCV's float kernel reaches round(4 sigma) px
    sx0, sy0 = max(bx0 - context, 0), max(by0 - context, 0)
    sx1, sy1 = min(bx1 + context, width), min(by1 + context, height)
    blurred = cv2.GaussianBlur(gray[sy0:sy1, sx0:sx1].astype(np.float32), (0, 0), sigma)
    return blurred[by0 - sy0:by1 - sy0, bx0 - sx0:bx1 - sx0], (bx0, by0)


def _print_extent(gray, q, A, axis, sign, square_mm, perp_mm, sigma, samples: int = 40) -> float:
    """How far (board mm, up to one square) the print visibly goes on from corner ``q`` (px)
    along grid axis ``axis`` (0: x, 1: y) in direction ``sign``, seen in ``gray`` blurred with
    ``sigma``.

    Beyond an edge corner lie the two outer squares on either side of the grid line through it,
    one black and one white as long as the print goes on.  Their grey levels are sampled (bilinear)
    at ``perp_mm`` on either side of that line, from 0.15 square (clear of the other line's blur)
    out to one square; the print ends where their contrast falls below half its value near the
    corner (beyond it both samples see the same surround, or the same occluder).  Samples off the
    image are NaN, which ends the print there.
    """
    t = np.linspace(0.15, 1.0, samples)
    e = np.eye(2)
    along = q + (sign * t[:, None] * square_mm * e[axis]) @ A.T
    side = perp_mm * e[1 - axis] @ A.T
    xy = np.concatenate([along + side, along - side])
    lo, hi = np.floor(xy.min(0)).astype(int) - 1, np.ceil(xy.max(0)).astype(int) + 2
    box = _blurred_box(gray, lo[0], lo[1], hi[0], hi[1], sigma)
    if box is None:
        return 0.0
    patch, origin = box
    xy = (xy - origin).astype(np.float32)
    values = cv2.remap(patch, xy[:, :1], xy[:, 1:], cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan).ravel()
    contrast = np.abs(values[:samples] - values[samples:])
    reference = np.median(contrast[t <= 0.3])
    if not reference > 0:
        return 0.0
    ends = np.flatnonzero(~(contrast >= 0.5 * reference))
    return square_mm if len(ends) == 0 else float(t[ends[0]]) * square_mm


def _refine_saddles(gray, points: np.ndarray, object_xy: np.ndarray, square_mm: float,
                    sigma: float, band_mm: float | None = None, reach: float = 0.5,
                    iterations: int = 20) -> np.ndarray:
    """Re-measure corners (N, 2) px with a saddle fit that only sees the board's own squares.

    cornerSubPix (Förstner & Gülch 1987) finds the point q that every gradient g at pixels p in a
    window is orthogonal to, least squares: (sum w g g^T) q = sum w g g^T p.  Its square window
    of half a square reaches, at an edge corner of a sheared view, the surround beside the outer
    squares when the print has no margin or is cut into them (OpenCV's sample stereo images:
    3-6 corners of an end column 1.5-9 px off), or an occluder beside the board.  Here the
    window is a parallelogram in board units, through the local board -> image map fitted to the
    neighbouring corners (``_local_affines``): |u|, |v| within ``reach`` square of the corner, and
    ``guard`` px (3 sigma + 2: the blur and the gradient's stencil) short of the next grid line
    or, where there is no neighbouring corner, of where the print is seen to end
    (``_print_extent``).  Both extents are taken symmetric (the shorter side rules), so the
    window stays point-symmetric about q, as a saddle is; where the image border cuts it, only
    pixels whose mirror through q is inside count.  The weights, cos^2 along u times along v,
    fall to zero at the window's sides, so no pixel jumps in or out as q moves.  ``band_mm``
    keeps only pixels within that distance of the two edge lines (ChArUco: the markers' borders
    stay out).  Gradients are central differences on a copy blurred with ``sigma`` px.
    On clean renders of the wide camera (tests/test_detect.py's views) this measured the
    checkerboard to 0.010 px mean (cornerSubPix with the old window: 0.013) and ChArUco to
    0.020 px (0.028) with ``reach`` 0.8 (its cross of bands holds few pixels).  A corner without a local map keeps its estimate; one whose fit fails,
    does not converge or moves by more than a quarter square is NaN (not measured).
    """
    affines, _ = _local_affines(object_xy, points, 1.5 * square_mm)
    guard = 3.0 * sigma + 2.0
    perp_mm = band_mm if band_mm is not None else 0.3 * square_mm
    height, width = gray.shape
    refined = points.copy()
    seen = np.flatnonzero(np.isfinite(affines[:, 0, 0]))
    A = affines[seen]
    A_inv = np.linalg.inv(A)
    cells = np.round(object_xy / square_mm).astype(int)
    known = {tuple(c) for c in cells[np.isfinite(points).all(axis=1)]}
    extent = np.full((len(seen), 2), square_mm)
    for m, i in enumerate(seen):
        for k in range(2):
            for sign in (-1, 1):
                if tuple(cells[i] + sign * np.eye(2, dtype=int)[k]) not in known:
                    extent[m, k] = min(extent[m, k], _print_extent(
                        gray, points[i], A[m], k, sign, square_mm, perp_mm, sigma))
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
    # All corners iterate together, on a stack of gradient patches that hold each one's window
    # with _SADDLE_MARGIN px to spare; a corner whose window moves out gets a new patch and goes on.
    pending = np.arange(len(seen))
    while len(pending):
        origin = np.floor(q[pending] - half[pending]).astype(int) - _SADDLE_MARGIN
        size = int((np.ceil(q[pending] + half[pending]) + 1 - origin).max()) + _SADDLE_MARGIN
        moments = _gradient_moments(gray, origin, size, sigma)
        live = np.arange(len(pending))  # rows of the stack still iterating on it
        moved_out = []
        while len(live):
            c = pending[live]
            box_lo = np.maximum(np.floor(q[c] - half[c]), 1).astype(int)
            box_hi = np.minimum(np.ceil(q[c] + half[c]) + 1, [width - 1, height - 1]).astype(int)
            failed = (box_hi <= box_lo).any(1)
            out = ~failed & ((box_lo < origin[live]) | (box_hi > origin[live] + size)).any(1)
            moved_out.extend(c[out])
            live, c, box_lo, box_hi = (a[~failed & ~out] for a in (live, c, box_lo, box_hi))
            if not len(live):
                break
            shift, solvable = _saddle_steps(moments[live], origin[live], q[c], A_inv[c],
                                            lim[c], box_lo, box_hi, band_mm, (width, height))
            q[c[solvable]] += shift[solvable]
            steps[c] += 1
            ok[c[solvable]] = np.linalg.norm(shift[solvable], axis=1) < 1e-4
            live = live[solvable & ~ok[c] & (steps[c] < iterations)]
        pending = np.array(moved_out, dtype=int)
    moved = np.linalg.norm(np.einsum("mij,mj->mi", A_inv, q - start), axis=1)
    refined[seen] = np.where((ok & (moved < 0.25 * square_mm))[:, None], q, np.nan)
    return refined


def _gradient_moments(gray, origin: np.ndarray, size: int, sigma: float) -> np.ndarray:
    """Per pixel of the squares of ``size`` px whose top-left pixels are ``origin`` (M, 2) (x, y):
    (M, size * size, 5) float64 [gx gx, gx gy, gy gy, gx (gx x + gy y), gy (gx x + gy y)], with
    (gx, gy) the gradient (central differences) of ``gray`` blurred with ``sigma`` and (x, y)
    the pixel relative to the square's top-left; zero where it would need pixels off the image.

    Every sum of the saddle fit is a weighted sum of these, so an iteration is one product with
    the weights: the gradients are computed once however often the window moves.
    """
    blurred = np.zeros((len(origin), size + 2, size + 2))
    for k, (x, y) in enumerate(origin):
        box = _blurred_box(gray, x - 1, y - 1, x + size + 1, y + size + 1, sigma)
        if box is not None:
            patch, (bx, by) = box
            blurred[k, by - y + 1:by - y + 1 + patch.shape[0],
                    bx - x + 1:bx - x + 1 + patch.shape[1]] = patch
    gx = 0.5 * (blurred[:, 1:-1, 2:] - blurred[:, 1:-1, :-2])
    gy = 0.5 * (blurred[:, 2:, 1:-1] - blurred[:, :-2, 1:-1])
    xs = np.arange(size)
    g_dot_p = gx * xs + gy * xs[:, None]
    return np.stack([gx * gx, gx * gy, gy * gy, gx * g_dot_p, gy * g_dot_p],
                    -1).reshape(len(origin), size * size, 5)


def _saddle_steps(moments, origin, q, A_inv, lim, box_lo, box_hi, band_mm, image_size):
    """One step of the saddle fit for M corners at once: shifts (M, 2) px and whether each
    corner's normal matrix was well enough conditioned to solve (M,) bool.

    ``moments`` (M, S * S, 5): ``_gradient_moments`` of squares with top-left pixels ``origin``
    (M, 2); ``q`` (M, 2) the current estimates; ``A_inv`` (M, 2, 2) px -> board mm; ``lim``
    (M, 2) the window's half-extents in mm; ``box_lo``, ``box_hi`` (M, 2) its bounding box (end
    exclusive) in px.
    """
    size = math.isqrt(moments.shape[1])
    width, height = image_size
    pixels = origin[:, :, None] + np.arange(size)  # (M, 2, S): x then y coordinates
    dx, dy = pixels[:, 0] - q[:, :1], pixels[:, 1] - q[:, 1:]  # (M, S) offsets from q
    # Only pixels whose mirror image through q is in the image too: a window cut by the image
    # border stays point-symmetric, as the saddle is.
    mirrored = np.minimum(q, [width - 1, height - 1] - q)
    in_x = ((pixels[:, 0] >= box_lo[:, :1]) & (pixels[:, 0] < box_hi[:, :1])
            & (np.abs(dx) <= mirrored[:, :1]))
    in_y = ((pixels[:, 1] >= box_lo[:, 1:]) & (pixels[:, 1] < box_hi[:, 1:])
            & (np.abs(dy) <= mirrored[:, 1:]))
    use = in_x[:, None, :] & in_y[:, :, None]  # (M, S rows of y, S columns of x)
    # The weight's phases, pi/2 at the window's sides: theta = pi/2 (A_inv p) / lim is a sum of
    # a term in x and one in y, so their cosines come from (M, S) cosines and sines of each.
    scale = 0.5 * np.pi * A_inv / lim[:, :, None]
    w = np.ones(use.shape)
    near_edges = np.zeros(use.shape, bool)  # within band_mm of either edge line
    for axis in range(2):
        tx, ty = scale[:, axis, :1] * dx, scale[:, axis, 1:] * dy
        theta = np.abs(tx[:, None, :] + ty[:, :, None])
        use &= theta <= 0.5 * np.pi
        if band_mm is not None:
            near_edges |= theta < 0.5 * np.pi * band_mm / lim[:, axis, None, None]
        w *= (np.cos(tx)[:, None, :] * np.cos(ty)[:, :, None]
              - np.sin(tx)[:, None, :] * np.sin(ty)[:, :, None]) ** 2
    if band_mm is not None:
        use &= near_edges
    w *= use
    sums = np.matmul(w.reshape(len(q), 1, -1), moments)[:, 0]  # (M, 5)
    normal = sums[:, [0, 1, 1, 2]].reshape(-1, 2, 2)
    # sum w g g^T (p - q), the pixel p relative to the square's top-left.
    rhs = sums[:, 3:] - (normal @ (q - origin)[:, :, None])[..., 0]
    solvable = np.linalg.cond(normal) <= 1e6
    shift = np.zeros_like(q)
    shift[solvable] = np.linalg.solve(normal[solvable], rhs[solvable, :, None])[..., 0]
    return shift, solvable


# ----------------------------------------------------------------------------- checkerboard
def _detect_checkerboard(gray, search: _SearchImage, pattern: Checkerboard,
                         method: str) -> Detection:
    size = pattern.pattern_size
    if method == "sb":
        ok, corners = cv2.findChessboardCornersSB(search.image, size, flags=cv2.CALIB_CB_ACCURACY)
    else:
        ok, corners = cv2.findChessboardCorners(search.image, size)
    if not ok:
        name = "findChessboardCornersSB" if method == "sb" else "findChessboardCorners"
        return _failed(pattern, f"{name} found no {size[0]}x{size[1]} inner-corner grid")
    points = search.to_full(corners.reshape(-1, 2))
    if method == "sb":
        points = points[::-1]  # OpenCV 5.0's SB starts at the opposite corner (patterns.py)
    if method == "classic" or search.downscaled:  # SB's own subpixel result is kept at full size
        points = _refine_saddles(gray, points, pattern.object_points()[:, :2], pattern.square_mm,
                                 _checkerboard_sigma(points, pattern.pattern_size))
    points = _orient_checkerboard(gray, points, pattern)
    return Detection(_drop_grid_outliers(pattern.object_points()[:, :2], points,
                                         pattern.square_mm), pattern.ids(), True)


def _checkerboard_sigma(points: np.ndarray, pattern_size: tuple[int, int]) -> float:
    """Blur for the saddle fit: 1.5 px, below a tenth of the shortest grid step (row, column or
    diagonal) in the image."""
    cols, rows = pattern_size
    grid = points.reshape(rows, cols, 2)
    steps = [grid[:, 1:] - grid[:, :-1], grid[1:] - grid[:-1],
             grid[1:, 1:] - grid[:-1, :-1], grid[1:, :-1] - grid[:-1, 1:]]
    step = min(float(np.linalg.norm(s, axis=-1).min()) for s in steps)
    return min(1.5, 0.1 * step)


def _mean_around(gray, centre: np.ndarray, radius: float) -> float | None:
    """Mean grey level of a square patch around ``centre``; None if it leaves the image."""
    height, width = gray.shape
    r = max(radius, 1.0)
    if not (r <= centre[0] <= width - 1 - r and r <= centre[1] <= height - 1 - r):
        return None
    side = 2 * int(r) + 1
    return float(cv2.getRectSubPix(gray, (side, side), tuple(map(float, centre))).mean())


def _orient_checkerboard(gray, points: np.ndarray, pattern: Checkerboard) -> np.ndarray:
    """Order ``points`` so that corner 0 is the one whose outer diagonal square is black.

    Beyond an end corner, the square diagonally outward and the square outward along the row only
    (one step further in, along the column) have opposite colours; their difference in grey level
    says which is black, independent of lighting.  Object order has the black diagonal square at
    corner 0 and, for an odd + even square count, a white one at the last corner: both ends vote.
    A board with colours symmetric under 180 degrees (both counts odd or both even), or one whose
    end squares are out of the image, falls back to the convention of symmetric circle grids.
    """
    cols, rows = pattern.pattern_size
    grid = points.reshape(rows, cols, 2)
    votes = []
    for corner, row_step, col_step, sign in (
        (grid[0, 0], grid[0, 1] - grid[0, 0], grid[1, 0] - grid[0, 0], 1.0),
        (grid[-1, -1], grid[-1, -2] - grid[-1, -1], grid[-2, -1] - grid[-1, -1], -1.0),
    ):
        radius = 0.2 * min(np.linalg.norm(row_step), np.linalg.norm(col_step))
        diagonal = _mean_around(gray, corner - 0.5 * row_step - 0.5 * col_step, radius)
        beside = _mean_around(gray, corner - 0.5 * row_step + 0.5 * col_step, radius)
        if diagonal is not None and beside is not None:
            votes.append(sign * (beside - diagonal))  # > 0: a vote for object order
    colour_symmetric = (pattern.squares_x + pattern.squares_y) % 2 == 0
    if colour_symmetric or not votes:
        return _upright(points, pattern.pattern_size, quarter_turns=False)
    return points if sum(votes) > 0 else points[::-1]


def _upright(points: np.ndarray, pattern_size: tuple[int, int], quarter_turns: bool) -> np.ndarray:
    """Among the grid's symmetries (180 degrees; 90 too when ``quarter_turns``), the ordering whose
    row direction (point 0 -> point 1, averaged over the grid) is closest to the image's +x axis."""
    cols, rows = pattern_size
    index = np.arange(cols * rows).reshape(rows, cols)
    candidates = [np.rot90(index, k) for k in (range(4) if quarter_turns else (0, 2))]

    def alignment(order: np.ndarray) -> float:
        row_dir = np.diff(points[order], axis=1).mean(axis=(0, 1))
        return row_dir[0] / np.linalg.norm(row_dir)

    return points[max(candidates, key=alignment).ravel()]


# ----------------------------------------------------------------------------- circle grids
def _blob_detector(search: _SearchImage, pattern: SymmetricCircles | AsymmetricCircles):
    """SimpleBlobDetector sized for this board in this image.

    The default maxArea (5000 px^2) drops the discs of a board seen close up.  Largest disc: the
    feature span (centre to centre, plus one diameter) fills twice the image diagonal, which a
    tilted board near the camera can approach on its near side; smallest: 4 px across, below which
    neither the blob detector nor a centroid is trustworthy.  The default 10 px minimum distance
    between blobs would merge the discs of a far board.
    """
    span_mm = np.ptp(pattern.object_points()[:, :2], axis=0).min() + pattern.diameter_mm
    largest = 2.0 * math.hypot(*search.image.shape) * pattern.diameter_mm / span_mm
    params = cv2.SimpleBlobDetector_Params()
    params.minArea = math.pi * 2.0**2
    params.maxArea = math.pi * (largest / 2) ** 2
    params.minDistBetweenBlobs = 2.0
    return cv2.SimpleBlobDetector_create(params)


def _detect_circles(gray, search: _SearchImage, pattern: SymmetricCircles | AsymmetricCircles):
    found = _find_circle_grid(search, pattern)
    if isinstance(found, str):
        return _failed(pattern, found)
    return Detection(_measured_discs(gray, *found, pattern)[0], pattern.ids(), True)


def _measured_discs(gray, points: np.ndarray, affines: np.ndarray, pattern, passes: int = 4):
    """``_measure_discs`` with windows sized by the discs as imaged: a first pass with the
    pattern's diameter_mm, then again with this image's median measured diameter while that
    differs from the one used by more than 1 % (at most ``passes`` in all), so a pattern whose
    diameter is off still gets windows that hold its discs and their paper.  A window too small
    cuts the blurred rim and under-measures, so a guess 20 % small takes three passes."""
    used = pattern.diameter_mm
    for _ in range(passes):
        centres, diameters = _measure_discs(gray, points, affines, pattern, used)
        if not np.isfinite(diameters).any():
            break
        measured = float(np.nanmedian(diameters))
        if abs(measured / used - 1) <= 0.01:
            break
        used = measured
    return centres, diameters


def measure_disc_diameter(images, pattern: SymmetricCircles | AsymmetricCircles) -> float:
    """The discs' diameter in mm, measured from images of a circle grid whose spacing is known.

    ``images``: 8-bit grey (H, W) or BGR (H, W, 3) arrays; ``pattern.diameter_mm`` need only be
    a rough guess (it sizes the first measuring window; within about -20 %/+60 % of the truth).
    Each disc's darkness summed over its window, over the darkness of its core, is its imaged
    area (blur moves darkness about but keeps its sum); the local board -> image map fitted to
    the neighbouring centres (``_local_affines``) takes it to board mm^2, and the diameter of the
    circle of that area is the disc's.  The result is the median over every disc measured in every
    image (discs cut by the image or the print's edge are left out).  Raises ValueError if the
    pattern is not a circle grid or no disc could be measured.
    """
    if not isinstance(pattern, (SymmetricCircles, AsymmetricCircles)):
        raise ValueError(f"measure_disc_diameter: pattern must be a circle grid, got "
                         f"{pattern.kind!r}")
    diameters = []
    for k, image in enumerate(images):
        image = np.asarray(image)
        if image.dtype != np.uint8 or image.shape[2:] not in ((), (3,)):
            raise ValueError(f"measure_disc_diameter: image {k}: expected an 8-bit (H, W) or "
                             f"(H, W, 3) image, got {image.dtype} {image.shape}")
        gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
        found = _find_circle_grid(_SearchImage.of(gray), pattern)
        if not isinstance(found, str):
            diameters.append(_measured_discs(gray, *found, pattern)[1])
    measured = np.concatenate(diameters) if diameters else np.array([])
    if not np.isfinite(measured).any():
        raise ValueError(f"measure_disc_diameter: no disc of the {pattern.kind} grid could be "
                         f"measured in the {len(diameters)} image(s) where it was found")
    return float(np.nanmedian(measured))


def _find_circle_grid(search: _SearchImage, pattern: SymmetricCircles | AsymmetricCircles):
    """(points (N, 2) full-resolution px in object order, local affines) or the failure reason.

    The default grid finder fails on some clean, moderately tilted views that clustering finds;
    clustering in turn sometimes returns a scrambled order, which the affine check rejects.
    """
    symmetric = isinstance(pattern, SymmetricCircles)
    grid = cv2.CALIB_CB_SYMMETRIC_GRID if symmetric else cv2.CALIB_CB_ASYMMETRIC_GRID
    cols, rows = pattern.pattern_size
    object_xy = pattern.object_points()[:, :2]
    step_mm = _nearest_mm(object_xy)
    blobs = _blob_detector(search, pattern)
    kind = "symmetric" if symmetric else "asymmetric"
    reason = f"findCirclesGrid found no {cols}x{rows} {kind} circle grid"
    for flags in (grid, grid | cv2.CALIB_CB_CLUSTERING):
        ok, centres = cv2.findCirclesGrid(search.image, pattern.pattern_size, flags=flags,
                                          blobDetector=blobs)
        if not ok:
            continue
        points = search.to_full(centres.reshape(-1, 2))
        if symmetric:
            points = _upright(points, pattern.pattern_size, quarter_turns=cols == rows)
        affines, misfit = _local_affines(object_xy, points, 1.5 * step_mm)
        # Even strong perspective and the wide lens leave < 0.14 step of misfit over a point's
        # neighbours (measured on the truth); a mis-ordered grid is off by about a step.
        if np.nanmax(misfit) > 0.3 * step_mm:
            reason = "findCirclesGrid returned a grid whose order is not locally affine"
            continue
        return points, affines
    return reason


def _measure_discs(gray, points: np.ndarray, affines: np.ndarray, pattern, diameter_mm: float,
                   iterations: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Each disc's centre (N, 2) px, the centroid of its darkness, and diameter (N,) mm.

    Through the local board -> image map ``A`` (fitted to the neighbouring centres) each disc
    gets an elliptical window in board units: the disc plus a margin for blur (radius
    1.25 ``diameter_mm`` / 2), and a ring of paper out to half the distance to the nearest disc.
    A plane fitted to the ring gives the local paper white (absorbing shading); the weights
    ``white - I`` then make the centroid the area centroid of the imaged disc, as exact as the
    image's anti-aliasing.  The window is re-centred on the new estimate a few times, so the
    starting estimate need only be good to a fraction of the radius.  Nothing beyond the board
    enters: the ring keeps only pixels inside the pattern's outline (``outline_mm``, its
    ``margin_mm`` included, less ``DISC_GUARD_PX``) and the disc window is cut point-symmetrically
    about the estimate to that outline, so a window that must be cut is cut on both sides.  A disc
    with less than its radius of paper to the outline (an outer disc of a board printed with
    ``margin_mm=0``) or cut by the image border has no trustworthy centroid: its row is NaN.
    On 24 clean wide-camera renders per grid this measured the exact imaged-disc centroid to
    0.002-0.003 px mean (0.013 px max); the blob detector's own centres were off it by
    0.015-0.017 px mean (0.08 px max).
    Diameter: the window's summed darkness over the darkness of the disc's core (inside half
    its radius) is the imaged disc's area in px^2 (blur moves darkness about but keeps its sum),
    |det A^-1| takes it to board mm^2; the circle of that area has the disc's diameter.  NaN for
    discs whose window is cut.
    """
    object_xy = pattern.object_points()[:, :2]
    r_disc = diameter_mm / 2
    r_inner, r_outer = 1.25 * r_disc, 0.5 * _nearest_mm(object_xy)
    print_lo, print_hi = pattern.outline_mm()[0], pattern.outline_mm()[2]
    height, width = gray.shape
    refined = points.copy()
    diameters = np.full(len(points), np.nan)
    for i, A in enumerate(affines):
        A_inv = np.linalg.inv(A)
        reach = r_outer * np.linalg.norm(A, 2)  # px
        # Board mm per px across the print's sides (x = const, y = const lines).
        guard_mm = DISC_GUARD_PX * np.linalg.norm(A_inv, axis=1)
        room = np.minimum(object_xy[i] - print_lo, print_hi - object_xy[i]) - guard_mm
        if np.any(room < r_disc):  # the disc's rim touches the print's edge: no paper around it
            refined[i] = np.nan
            continue
        disc_reach = r_inner * np.linalg.norm(A, 2)
        # The print's edges (less the guard) in mm from the disc's centre.
        edge_lo, edge_hi = print_lo + guard_mm - object_xy[i], print_hi - guard_mm - object_xy[i]
        for _ in range(iterations):
            cx, cy = refined[i]
            if not (disc_reach <= cx <= width - 1 - disc_reach
                    and disc_reach <= cy <= height - 1 - disc_reach):
                refined[i] = np.nan
                break
            x0, x1 = max(math.floor(cx - reach), 0), min(math.ceil(cx + reach) + 1, width)
            y0, y1 = max(math.floor(cy - reach), 0), min(math.ceil(cy + reach) + 1, height)
            # Offsets from the estimate and board mm from the disc's centre, a row of x and a
            # column of y broadcast over the window (per-axis arithmetic: numpy reduces a
            # trailing axis of two slowly, and the large camera's windows hold 10^4-10^5 px).
            ox, oy = np.arange(x0, x1) - cx, (np.arange(y0, y1) - cy)[:, None]
            bx, by = A_inv[0, 0] * ox + A_inv[0, 1] * oy, A_inv[1, 0] * ox + A_inv[1, 1] * oy
            radius2 = bx * bx + by * by  # mm^2
            patch = gray[y0:y1, x0:x1].astype(np.float64)
            # Paper: the ring, inside the print; the disc window: point-symmetric about the
            # estimate and inside both the print and the image, so what lies beyond the board
            # or the image never enters, and what is cut is cut on both sides.  (A window whose
            # box lies inside either limit, as most do, needs no per-pixel test.)
            box_mm = np.abs(A_inv) @ [max(-ox[0], ox[-1]), max(-oy[0, 0], oy[-1, 0])]
            inside = (np.bool_(True) if np.all(box_mm <= room)
                      else (np.abs(bx) <= room[0]) & (np.abs(by) <= room[1]))
            on_print = (np.bool_(True) if np.all((edge_lo <= -box_mm) & (box_mm <= edge_hi))
                        else ((bx >= edge_lo[0]) & (bx <= edge_hi[0])
                              & (by >= edge_lo[1]) & (by <= edge_hi[1])))
            ring = (radius2 >= r_inner**2) & (radius2 <= r_outer**2) & on_print
            disc = (radius2 < r_inner**2) & inside
            if np.count_nonzero(ring) < 3 or not disc.any():
                refined[i] = np.nan
                break
            # White plane over the ring, least squares through its normal equations.
            ring_y, ring_x = np.nonzero(ring)
            design = np.column_stack([np.ones(len(ring_x)), ox[ring_x], oy[ring_y, 0]])
            plane = np.linalg.lstsq(design.T @ design, design.T @ patch[ring], rcond=None)[0]
            white = plane[0] + plane[1] * ox + plane[2] * oy
            weight = white - patch
            disc_y, disc_x = np.nonzero(disc)
            w = weight[disc]
            refined[i] = (cx + w @ ox[disc_x] / w.sum(), cy + w @ oy[disc_y, 0] / w.sum())
        if not np.isfinite(refined[i]).all():
            continue  # its window left the image or the print (possibly before the first pass)
        core = (radius2 < (0.5 * r_disc) ** 2) & inside
        whole = radius2 < r_inner**2
        if core.any() and not (whole & ~inside).any():
            contrast = np.median(weight[core])
            area_px = weight[whole].sum() / contrast
            diameters[i] = 2 * math.sqrt(area_px * abs(np.linalg.det(A_inv)) / math.pi)
    return refined, diameters


# ----------------------------------------------------------------------------- ChArUco
def _detect_charuco(gray, search: _SearchImage, pattern: Charuco) -> Detection:
    board = pattern.cv_board()
    # Markers are searched on the rescaled copy: ArUco needs a few pixels per marker cell (a 7x7
    # marker of a far board on the 640 px camera has about 1.2), and enlarging the wide camera's
    # images 3x found twice the corners (1493 against 740 of 2112 over 24 clean frames) at no
    # cost in accuracy.  CharucoDetector then interpolates the chessboard corners from the
    # scaled-back markers and refines them on the full image.
    aruco = cv2.aruco.ArucoDetector(board.getDictionary(), cv2.aruco.DetectorParameters())
    markers, marker_ids, _ = aruco.detectMarkers(search.image)
    if marker_ids is None:
        return _failed(pattern, "no ArUco marker of the board was found")
    markers = tuple(search.to_full(m).astype(np.float32) for m in markers)
    # A two-sided board: one side faces the camera; its marker ids tell which.
    side = pattern
    if pattern.two_sided:
        back = pattern.back()
        if np.isin(marker_ids, back.marker_ids()).sum() > np.isin(marker_ids,
                                                                   pattern.marker_ids()).sum():
            side = back
            board = side.cv_board()
    corners, ids, _, _ = cv2.aruco.CharucoDetector(board).detectBoard(
        gray, markerCorners=markers, markerIds=marker_ids)
    if ids is None or len(ids) < MIN_CHARUCO_CORNERS:
        seen = 0 if ids is None else len(ids)
        return _failed(pattern, f"only {seen} ChArUco corners ({len(marker_ids)} markers) found, "
                                f"need {MIN_CHARUCO_CORNERS}")
    points = np.full((len(pattern.ids()), 2), np.nan)
    points[ids.ravel()] = corners.reshape(-1, 2)
    points = _refine_saddles(gray, points, side.object_points()[:, :2], side.square_mm,
                             CHARUCO_SIGMA, band_mm=(side.square_mm - side.marker_mm) / 4,
                             reach=CHARUCO_REACH)
    if side is not pattern:  # the back's corners in the front's order (the board frame)
        front = np.full_like(points, np.nan)
        front[pattern.back_to_front] = points
        points = front
    return Detection(points, pattern.ids(), True)


# ----------------------------------------------------------------------------- datasets
@dataclass(frozen=True, eq=False)
class CameraDetections:
    """One camera's detections over a dataset: ``points`` (F, N, 2) px (NaN where not seen),
    ``found`` (F,) bool, ``ids`` (N,), and ``errors`` {frame: reason} for every frame not found."""

    camera: str
    pattern: str
    method: str
    points: np.ndarray
    found: np.ndarray
    ids: np.ndarray
    errors: dict[int, str] = field(default_factory=dict)

    def save(self, path: str | Path) -> Path:
        """Write a .npz (plain arrays, no pickles) and return its path."""
        path = Path(path)
        frames = sorted(self.errors)
        path = path if path.suffix == ".npz" else path.with_name(path.name + ".npz")
        write_npz(path, camera=self.camera, pattern=self.pattern, method=self.method,
                  points=self.points, found=self.found, ids=self.ids,
                  error_frames=np.array(frames, dtype=np.int64),
                  error_messages=np.array([self.errors[f] for f in frames], dtype=str),
                  opencv_version=cv2.__version__)
        return path

    @classmethod
    def load(cls, path: str | Path) -> "CameraDetections":
        try:
            z = read_arrays(path, "a detections file")
            return cls(str(z["camera"]), str(z["pattern"]), str(z["method"]), z["points"],
                       z["found"], z["ids"],
                       {int(f): str(m) for f, m in zip(z["error_frames"], z["error_messages"])})
        except (FileNotFoundError, TypeError, KeyError, ValueError) as e:
            raise ValueError(f"{path}: not a detections file written by CameraDetections.save "
                             f"({e})") from None


def detect_dataset(dataset, method: str | None = None,
                   progress: Callable[[int, int], None] | None = None) -> list[CameraDetections]:
    """Detect the board in every image of a ``Dataset``; one ``CameraDetections`` per camera.

    A frame that fails (board not found, image missing or unreadable) is recorded with its reason
    and the sweep goes on.  ``progress(done, total)`` is called after each image.
    """
    pattern = dataset.pattern
    method = resolve_method(pattern, method)
    n, frames = len(pattern.ids()), dataset.frames
    total, done = len(dataset.cameras) * frames, 0
    result = []
    for c, camera in enumerate(dataset.cameras):
        points = np.full((frames, n, 2), np.nan)
        found = np.zeros(frames, dtype=bool)
        errors = {}
        for f in range(frames):
            try:
                det = detect(dataset.image(c, f), pattern, method)
            except (OSError, ValueError) as e:  # FileNotFoundError is an OSError
                det = _failed(pattern, str(e))
            points[f], found[f] = det.points, det.found
            if not det.found:
                errors[f] = det.error
            done += 1
            if progress:
                progress(done, total)
        result.append(CameraDetections(camera.name, pattern.kind, method, points, found,
                                       pattern.ids(), errors))
    return result


def detection_errors(det: CameraDetections, gt_points: np.ndarray,
                     gt_visible: np.ndarray) -> dict:
    """Accuracy of one camera's detections against the truth (``gt_points`` (F, N, 2),
    ``gt_visible`` (F, N)).

    A found frame is *flipped* when its points, reversed, fit the truth better than as returned
    (a 180-degree orientation error).  Flipped frames are counted and listed, not repaired, and are
    left out of the distance statistics (their errors are board-sized and would swamp them).
    Distances are over the visible, detected points of the other found frames; ``mean_dx_px`` and
    ``mean_dy_px`` are the signed mean of detected - true.
    """
    gt_points, gt_visible = np.asarray(gt_points), np.asarray(gt_visible, dtype=bool)
    if gt_points.shape != det.points.shape or gt_visible.shape != det.points.shape[:2]:
        raise ValueError(f"detection_errors: detections {det.points.shape} do not match ground "
                         f"truth points {gt_points.shape} / visible {gt_visible.shape}")
    seen = np.isfinite(det.points).all(-1) & det.found[:, None]
    flipped = []
    for f in np.flatnonzero(det.found):
        as_is = _mean_distance(det.points[f], gt_points[f], seen[f] & gt_visible[f])
        reversed_ = _mean_distance(det.points[f, ::-1], gt_points[f],
                                   seen[f, ::-1] & gt_visible[f])
        if reversed_ < as_is:
            flipped.append(int(f))
    use = seen & gt_visible
    use[flipped] = False
    diff = det.points[use] - gt_points[use]
    dist = np.linalg.norm(diff, axis=-1)
    if len(dist):
        stats = dict(mean_px=dist.mean(), rms_px=np.sqrt((dist**2).mean()), max_px=dist.max(),
                     mean_dx_px=diff[:, 0].mean(), mean_dy_px=diff[:, 1].mean())
    else:
        stats = dict.fromkeys(("mean_px", "rms_px", "max_px", "mean_dx_px", "mean_dy_px"), math.nan)
    return {
        "frames": len(det.found),
        "found": int(det.found.sum()),
        "detection_rate": float(det.found.mean()),
        "point_detection_rate": float((seen & gt_visible).sum() / max(gt_visible.sum(), 1)),
        "points": int(use.sum()),
        **{k: float(v) for k, v in stats.items()},
        "flips": len(flipped),
        "flipped_frames": flipped,
    }


def _mean_distance(points: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> float:
    if not mask.any():
        return math.inf
    return float(np.linalg.norm(points[mask] - truth[mask], axis=-1).mean())
