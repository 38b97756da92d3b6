"""Calibration boards: exact geometry and exact textures of the paper's four patterns.

SynthCal (section 4.1, "Dataset") uses four boards, which are the defaults here; every parameter can be
overridden:

* ``Checkerboard`` (Ch): 9 x 12 squares of 15 mm, hence 8 x 11 = 88 inner corners.
* ``SymmetricCircles`` (Sc): 10 x 10 circles, 7 mm diameter, 15 mm centre spacing.
* ``AsymmetricCircles`` (Ac): "9 x 10, 9 mm diameter, 22 mm diagonal spacing", read as 9 rows of
  10 circles, OpenCV's ``patternSize = (10, 9)``, 90 circles (the class docstring says why).
* ``Charuco`` (Cu): 9 x 12 squares of 15 mm, 11 mm markers from ``DICT_7X7_250``, 88 corners.

Each board tells the rest of the suite three things:

1. its feature points (``object_points()``, ``ids()``, ``pattern_size``) in exactly the order OpenCV's
   detector returns them, so detections and ground truth pair up index by index;
2. its outline: ``size_mm`` (pattern plus a white quiet zone of ``margin_mm`` on every side) and
   ``texture_origin_mm``, the board-frame position of the outline's top-left corner;
3. its appearance: ``texture(px_per_mm)``, a grayscale image of the whole outline whose every pixel
   is the exact area coverage of the ideal black-and-white print (squares, marker cells and circles
   are integrated analytically, so edges and circle centroids carry no rasterisation bias).

Frames and pixel convention.  The board frame is the object-point frame: points lie on z = 0, x to
the right and y down on the printed texture (as OpenCV's object points).  Texture pixel edges align
with the board outline: texel (i, j) covers board x in ``origin_x + [j, j + 1] / px_per_mm`` and y
in ``origin_y + [i, i + 1] / px_per_mm``, so its centre is
``texture_origin_mm + ((j + 0.5) / px_per_mm, (i + 0.5) / px_per_mm)``.  Seen as an image with
OpenCV's pixel centres, board point (X, Y) sits at ``((X, Y) - texture_origin_mm) * px_per_mm - 0.5``.
If ``size_mm * px_per_mm`` is not an integer, the last texel row/column reaches past the outline by
less than one texel and is white (quiet zone).
"""

from __future__ import annotations

import abc
import dataclasses
import math
from dataclasses import dataclass
from typing import ClassVar

import cv2
import numpy as np


# ----------------------------------------------------------------------------- exact rasterisation
def _overlap(pixel_count: int, start: float, cell: float, n_cells: int) -> tuple[int, np.ndarray]:
    """Overlap lengths between unit texels and a row of ``n_cells`` cells.

    Coordinates are in texels along one axis (texel k spans [k, k + 1]); the cells span
    ``start + [m, m + 1] * cell``.  Returns the first texel touched and an (K, n_cells) matrix whose
    entry (k, m) is the length of texel ``first + k`` inside cell m (exact, in [0, 1]).
    """
    end = start + n_cells * cell
    first = max(int(math.floor(start)), 0)
    last = min(int(math.ceil(end)), pixel_count)  # exclusive
    lo = np.arange(first, last, dtype=np.float64)[:, None]
    edges = start + cell * np.arange(n_cells + 1, dtype=np.float64)
    return first, np.clip(np.minimum(lo + 1.0, edges[1:]) - np.maximum(lo, edges[:-1]), 0.0, None)


def _add_cells(black: np.ndarray, cells: np.ndarray, x0: float, y0: float, cell: float) -> None:
    """Add the exact black coverage of a grid of 0/1 ``cells`` (rows, cols) to ``black`` in place.

    The grid's top-left corner is at texel coordinates (x0, y0) (texel edges at integers) and each cell
    is ``cell`` texels wide.  A union of axis-aligned rectangles integrates separably over a texel,
    so the coverage is the matrix product rows_overlap @ cells @ cols_overlap.T.
    """
    height, width = black.shape
    i0, rows = _overlap(height, y0, cell, cells.shape[0])
    j0, cols = _overlap(width, x0, cell, cells.shape[1])
    black[i0:i0 + rows.shape[0], j0:j0 + cols.shape[0]] += rows @ cells.astype(np.float64) @ cols.T


