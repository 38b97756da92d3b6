"""Finding each board family in an image (the package notes): the search image, the
checkerboard (classic and SB) with its orientation, circle grids with their disc diameter, and
ChArUco; every point then measured by the saddle fit or the disc centroid.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np

from ..core.patterns import AsymmetricCircles, Charuco, Checkerboard, Pattern, SymmetricCircles
from .discs import measured_discs
from .saddle import drop_grid_outliers, local_affines, nearest_mm, refine_saddles


SEARCH_MAX_SIDE = 1600


SEARCH_BLUR_PX = 1.0  # sigma of the blur of a reduced checkerboard or circle grid search copy


CHARUCO_MIN_SEARCH_SIDE = 1920  # markers of small images are searched on an enlarged copy


MIN_CHARUCO_CORNERS = 6


NO_MARKER = "no ArUco marker of the board was found"


CHARUCO_SIGMA = 0.8


# The cross of edge bands holds few pixels: longer arms than the checkerboard's (0.5 square)
# took the wide camera's mean error from 0.071 px to 0.058 (24 clean frames: 8 of them).
CHARUCO_REACH = 0.8


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
    #: Not found, but the board itself was read in the image as searched (ChArUco: two or more
    #: of its own markers, too few corners between them): its other polarity and mirror image
    #: need no search.
    board_seen: bool = False


def failed_detection(pattern: Pattern, reason: str) -> Detection:
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


def detect(image: np.ndarray, pattern: Pattern, method: str | None = None,
           in_view: bool = True) -> Detection:
    """Detect ``pattern`` in an 8-bit grayscale (H, W) or BGR (H, W, 3) image.

    A board that is not found gives ``found=False`` with the reason; bad input raises ValueError.
    ``in_view``: whether the board is likely in the image (it was in the camera's previous
    frame); it orders a ChArUco board's searches (see below), not what they find.
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
    search = _search_image(first, pattern)
    # The three other ChArUco searches (other polarity, mirrored) cost three marker searches
    # each time the board is out of view, as it is in most of a studio's frames: one marker
    # search for every marker of either polarity, as printed or mirrored, tells first whether
    # any of them can find something. It finds a marker wherever the first search does (the
    # same candidates, the plain ids first), so where the board is likely out of view it goes
    # first: when it finds none, neither would the first search.
    charuco = pattern.kind == "charuco"
    if charuco and not in_view and not _any_marker_seen(search.image, pattern):
        return failed_detection(pattern, NO_MARKER)
    found = _detect_in(first, search, pattern, method)
    if found.found or found.board_seen:
        return found
    if charuco and in_view and not _any_marker_seen(search.image, pattern):
        return found
    other = _detect_in(255 - first, _search_image(255 - first, pattern), pattern, method)
    if other.found or other.board_seen:
        return other
    if not charuco:
        return found
    # A one-sided ChArUco print seen from behind (through thin paper or acrylic) is its mirror
    # image, whose markers read as no id; mirrored back, each corner keeps its id, so it is the
    # same board point. A chessboard or circle grid mirrored is found in the image as it is.
    for polarity in (first, 255 - first):
        mirrored = np.ascontiguousarray(polarity[:, ::-1])
        back = _detect_in(mirrored, _search_image(mirrored, pattern), pattern, method)
        if back.found:
            points = back.points.copy()
            points[:, 0] = gray.shape[1] - 1 - points[:, 0]  # pixel centres: x -> W - 1 - x
            return Detection(points, back.ids, True)
        if back.board_seen:
            return back
    return found


def _search_image(gray, pattern: Pattern) -> "_SearchImage":
    if pattern.kind == "charuco":
        return _SearchImage.of(gray, CHARUCO_MIN_SEARCH_SIDE)
    search = _SearchImage.of(gray)
    # Sensor noise survives the reduction (4096 -> 1600 px divides its sigma by only 2.56) and
    # fills findChessboardCorners' quads and the blob detector's thresholds with specks that cost
    # most of their time: with the copy blurred, detection of 8 noisy 12 MP frames went from 70
    # to 33 ms a frame (checkerboard) and from 121 to 75 ms (circle grids).  Every point is then
    # measured on the full image, so only where that starts moves: by at most 7.6e-6 px on clean
    # frames and 3.5e-3 px on noisy ones, the mean error against the truth unchanged in its
    # fourth decimal (16 noisy frames per board).
    if search.downscaled:
        return _SearchImage(cv2.GaussianBlur(search.image, (0, 0), SEARCH_BLUR_PX), search.scale)
    return search


