"""Pattern detection: find a board's feature points in an image, in ``object_points()`` order.

This is the measuring instrument of the benchmark, so it works as a careful user would: OpenCV's
detectors find the board, the board's own appearance (never the ground truth) fixes the order, and
the points are then measured as precisely as the image allows.

* Checkerboard, ``"classic"`` (default): findChessboardCorners, then cornerSubPix on a slightly
  blurred copy with a window sized from the squares.  ``"sb"``: findChessboardCornersSB with
  CALIB_CB_ACCURACY and its own subpixel result (OpenCV 5.0 returns it in reverse order).  On clean
  renders of the paper's wide-angle camera classic is about 4x more accurate (see
  benchmarks/detection_accuracy.py); SB is kept to measure what the choice costs.
* Circle grids, ``"grid"``: findCirclesGrid (retried with CALIB_CB_CLUSTERING, which copes with
  stronger perspective) with a blob detector sized from the image and the board; the returned
  grid must be locally affine (a mis-ordered grid is rejected), and every centre is re-measured at
  full resolution as the darkness centroid of its disc (a disc cut by the image border, whose
  centroid would be biased, becomes a NaN row).  That is the centroid of the imaged
  ellipse, which is not the image of the circle's centre under perspective: the bias is what
  circle boards really cost, and it is kept, not corrected.
* ChArUco, ``"charuco"``: cv2.aruco.CharucoDetector, then each corner re-measured with a
  Förstner-type saddle fit restricted to the square edges, which keeps the markers out of the fit
  (see ``_refine_charuco``).  Partial boards are allowed (unseen corners are NaN rows); fewer than
  ``MIN_CHARUCO_CORNERS`` corners count as not found.

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
then measured on the full image: cornerSubPix for checkerboard corners (SB's included when the copy
was shrunk); for ChArUco the markers found on the copy, scaled back, go to CharucoDetector, which
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
from .rundir import write_npz

SEARCH_MAX_SIDE = 1600
CHARUCO_MIN_SEARCH_SIDE = 1920  # markers of small images are searched on an enlarged copy
MIN_CHARUCO_CORNERS = 6
METHODS = {
    "checkerboard": ("classic", "sb"),
    "symmetric_circles": ("grid",),
    "asymmetric_circles": ("grid",),
    "charuco": ("charuco",),
}
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-6)


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
        points = _corner_subpix(gray, points, pattern.pattern_size)
    points = _orient_checkerboard(gray, points, pattern)
    return Detection(_drop_grid_outliers(pattern.object_points()[:, :2], points,
                                         pattern.square_mm), pattern.ids(), True)


def _corner_subpix(gray, points: np.ndarray, pattern_size: tuple[int, int]) -> np.ndarray:
    """cornerSubPix on a blurred copy, with the largest window that cannot reach another corner.

    Window: the (2w + 1)^2 square reaches sqrt(2) w along its diagonal and the nearest other
    corner (along a row, a column or a diagonal, under any perspective) is at least ``step`` away,
    so w = step / 2 keeps it out with a margin for blur.  Blur: cornerSubPix's gradients are biased
    on one-pixel-sharp edges; a Gaussian (point-symmetric, so it moves no corner) of sigma 1.5 px
    brought the mean error on the wide camera's clean renders from 0.045 px to 0.011 px.  Sigma
    stays below a tenth of the step so the window holds the blurred edges many times over.
    """
    cols, rows = pattern_size
    grid = points.reshape(rows, cols, 2)
    steps = [grid[:, 1:] - grid[:, :-1], grid[1:] - grid[:-1],
             grid[1:, 1:] - grid[:-1, :-1], grid[1:, :-1] - grid[:-1, 1:]]
    step = min(float(np.linalg.norm(s, axis=-1).min()) for s in steps)
    sigma = min(1.5, 0.1 * step)
    blurred = cv2.GaussianBlur(gray.astype(np.float32), (0, 0), sigma)
    half = max(2, int(0.5 * step))
    refined = cv2.cornerSubPix(blurred, points.astype(np.float32).reshape(-1, 1, 2), (half, half),
                               (-1, -1), _SUBPIX_CRITERIA)
    return refined.reshape(-1, 2).astype(np.float64)


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
    symmetric = isinstance(pattern, SymmetricCircles)
    grid = cv2.CALIB_CB_SYMMETRIC_GRID if symmetric else cv2.CALIB_CB_ASYMMETRIC_GRID
    cols, rows = pattern.pattern_size
    object_xy = pattern.object_points()[:, :2]
    step_mm = _nearest_mm(object_xy)
    blobs = _blob_detector(search, pattern)
    kind = "symmetric" if symmetric else "asymmetric"
    reason = f"findCirclesGrid found no {cols}x{rows} {kind} circle grid"
    # The default grid finder fails on some clean, moderately tilted views that clustering finds;
    # clustering in turn sometimes returns a scrambled order, which the affine check rejects.
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
        return Detection(_disc_centroids(gray, points, affines, pattern), pattern.ids(), True)
    return _failed(pattern, reason)


def _disc_centroids(gray, points: np.ndarray, affines: np.ndarray, pattern,
                    iterations: int = 3) -> np.ndarray:
    """Re-measure each disc centre as the centroid of its darkness, at full resolution.

    Through the local board -> image map (fitted to the neighbouring centres) each disc gets an
    elliptical window in board units: the disc plus a margin for blur inside, and a ring of paper
    out to half the distance to the nearest disc.  A plane fitted to the ring gives the local paper
    white (absorbing shading); the weights ``white - I`` then make the centroid the area centroid of
    the imaged disc, as exact as the image's anti-aliasing.  The window is re-centred on the new
    estimate a few times, so the starting estimate need only be good to a fraction of the radius.
    A disc cut by the image border has no trustworthy centroid: its row is NaN.
    On 24 clean wide-camera renders per grid this measured the exact imaged-disc centroid to
    0.002-0.003 px mean (0.013 px max); the blob detector's own centres were off it by 0.015-0.017
    px mean (0.08 px max).
    """
    r_disc = pattern.diameter_mm / 2
    r_inner, r_outer = 1.25 * r_disc, 0.5 * _nearest_mm(pattern.object_points()[:, :2])
    height, width = gray.shape
    refined = points.copy()
    for i, A in enumerate(affines):
        A_inv = np.linalg.inv(A)
        reach, disc_reach = np.array([r_outer, r_inner]) * np.linalg.norm(A, 2)  # px
        for _ in range(iterations):
            cx, cy = refined[i]
            if not (disc_reach <= cx <= width - 1 - disc_reach
                    and disc_reach <= cy <= height - 1 - disc_reach):
                refined[i] = np.nan
                break
            # Near the border the window is cut: the ring keeps enough paper for the plane.
            x0, x1 = max(math.floor(cx - reach), 0), min(math.ceil(cx + reach) + 1, width)
            y0, y1 = max(math.floor(cy - reach), 0), min(math.ceil(cy + reach) + 1, height)
            ys, xs = np.mgrid[y0:y1, x0:x1]
            offsets = np.stack([xs - cx, ys - cy], -1)
            radius_mm = np.linalg.norm(offsets @ A_inv.T, axis=-1)
            patch = gray[y0:y1, x0:x1].astype(np.float64)
            ring = (radius_mm >= r_inner) & (radius_mm <= r_outer)
            design = np.column_stack([np.ones(ring.sum()), offsets[ring]])
            plane = np.linalg.lstsq(design, patch[ring], rcond=None)[0]
            disc = radius_mm < r_inner
            weight = plane[0] + offsets[disc] @ plane[1:] - patch[disc]
            refined[i] = (cx, cy) + weight @ offsets[disc] / weight.sum()
    return refined


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
    points = _refine_charuco(gray, points, side)
    if side is not pattern:  # the back's corners in the front's order (the board frame)
        front = np.full_like(points, np.nan)
        front[pattern.back_to_front] = points
        points = front
    return Detection(points, pattern.ids(), True)


def _refine_charuco(gray, points: np.ndarray, pattern: Charuco, sigma: float = 0.8,
                    iterations: int = 10) -> np.ndarray:
    """Re-measure ChArUco corners with a saddle fit on the square edges only.

    cornerSubPix (Förstner & Gülch 1987) finds the point q that every gradient g at pixels p in a
    window is orthogonal to, least squares: (sum g g^T) q = sum g g^T p.  Around a ChArUco corner a
    square window wide enough to be precise takes in the markers' borders, 2 mm inside the white
    squares, whose gradients pull the corner (OpenCV's detector: 0.13 px mean, 0.56 px max over
    24 clean renders of the wide camera).  Here the same equations run over a cross: pixels within
    ``band`` of the two edge lines through the corner (half the marker's inset, in board units via
    the local affine map fitted to the neighbouring corners) out to 0.6 square, on a copy blurred
    with ``sigma`` px for well-sampled gradients (0.047 px mean, 0.41 px max on the same corners,
    which include far boards with 12 px squares; 0.028 px mean on near ones).
    Corners with fewer than two detected non-collinear neighbours keep OpenCV's estimate, as do
    those whose fit leaves the image or moves them by more than a band.
    """
    object_xy = pattern.object_points()[:, :2]
    affines, _ = _local_affines(object_xy, points, 1.5 * pattern.square_mm)
    band = (pattern.square_mm - pattern.marker_mm) / 4
    reach = 0.6 * pattern.square_mm
    margin = math.ceil(3 * sigma) + 1  # the blur and the gradient need pixels beyond the window
    height, width = gray.shape
    refined = points.copy()
    for i in np.flatnonzero(np.isfinite(affines[:, 0, 0])):
        A_inv = np.linalg.inv(affines[i])
        half = reach * np.linalg.norm(affines[i], 2)
        q = points[i].copy()
        for _ in range(iterations):
            x0, y0 = math.floor(q[0] - half) - margin, math.floor(q[1] - half) - margin
            x1, y1 = math.ceil(q[0] + half) + margin + 1, math.ceil(q[1] + half) + margin + 1
            if x0 < 0 or y0 < 0 or x1 > width or y1 > height:
                q = points[i]
                break
            patch = cv2.GaussianBlur(gray[y0:y1, x0:x1].astype(np.float32), (0, 0), sigma)
            gy, gx = (g[margin:-margin, margin:-margin]
                      for g in np.gradient(patch.astype(np.float64)))
            ys, xs = np.mgrid[y0 + margin:y1 - margin, x0 + margin:x1 - margin]
            offsets = np.stack([xs - q[0], ys - q[1]], -1)
            uv = np.abs(offsets @ A_inv.T)
            cross = (uv.min(-1) < band) & (uv.max(-1) < reach)
            g = np.stack([gx[cross], gy[cross]], -1)
            normal = g.T @ g
            if np.linalg.cond(normal) > 1e6:  # no edges in two directions: nothing to fit
                q = points[i]
                break
            shift = np.linalg.solve(normal, np.einsum("ni,nj,nj->i", g, g, offsets[cross]))
            q = q + shift
            if np.linalg.norm(shift) < 1e-4:
                break
        moved = np.linalg.norm((q - points[i]) @ A_inv.T)
        refined[i] = q if moved < band else points[i]
    return refined


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
            with np.load(path, allow_pickle=False) as z:
                return cls(str(z["camera"]), str(z["pattern"]), str(z["method"]), z["points"],
                           z["found"], z["ids"],
                           {int(f): str(m) for f, m in zip(z["error_frames"], z["error_messages"])})
        except (OSError, KeyError, ValueError) as e:
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