def _add_disc(black: np.ndarray, cx: float, cy: float, radius: float) -> None:
    """Add the exact area coverage of a disc (centre and radius in texel units) to ``black``.

    Uses the signed quadrant area S(x, y) = area of disc ∩ [0, x] x [0, y] (odd in x and y), so a
    texel's coverage is the inclusion-exclusion of S over its four corners.
    """
    height, width = black.shape
    i0, i1 = max(int(math.floor(cy - radius)), 0), min(int(math.ceil(cy + radius)), height)
    j0, j1 = max(int(math.floor(cx - radius)), 0), min(int(math.ceil(cx + radius)), width)
    x = np.arange(j0, j1 + 1, dtype=np.float64)[None, :] - cx
    y = np.arange(i0, i1 + 1, dtype=np.float64)[:, None] - cy
    ax, ay = np.broadcast_arrays(np.minimum(np.abs(x), radius), np.minimum(np.abs(y), radius))

    def below_arc(t: np.ndarray) -> np.ndarray:  # integral of sqrt(r^2 - u^2) from 0 to t
        return 0.5 * (t * np.sqrt(radius**2 - t**2) + radius**2 * np.arcsin(t / radius))

    crossing = np.sqrt(np.maximum(radius**2 - ay**2, 0.0))  # where the arc meets height ay
    outside = ax > crossing
    area = np.where(
        outside, ay * crossing + below_arc(ax) - below_arc(np.minimum(crossing, ax)), ax * ay
    )
    signed = np.sign(x) * np.sign(y) * area
    black[i0:i1, j0:j1] += signed[1:, 1:] - signed[:-1, 1:] - signed[1:, :-1] + signed[:-1, :-1]


# ----------------------------------------------------------------------------------- the family
@dataclass(frozen=True, kw_only=True)
class Pattern(abc.ABC):
    """A planar calibration board: feature points, outline and texture (see the module docstring)."""

    kind: ClassVar[str]
    code: ClassVar[str]
    # Whether the back carries a print too (a field of the boards that can: ChArUco).
    two_sided = False

    # White quiet zone around the printed features, on every side. A field's metadata "min" is
    # its least value (default: any positive number).
    margin_mm: float = dataclasses.field(default=10.0, metadata={"min": 0.0})
    # Printed white on black (the quiet zone black too): boards made by inverting a print, or
    # cut from a dark plate. The features are the same; every colour is the other one.
    inverted: bool = False

    def __post_init__(self) -> None:
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if isinstance(value, (int, float)) and not isinstance(value, bool):
                least = field.metadata.get("min")
                if not math.isfinite(value) or (value <= 0 if least is None else value < least):
                    expected = "positive" if least is None else f"at least {least}"
                    raise ValueError(f"{self.kind}: {field.name} must be {expected}, got {value!r}")
        self._validate()

    @property
    def name(self) -> str:
        return self.kind

    # -- per-board geometry
    @property
    @abc.abstractmethod
    def pattern_size(self) -> tuple[int, int]:
        """(points per row, rows): the ``patternSize`` OpenCV's detector expects."""

    @abc.abstractmethod
    def object_points(self) -> np.ndarray:
        """(N, 3) float64 feature points in mm, z = 0, in OpenCV's detection order."""

    @abc.abstractmethod
    def _feature_bounds_mm(self) -> tuple[float, float, float, float]:
        """(x_min, y_min, x_max, y_max) of everything printed, in the board frame."""

    @abc.abstractmethod
    def _paint(self, black: np.ndarray, origin_px: np.ndarray, px_per_mm: float) -> None:
        """Add the black coverage of the features; board (X, Y) is texel (X, Y) * ppmm - origin_px."""

    def _validate(self) -> None:
        """Cross-field checks; raise ValueError naming the field."""

    # -- shared
    def ids(self) -> np.ndarray:
        """(N,) int feature ids, index-aligned with ``object_points()``."""
        return np.arange(len(self.object_points()))

    @property
    def texture_origin_mm(self) -> np.ndarray:
        """(2,) board-frame position of the top-left corner of the outline (= of the texture)."""
        x_min, y_min, _, _ = self._feature_bounds_mm()
        return np.array([x_min - self.margin_mm, y_min - self.margin_mm])

    @property
    def size_mm(self) -> tuple[float, float]:
        """(width, height) of the board outline, quiet zone included."""
        x_min, y_min, x_max, y_max = self._feature_bounds_mm()
        return (x_max - x_min + 2 * self.margin_mm, y_max - y_min + 2 * self.margin_mm)

    def outline_mm(self) -> np.ndarray:
        """(4, 2) corners of the board's outline, in order around it, board frame mm."""
        (x0, y0), (w, h) = self.texture_origin_mm, self.size_mm
        return np.array([[x0, y0], [x0 + w, y0], [x0 + w, y0 + h], [x0, y0 + h]])

    @property
    def outline_centre_mm(self) -> np.ndarray:
        """(2,) centre of the outline (what the board turns about when it moves)."""
        return np.asarray(self.texture_origin_mm) + np.asarray(self.size_mm) / 2

    def texture_shape(self, px_per_mm: float) -> tuple[int, int]:
        """(H, W) of ``texture(px_per_mm)``: the outline, rounded up to whole texels."""
        # The 1e-9 absorbs float rounding of a whole product, which would otherwise add a texel.
        width, height = self.size_mm
        return (math.ceil(height * px_per_mm - 1e-9), math.ceil(width * px_per_mm - 1e-9))

    def texture(self, px_per_mm: float) -> np.ndarray:
        """(H, W) uint8 image of the board, 0 = black print, 255 = white, exact area coverage."""
        return self._texture_of(self._paint, px_per_mm)

    def _texture_of(self, paint, px_per_mm: float) -> np.ndarray:
        if not (px_per_mm > 0 and math.isfinite(px_per_mm)):
            raise ValueError(f"px_per_mm must be positive, got {px_per_mm!r}")
        black = np.zeros(self.texture_shape(px_per_mm))
        paint(black, self.texture_origin_mm * px_per_mm, float(px_per_mm))
        # rint(255 (1 - clip(black))) in place: a studio's board is a 45 MP texture, whose
        # float64 temporaries (360 MB each, faulted in afresh) took 2 of its 3 s.
        np.clip(black, 0.0, 1.0, out=black)
        np.subtract(1.0, black, out=black)
        black *= 255.0
        texture = np.rint(black, out=black).astype(np.uint8)
        return 255 - texture if self.inverted else texture