def _detect_in(gray, search: "_SearchImage", pattern: Pattern, method: str) -> Detection:
    try:
        if pattern.kind == "checkerboard":
            return _detect_checkerboard(gray, search, pattern, method)
        if pattern.kind == "charuco":
            return _detect_charuco(gray, search, pattern)
        return _detect_circles(gray, search, pattern)
    except cv2.error as e:  # OpenCV asserts on some degenerate candidate sets: a failed frame
        return failed_detection(pattern, f"OpenCV error: {e.err or e}")


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
        return failed_detection(pattern, f"{name} found no {size[0]}x{size[1]} inner-corner grid")
    points = search.to_full(corners.reshape(-1, 2))
    if method == "sb":
        points = points[::-1]  # OpenCV 5.0's SB starts at the opposite corner (patterns.py)
    if method == "classic" or search.downscaled:  # SB's own subpixel result is kept at full size
        points = refine_saddles(gray, points, pattern.object_points()[:, :2], pattern.square_mm,
                                 _checkerboard_sigma(points, pattern.pattern_size))
    points = _orient_checkerboard(gray, points, pattern)
    return Detection(drop_grid_outliers(pattern.object_points()[:, :2], points,
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
        return failed_detection(pattern, found)
    return Detection(measured_discs(gray, *found, pattern)[0], pattern.ids(), True)


def measure_disc_diameter(images, pattern: SymmetricCircles | AsymmetricCircles) -> float:
    """The discs' diameter in mm, measured from images of a circle grid whose spacing is known.

    ``images``: 8-bit grey (H, W) or BGR (H, W, 3) arrays; ``pattern.diameter_mm`` need only be
    a rough guess (it sizes the first measuring window; within about -20 %/+60 % of the truth).
    Each disc's darkness summed over its window, over the darkness of its core, is its imaged
    area (blur moves darkness about but keeps its sum); the local board -> image map fitted to
    the neighbouring centres (``local_affines``) takes it to board mm^2, and the diameter of the
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
        found = _find_circle_grid(_search_image(gray, pattern), pattern)
        if not isinstance(found, str):
            diameters.append(measured_discs(gray, *found, pattern)[1])
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
    step_mm = nearest_mm(object_xy)
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
        affines, misfit = local_affines(object_xy, points, 1.5 * step_mm)
        # Even strong perspective and the wide lens leave < 0.14 step of misfit over a point's
        # neighbours (measured on the truth); a mis-ordered grid is off by about a step.
        if np.nanmax(misfit) > 0.3 * step_mm:
            reason = "findCirclesGrid returned a grid whose order is not locally affine"
            continue
        return points, affines
    return reason


# ----------------------------------------------------------------------------- ChArUco
def _detect_charuco(gray, search: _SearchImage, pattern: Charuco) -> Detection:
    board = pattern.cv_board()
    # Markers are searched on the rescaled copy: ArUco needs a few pixels per marker cell (a 7x7
    # marker of a far board on the 640 px camera has about 1.2), and enlarging the wide camera's
    # images 3x found twice the corners (1493 against 740 of 2112 over 24 clean frames) at no
    # cost in accuracy.  CharucoDetector then interpolates the chessboard corners from the
    # scaled-back markers and refines them on the full image.
    markers, marker_ids = detect_markers(search.image, _first_markers(pattern.dictionary,
                                                                      _marker_rows(pattern)))
    if marker_ids is None or len(marker_ids) == 0:
        return failed_detection(pattern, NO_MARKER)
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
        failed = failed_detection(pattern, f"only {seen} ChArUco corners ({len(marker_ids)} "
                                           f"markers) found, need {MIN_CHARUCO_CORNERS}")
        # Two of the side's own ids place the board in this polarity, unmirrored (a mirrored or
        # inverted marker reads as no id, or as one id at random of the dictionary's): the
        # searches of the other polarity and the mirror image would find nothing. A fifth of
        # the wide camera's frames see the board so, each of those searches 14 ms there.
        own = np.isin(marker_ids, side.marker_ids()).sum()
        return dataclasses.replace(failed, board_seen=bool(own >= 2))
    points = np.full((len(pattern.ids()), 2), np.nan)
    points[ids.ravel()] = corners.reshape(-1, 2)
    points = refine_saddles(gray, points, side.object_points()[:, :2], side.square_mm,
                             CHARUCO_SIGMA, band_mm=(side.square_mm - side.marker_mm) / 4,
                             reach=CHARUCO_REACH)
    if side is not pattern:  # the back's corners in the front's order (the board frame)
        front = np.full_like(points, np.nan)
        front[pattern.back_to_front] = points
        points = front
    return Detection(points, pattern.ids(), True)


def _any_marker_seen(search_image: np.ndarray, pattern: Charuco) -> bool:
    """Whether one marker search of ``search_image`` finds any marker of the board's ids (the
    first markers of its dictionary, up to its largest id) in either polarity
    (``detectInvertedMarker``), as printed or mirrored."""
    return len(detect_markers(search_image, _with_mirrored_markers(pattern.dictionary,
                                                                   _marker_rows(pattern)),
                              inverted=True)[0]) > 0


def detect_markers(image: np.ndarray, dictionary, inverted: bool = False):
    """(corners, ids) of ``cv2.aruco.ArucoDetector(dictionary).detectMarkers(image)`` with the
    default parameters (``inverted``: detectInvertedMarker too), searched only over the part of
    the image that is not uniform.

    Where a studio's camera sees the board small, or not at all, most of its (enlarged) image is
    the uniform background, and the search's adaptive thresholds and contours cost as much
    there as on the board (12 ms of a 1920 px search of h36m's frames, 2.8 ms in the box).
    Every step of the search sees only the box around the pixels that differ from the image's
    first, widened by the largest threshold window and the border distance: its thresholds and
    contours are those of the whole image there (a uniform surround is never below its local
    mean), and nothing is found outside it.  The perimeter limits, rates of the searched
    image's longer side, are rescaled to the same whole pixels; the rest is in pixels or
    relative to each candidate, and the corners are whole pixels moved back by the box's
    origin.  Only the decoding of a candidate is not exactly the same: OpenCV removes its
    perspective from corners in the searched image's coordinates, and rounding then reads a
    marker of a few pixels a cell differently wherever the origin is (OpenCV's own search of
    the whole image, shifted by a few pixels in a larger uniform one, gains or loses the same
    markers for some shifts).  On h36m's 1120 frames (2240 searches, plain and mirrored
    dictionaries) the markers are the whole image's, in the same order; over the paper grid's
    1016 clean ChArUco frames, 7 of the 640 x 480 camera's (searched 3x enlarged) gain a marker
    at the edge of decoding or, one, lose one (tests/detect/test_detect.py compares placements
    where nothing is at that edge); a uniform image has none.
    """
    params = cv2.aruco.DetectorParameters()
    params.detectInvertedMarker = inverted
    height, width = image.shape
    x, y, w, h = cv2.boundingRect(cv2.compare(image, float(image[0, 0]), cv2.CMP_NE))
    if w == 0:  # uniform: no pixel is below its local mean, so no contour
        return (), np.empty(0, np.int32)
    margin = params.adaptiveThreshWinSizeMax + params.minDistanceToBorder + 1
    x0, y0 = max(x - margin, 0), max(y - margin, 0)
    x1, y1 = min(x + w + margin, width), min(y + h + margin, height)
    if (x1 - x0) * (y1 - y0) > width * height // 2:  # little to gain
        return cv2.aruco.ArucoDetector(dictionary, params).detectMarkers(image)[:2]
    whole, box = max(width, height), max(x1 - x0, y1 - y0)
    for rate in ("minMarkerPerimeterRate", "maxMarkerPerimeterRate"):
        # OpenCV truncates rate x side to whole pixels: the same count, half a pixel clear.
        setattr(params, rate, (math.floor(getattr(params, rate) * whole) + 0.5) / box)
    corners, ids, _ = cv2.aruco.ArucoDetector(dictionary, params).detectMarkers(
        image[y0:y1, x0:x1])
    return tuple(c + np.float32([x0, y0]) for c in corners), ids


def _marker_rows(pattern: Charuco) -> int:
    """How many of its dictionary's first markers a board's search reads: up to its largest id
    (its back's, when two-sided)."""
    last = pattern.back() if pattern.two_sided else pattern
    return int(last.marker_ids().max()) + 1


@functools.cache
def _first_markers(name: str, rows: int) -> cv2.aruco.Dictionary:
    """The first ``rows`` markers of the dictionary ``name``, with its error correction.

    OpenCV identifies a candidate as the first marker of the dictionary within the correction
    distance, so the ids below ``rows`` are read exactly as with the whole dictionary; only
    other ids (no marker of the board) are no longer read. The paper's wide camera's 3x
    enlarged search compares each candidate with 54 markers instead of 250: 3-5 ms of its
    16-21 on one thread."""
    whole = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))
    return cv2.aruco.Dictionary(whole.bytesList[:rows], whole.markerSize,
                                whole.maxCorrectionBits)


@functools.cache
def _with_mirrored_markers(name: str, rows: int) -> cv2.aruco.Dictionary:
    """The first ``rows`` markers of the dictionary ``name`` followed by each of them mirrored
    (ids + ``rows``), with its error correction. A mirror about the other axis is this one
    turned half a turn, which identification tries."""
    plain = _first_markers(name, rows)
    n = plain.markerSize
    mirrored = [cv2.aruco.Dictionary.getByteListFromBits(
        np.ascontiguousarray(cv2.aruco.Dictionary.getBitsFromByteList(row[None], n)[:, ::-1]))
        for row in plain.bytesList]
    both = np.concatenate([plain.bytesList, np.concatenate(mirrored)])
    return cv2.aruco.Dictionary(both, n, plain.maxCorrectionBits)