def _grid(cols: int, rows: int) -> tuple[np.ndarray, np.ndarray]:
    """Column and row indices (j, i) of a row-major cols x rows grid, as float64 arrays."""
    i, j = np.divmod(np.arange(cols * rows), cols)
    return j.astype(np.float64), i.astype(np.float64)


def _on_plane(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return np.column_stack([x, y, np.zeros_like(x)])


@dataclass(frozen=True, kw_only=True)
class Checkerboard(Pattern):
    """``squares_x`` x ``squares_y`` squares, the top-left one black; features are the inner corners.

    Object point (i, j) (row i, column j of inner corners) is (j, i) * square_mm, so the first inner
    corner is the origin; ``pattern_size = (squares_x - 1, squares_y - 1)`` for findChessboardCorners.
    With one odd and one even square count the colouring is not 180-degree symmetric, which lets a
    detector tell the board's orientation: findChessboardCorners returns ``object_points()`` order for
    upright and upside-down views alike.  findChessboardCornersSB is colour-aware too but starts at the
    opposite corner: on OpenCV 5.0 its point k is object point N - 1 - k (reverse its output).
    """

    kind: ClassVar[str] = "checkerboard"
    code: ClassVar[str] = "Ch"

    squares_x: int = 9
    squares_y: int = 12
    square_mm: float = 15.0

    def _validate(self) -> None:
        for field in ("squares_x", "squares_y"):
            if getattr(self, field) < 3:
                raise ValueError(f"{self.kind}: {field} must be at least 3")

    @property
    def pattern_size(self) -> tuple[int, int]:
        return (self.squares_x - 1, self.squares_y - 1)

    def object_points(self) -> np.ndarray:
        j, i = _grid(*self.pattern_size)
        return _on_plane(j * self.square_mm, i * self.square_mm)

    def _feature_bounds_mm(self) -> tuple[float, float, float, float]:
        s = self.square_mm
        return (-s, -s, (self.squares_x - 1) * s, (self.squares_y - 1) * s)

    def _paint(self, black: np.ndarray, origin_px: np.ndarray, px_per_mm: float) -> None:
        parity = np.add.outer(np.arange(self.squares_y), np.arange(self.squares_x)) % 2 == 0
        corner = np.array(self._feature_bounds_mm()[:2]) * px_per_mm - origin_px
        _add_cells(black, parity, corner[0], corner[1], self.square_mm * px_per_mm)


@dataclass(frozen=True, kw_only=True)
class _CircleGrid(Pattern):
    """Black discs on white; features are the disc centres (findCirclesGrid)."""

    cols: int
    rows: int
    diameter_mm: float

    @property
    def pattern_size(self) -> tuple[int, int]:
        return (self.cols, self.rows)

    def _feature_bounds_mm(self) -> tuple[float, float, float, float]:
        points = self.object_points()
        r = self.diameter_mm / 2
        return (*(points[:, :2].min(axis=0) - r), *(points[:, :2].max(axis=0) + r))

    def _paint(self, black: np.ndarray, origin_px: np.ndarray, px_per_mm: float) -> None:
        for x, y, _ in self.object_points() * px_per_mm:
            _add_disc(black, x - origin_px[0], y - origin_px[1], self.diameter_mm / 2 * px_per_mm)


@dataclass(frozen=True, kw_only=True)
class SymmetricCircles(_CircleGrid):
    """``cols`` x ``rows`` discs on a square lattice; point (i, j) is (j, i) * spacing_mm.

    Detect with ``cv2.findCirclesGrid(img, pattern_size, flags=cv2.CALIB_CB_SYMMETRIC_GRID)``.
    The grid is symmetric under a 180-degree rotation (and 90 degrees when square), so the detector
    orders by image position: an upright view comes back in ``object_points()`` order, an
    upside-down one reversed.  Views must stay within +-45 degrees of upright to pair up correctly.
    """

    kind: ClassVar[str] = "symmetric_circles"
    code: ClassVar[str] = "Sc"

    cols: int = 10
    rows: int = 10
    diameter_mm: float = 7.0
    spacing_mm: float = 15.0

    def _validate(self) -> None:
        if self.diameter_mm >= self.spacing_mm:
            raise ValueError(f"{self.kind}: diameter_mm must be below spacing_mm (discs would touch)")

    def object_points(self) -> np.ndarray:
        j, i = _grid(self.cols, self.rows)
        return _on_plane(j * self.spacing_mm, i * self.spacing_mm)


@dataclass(frozen=True, kw_only=True)
class AsymmetricCircles(_CircleGrid):
    """OpenCV's asymmetric circle grid: ``rows`` rows of ``cols`` discs, odd rows shifted half a pitch.

    Point (i, j) (row i, column j) is ((2 j + i % 2) s, i s) with s = diagonal_spacing_mm / sqrt(2),
    the layout of OpenCV's calibration sample: diagonal neighbours are ``diagonal_spacing_mm`` apart,
    discs in one row 2 s apart, rows s apart.  Detect with
    ``cv2.findCirclesGrid(img, pattern_size, flags=cv2.CALIB_CB_ASYMMETRIC_GRID)``.

    The paper's "9 x 10" is read as 9 rows of 10 discs, ``pattern_size = (10, 9)`` (OpenCV's
    (points per row, rows)): 90 discs, 19 s wide and 8 s tall between centres.  The other reading,
    10 rows of 9, is unusable: with an even row count the layout maps onto itself under a 180-degree
    rotation, and OpenCV 5.0's findCirclesGrid then returns the rows swapped in pairs (1, 0, 3, 2, ...),
    an order no rigid motion of these object points reproduces.  With an odd row count (as in
    OpenCV's own 4 x 11) the order matches ``object_points()`` for upright and upside-down views alike,
    so ``rows`` must be odd.
    """

    kind: ClassVar[str] = "asymmetric_circles"
    code: ClassVar[str] = "Ac"

    cols: int = 10
    rows: int = 9
    diameter_mm: float = 9.0
    diagonal_spacing_mm: float = 22.0

    @property
    def spacing_mm(self) -> float:
        """s: the horizontal half-pitch and the row pitch."""
        return self.diagonal_spacing_mm / math.sqrt(2.0)

    def _validate(self) -> None:
        if self.rows % 2 == 0:
            raise ValueError(
                f"{self.kind}: rows must be odd; OpenCV's findCirclesGrid mis-orders asymmetric grids "
                f"with an even row count (got rows={self.rows})"
            )
        if self.diameter_mm >= self.diagonal_spacing_mm:
            raise ValueError(f"{self.kind}: diameter_mm must be below diagonal_spacing_mm")

    def object_points(self) -> np.ndarray:
        j, i = _grid(self.cols, self.rows)
        s = self.spacing_mm
        return _on_plane((2 * j + i % 2) * s, i * s)


@dataclass(frozen=True, kw_only=True)
class Charuco(Pattern):
    """ChArUco board in OpenCV's (>= 4.6, non-legacy) layout; features are the inner chessboard corners.

    Geometry is exactly ``cv_board()``'s: the top-left square is black, markers sit centred in the
    white squares with ids 0, 1, ... in row-major order, and ``object_points()`` equals
    ``getChessboardCorners()`` (origin at the outer top-left corner of the squares, first corner at
    (square_mm, square_mm)), indexed by the ids CharucoDetector returns.  ``DICT_7X7_250`` is the
    default: the board needs 54 markers, its ids 0..249 are the first 250 of DICT_7X7_1000, and the
    smaller dictionary has a larger minimum Hamming distance (corrects 8 bits instead of 6), so
    fewer false or confused ids.

    ``two_sided``: the back carries a second ChArUco board, printed mirrored so that each of its
    corners lies on a corner of the front (``back()``, with the next ``M`` marker ids of the
    dictionary: a detector tells the sides apart by their ids), as Caliscope's two-sided boards:
    cameras on opposite sides of a studio then see the same corners at the same time. The board
    frame stays the front's; ``back_to_front`` maps the back board's corner indices to it.
    ``marker_id_offset``: the id of the first marker (the back of a two-sided board uses the
    ids after the front's). ``legacy``: the layout of boards made by OpenCV before 4.6
    (``setLegacyPattern``): with an even number of rows the top-left square is white, so the
    markers sit in the other squares; with an odd number both layouts are the same board.
    """

    kind: ClassVar[str] = "charuco"
    code: ClassVar[str] = "Cu"

    squares_x: int = 9
    squares_y: int = 12
    square_mm: float = 15.0
    marker_mm: float = 11.0
    dictionary: str = "DICT_7X7_250"
    two_sided: bool = False
    legacy: bool = False
    # ArUco's dictionaries hold at most 1000 markers.
    marker_id_offset: int = dataclasses.field(default=0, metadata={"min": 0, "max": 999})

    def _validate(self) -> None:
        for field in ("squares_x", "squares_y"):
            if getattr(self, field) < 3:
                raise ValueError(f"{self.kind}: {field} must be at least 3")
        if self.marker_mm >= self.square_mm:
            raise ValueError(f"{self.kind}: marker_mm must be below square_mm")
        name = self.dictionary
        if not (isinstance(name, str) and name.startswith("DICT_") and hasattr(cv2.aruco, name)):
            raise ValueError(f"{self.kind}: dictionary {self.dictionary!r} is not a cv2.aruco DICT_*")
        needed = self.marker_id_offset + self._marker_count() * (2 if self.two_sided else 1)
        if self.aruco_dictionary().bytesList.shape[0] < needed:
            raise ValueError(f"{self.kind}: dictionary {self.dictionary} has too few markers "
                             f"({needed} needed" + (", both sides" if self.two_sided else "")
                             + ")")

    def _marker_count(self) -> int:
        return self.squares_x * self.squares_y // 2

    def marker_ids(self) -> np.ndarray:
        """(M,) int32: the ids of the board's markers, in row-major order of the white squares."""
        return np.arange(self._marker_count(), dtype=np.int32) + self.marker_id_offset

    def back(self) -> "Charuco":
        """The board printed on the back of a two-sided board, in its own frame (as a camera
        that sees the back reads it)."""
        return dataclasses.replace(self, two_sided=False,
                                   marker_id_offset=self.marker_id_offset + self._marker_count())

    @property
    def back_to_front(self) -> np.ndarray:
        """(N,) int: the front corner at which each corner of ``back()`` lies. The back is the
        front's mirror image across the board's vertical centre line x = squares_x * square_mm
        / 2, so back corner (row, col) is front corner (row, cols - 1 - col)."""
        cols, rows = self.pattern_size
        i, j = np.divmod(np.arange(cols * rows), cols)
        return i * cols + (cols - 1 - j)

    def back_texture(self, px_per_mm: float) -> np.ndarray:
        """The back's print seen through the board from the front: ``back()``'s texture mirrored
        about x = squares_x * square_mm / 2, exactly (painted mirrored, not flipped as an
        image, whose texel grid need not be symmetric about that line)."""
        width = self.squares_x * self.square_mm
        back = self.back()
        return self._texture_of(lambda black, origin, ppm: back._paint(black, origin, ppm, width),
                                px_per_mm)

    def aruco_dictionary(self) -> cv2.aruco.Dictionary:
        return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))

    def cv_board(self) -> cv2.aruco.CharucoBoard:
        """The matching OpenCV board, for CharucoDetector and matchImagePoints."""
        board = cv2.aruco.CharucoBoard(
            (self.squares_x, self.squares_y), self.square_mm, self.marker_mm,
            self.aruco_dictionary(), self.marker_ids()
        )
        board.setLegacyPattern(self.legacy)
        return board

    @property
    def pattern_size(self) -> tuple[int, int]:
        return (self.squares_x - 1, self.squares_y - 1)

    def object_points(self) -> np.ndarray:
        j, i = _grid(*self.pattern_size)
        return _on_plane((j + 1) * self.square_mm, (i + 1) * self.square_mm)

    def _feature_bounds_mm(self) -> tuple[float, float, float, float]:
        return (0.0, 0.0, self.squares_x * self.square_mm, self.squares_y * self.square_mm)

    def _paint(self, black: np.ndarray, origin_px: np.ndarray, px_per_mm: float,
               mirror_mm: float | None = None) -> None:
        """``mirror_mm``: paint the board mirrored about x = mirror_mm / 2 (``back_texture``)."""

        def cells_at(cells, x_mm, y_mm, width_mm, cell_px):
            if mirror_mm is not None:
                cells, x_mm = cells[:, ::-1], mirror_mm - x_mm - width_mm
            _add_cells(black, cells, x_mm * px_per_mm - origin_px[0],
                       y_mm * px_per_mm - origin_px[1], cell_px)

        parity = np.add.outer(np.arange(self.squares_y), np.arange(self.squares_x)) % 2 == (
            1 if self.legacy and self.squares_y % 2 == 0 else 0)  # True: a black square
        cells_at(parity, 0.0, 0.0, self.squares_x * self.square_mm, self.square_mm * px_per_mm)
        # Markers: 1-bit black border plus the dictionary bits, drawn cell by cell.
        dictionary = self.aruco_dictionary()
        cells = dictionary.markerSize + 2
        cell_px = self.marker_mm / cells * px_per_mm
        inset = (self.square_mm - self.marker_mm) / 2
        white_squares = np.argwhere(~parity)  # row-major (row, col) = marker id order
        for marker_id, (row, col) in enumerate(white_squares, self.marker_id_offset):
            bits = cv2.aruco.generateImageMarker(dictionary, marker_id, cells, borderBits=1) == 0
            cells_at(bits, col * self.square_mm + inset, row * self.square_mm + inset,
                     self.marker_mm, cell_px)


PATTERNS: dict[str, type[Pattern]] = {
    cls.kind: cls for cls in (Checkerboard, SymmetricCircles, AsymmetricCircles, Charuco)
}


def pattern_from_config(kind: str, **overrides) -> Pattern:
    """Build a board by kind name (e.g. "charuco") or short code (e.g. "Cu") with field overrides."""
    by_code = {cls.code: cls for cls in PATTERNS.values()}
    cls = PATTERNS.get(kind) or by_code.get(kind)
    if cls is None:
        raise ValueError(
            f"unknown pattern kind {kind!r}; available: "
            + ", ".join(f"{k} ({c.code})" for k, c in PATTERNS.items())
        )
    fields = {f.name for f in dataclasses.fields(cls)}
    for name in overrides:
        if name not in fields:
            raise ValueError(
                f"unknown field {name!r} for pattern {cls.kind!r}; fields: {', '.join(sorted(fields))}"
            )
    return cls(**overrides)
