"""Boards: counts, spacing, exact textures, and OpenCV's detectors finding the points in our order.

Every detection test runs the matching OpenCV detector on the texture itself (a fronto-parallel view
with no perspective, so no circle-centre bias) and compares with the prediction of the documented
pixel convention: board (X, Y) is at image ((X, Y) - texture_origin_mm) * px_per_mm - 0.5.
Two scales: 8 px/mm puts every corner and circle centre on a texel centre; 6.61 px/mm puts them at
arbitrary sub-texel positions, where the texture is blurred slightly (sigma 1 texel, symmetric, so it
moves no feature) because cornerSubPix is biased by ~0.08 px on perfectly sharp one-texel edges.
"""

import math

import cv2
import numpy as np
import pytest

from stereo_bench.detect import boards
from stereo_bench.detect.boards import _any_marker_seen, detect
from stereo_bench.core.patterns import (PATTERNS, AsymmetricCircles, Charuco, Checkerboard,
                                        SymmetricCircles, pattern_from_config)

SCALES = [(8.0, 0.0), (6.61, 1.0)]  # (px_per_mm, Gaussian blur sigma in texels)
TOLERANCE_PX = 0.05


def view(pattern, px_per_mm, sigma):
    image = pattern.texture(px_per_mm)
    return cv2.GaussianBlur(image, (0, 0), sigma) if sigma else image


def predicted_px(pattern, px_per_mm):
    return (pattern.object_points()[:, :2] - pattern.texture_origin_mm) * px_per_mm - 0.5


def upside_down(image, points_px):
    """The image rotated by 180 degrees and where the given points land in it."""
    height, width = image.shape
    return np.ascontiguousarray(image[::-1, ::-1]), np.array([width - 1, height - 1]) - points_px


def find_circles(pattern, image):
    params = cv2.SimpleBlobDetector_Params()
    params.minArea, params.maxArea = 10.0, 1e7  # default maxArea (5000 px^2) drops our large discs
    flags = {
        "symmetric_circles": cv2.CALIB_CB_SYMMETRIC_GRID,
        "asymmetric_circles": cv2.CALIB_CB_ASYMMETRIC_GRID,
    }[pattern.kind]
    found, centres = cv2.findCirclesGrid(
        image, pattern.pattern_size, flags=flags, blobDetector=cv2.SimpleBlobDetector_create(params)
    )
    assert found
    return centres.reshape(-1, 2)


def find_chessboard(pattern, image):
    found, corners = cv2.findChessboardCorners(image, pattern.pattern_size)
    assert found
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-6)
    # OpenCV 5.0 returns (N, 2) here; cornerSubPix wants (N, 1, 2).
    return cv2.cornerSubPix(image, corners.reshape(-1, 1, 2), (7, 7), (-1, -1), criteria).reshape(-1, 2)


# --------------------------------------------------------------------------------------- geometry
@pytest.mark.parametrize(
    "pattern, count, pattern_size, step_mm",
    [
        (Checkerboard(), 88, (8, 11), 15.0),
        (SymmetricCircles(), 100, (10, 10), 15.0),
        (AsymmetricCircles(), 90, (10, 9), 22.0),
        (Charuco(), 88, (8, 11), 15.0),
    ],
)
def test_counts_spacing_and_frame(pattern, count, pattern_size, step_mm):
    points = pattern.object_points()
    assert points.shape == (count, 3) and points.dtype == np.float64
    assert np.all(points[:, 2] == 0.0)
    assert pattern.pattern_size == pattern_size
    np.testing.assert_array_equal(pattern.ids(), np.arange(count))
    # Nearest-neighbour distance is the board's pitch (diagonal one for the asymmetric grid).
    distances = np.linalg.norm(points[:, None] - points[None], axis=2) + np.eye(count) * 1e9
    np.testing.assert_allclose(distances.min(axis=1), step_mm, rtol=1e-12)
    # Row-major, x to the right and y down: the first point is the top-left one.
    assert np.all(points[0, :2] == points[:, :2].min(axis=0))
    # The outline encloses every feature with the quiet zone to spare.
    origin, size = pattern.texture_origin_mm, np.array(pattern.size_mm)
    assert np.all(points[:, :2] - origin >= pattern.margin_mm)
    assert np.all(origin + size - points[:, :2] >= pattern.margin_mm)


def test_paper_board_sizes():
    assert Checkerboard().size_mm == pytest.approx((9 * 15 + 20, 12 * 15 + 20))
    assert SymmetricCircles().size_mm == pytest.approx((9 * 15 + 7 + 20, 9 * 15 + 7 + 20))
    s = 22 / math.sqrt(2)
    assert AsymmetricCircles().size_mm == pytest.approx((19 * s + 9 + 20, 8 * s + 9 + 20))
    assert Charuco().size_mm == pytest.approx((9 * 15 + 20, 12 * 15 + 20))
    np.testing.assert_allclose(Checkerboard().texture_origin_mm, [-25.0, -25.0])
    np.testing.assert_allclose(Charuco().texture_origin_mm, [-10.0, -10.0])


@pytest.mark.parametrize("pattern", [Checkerboard(), SymmetricCircles(), AsymmetricCircles(), Charuco()])
def test_texture_shape_covers_the_outline(pattern):
    for px_per_mm in (8.0, 6.61):
        height, width = pattern.texture(px_per_mm).shape
        assert width == math.ceil(pattern.size_mm[0] * px_per_mm - 1e-9)
        assert height == math.ceil(pattern.size_mm[1] * px_per_mm - 1e-9)


def test_disc_texture_has_exact_area_and_centroid():
    # Independent of any detector: the ink in each disc's window integrates to the disc's area and
    # its centroid (texel centres as positions) sits on the predicted centre.
    pattern, px_per_mm = AsymmetricCircles(), 6.61
    ink = (255.0 - pattern.texture(px_per_mm)) / 255.0
    radius_px = pattern.diameter_mm / 2 * px_per_mm
    half = int(radius_px) + 3
    for cx, cy in predicted_px(pattern, px_per_mm):
        i0, j0 = int(round(cy)) - half, int(round(cx)) - half
        window = ink[i0:i0 + 2 * half + 1, j0:j0 + 2 * half + 1]
        rows, cols = np.mgrid[i0:i0 + window.shape[0], j0:j0 + window.shape[1]]
        area = window.sum()
        assert area == pytest.approx(math.pi * radius_px**2, rel=2e-4)
        assert abs((window * cols).sum() / area - cx) < 2e-3
        assert abs((window * rows).sum() / area - cy) < 2e-3


def test_checkerboard_texture_is_pixel_exact_when_aligned():
    board, px_per_mm = Checkerboard(), 8.0
    square = int(board.square_mm * px_per_mm)
    margin = int(board.margin_mm * px_per_mm)
    expected = np.full(board.texture_shape(px_per_mm), 255, np.uint8)
    for row in range(board.squares_y):
        for col in range(board.squares_x):
            if (row + col) % 2 == 0:
                y, x = margin + row * square, margin + col * square
                expected[y:y + square, x:x + square] = 0
    np.testing.assert_array_equal(board.texture(px_per_mm), expected)


# -------------------------------------------------------------------------------------- detectors
@pytest.mark.parametrize("px_per_mm, sigma", SCALES)
def test_checkerboard_detected_in_order(px_per_mm, sigma):
    board = Checkerboard()
    image, expected = view(board, px_per_mm, sigma), predicted_px(board, px_per_mm)
    assert np.abs(find_chessboard(board, image) - expected).max() < TOLERANCE_PX
    # The odd x even colouring fixes the orientation: upside down, the same physical order.
    rotated, expected_rotated = upside_down(image, expected)
    assert np.abs(find_chessboard(board, rotated) - expected_rotated).max() < TOLERANCE_PX


def test_checkerboard_sb_returns_reverse_order():
    board, px_per_mm = Checkerboard(), 4.0  # SB is slow; 4 px/mm still gives 60 px squares
    found, corners = cv2.findChessboardCornersSB(
        board.texture(px_per_mm), board.pattern_size, flags=cv2.CALIB_CB_ACCURACY
    )
    assert found
    error = corners.reshape(-1, 2)[::-1] - predicted_px(board, px_per_mm)
    assert np.abs(error).max() < TOLERANCE_PX


@pytest.mark.parametrize("px_per_mm, sigma", SCALES)
@pytest.mark.parametrize("pattern", [SymmetricCircles(), AsymmetricCircles()])
def test_circle_grids_detected_in_order(pattern, px_per_mm, sigma):
    image, expected = view(pattern, px_per_mm, sigma), predicted_px(pattern, px_per_mm)
    assert np.abs(find_circles(pattern, image) - expected).max() < TOLERANCE_PX
    rotated, expected_rotated = upside_down(image, expected)
    if pattern.kind == "symmetric_circles":
        # 180-degree symmetric: the detector orders by image position, so upside down is reversed.
        expected_rotated = expected_rotated[::-1]
    assert np.abs(find_circles(pattern, rotated) - expected_rotated).max() < TOLERANCE_PX


def test_charuco_geometry_matches_opencv_board():
    board = Charuco()
    np.testing.assert_allclose(
        board.object_points(), board.cv_board().getChessboardCorners(), rtol=0, atol=1e-5
    )
    # Pixel-exact against OpenCV's own drawing where marker cells fall on whole texels
    # (11.25 mm markers = 9 cells of 1.25 mm = 10 texels at 8 px/mm).
    aligned, px_per_mm = Charuco(marker_mm=11.25), 8.0
    height, width = aligned.texture_shape(px_per_mm)
    reference = aligned.cv_board().generateImage(
        (width, height), marginSize=int(aligned.margin_mm * px_per_mm), borderBits=1
    )
    np.testing.assert_array_equal(aligned.texture(px_per_mm), reference)


@pytest.mark.parametrize("squares_y", [12, 11])
def test_legacy_charuco_is_opencvs_legacy_board(squares_y):
    """Boards made by OpenCV before 4.6: with an even row count the top-left square is white and
    the markers move to the other squares; our drawing is OpenCV's own, pixel for pixel, and a
    detector told the wrong layout finds no corner of an even board."""
    legacy, px_per_mm = Charuco(marker_mm=11.25, squares_y=squares_y, legacy=True), 8.0
    height, width = legacy.texture_shape(px_per_mm)
    reference = legacy.cv_board().generateImage(
        (width, height), marginSize=int(legacy.margin_mm * px_per_mm), borderBits=1)
    np.testing.assert_array_equal(legacy.texture(px_per_mm), reference)
    image = view(legacy, px_per_mm, 1.0)
    found = detect(image, legacy)
    assert found.found
    assert np.abs(found.points - predicted_px(legacy, px_per_mm)).max() < TOLERANCE_PX
    plain = detect(image, Charuco(marker_mm=11.25, squares_y=squares_y))
    assert plain.found == (squares_y % 2 == 1)


def test_charuco_seen_from_behind_is_found_mirrored_back():
    """A one-sided print seen through the board is the mirror image: every corner is found at its
    own id, where it lies in the image."""
    board, px_per_mm = Charuco(), 6.61
    image = view(board, px_per_mm, 1.0)
    width = image.shape[1]
    expected = predicted_px(board, px_per_mm) * [-1, 1] + [width - 1, 0]
    for seen in (image[:, ::-1], 255 - image[:, ::-1]):  # against the light: inverted as well
        found = detect(np.ascontiguousarray(seen), board)
        assert found.found and np.isfinite(found.points).all()
        assert np.abs(found.points - expected).max() < TOLERANCE_PX


def test_one_marker_search_tells_whether_a_charuco_board_is_in_view():
    """The search that decides whether the other polarity and the mirror are tried finds the
    board's markers in all four prints, and none in a board without markers."""
    board, px_per_mm = Charuco(), 6.61
    image = view(board, px_per_mm, 1.0)
    for seen in (image, 255 - image, image[:, ::-1], 255 - image[:, ::-1]):
        assert _any_marker_seen(np.ascontiguousarray(seen), board)
    assert not _any_marker_seen(view(Checkerboard(), px_per_mm, 1.0), board)
    # Looked for first (a board likely out of view), it changes the order, not the result.
    for seen in (image, 255 - image[:, ::-1], view(Checkerboard(), px_per_mm, 1.0)):
        seen = np.ascontiguousarray(seen)
        first, later = detect(seen, board, in_view=False), detect(seen, board)
        assert (first.found, first.error) == (later.found, later.error)
        np.testing.assert_array_equal(first.points, later.points)


@pytest.mark.parametrize("px_per_mm, sigma", SCALES)
def test_charuco_detected_with_ids(px_per_mm, sigma):
    board = Charuco()
    image = view(board, px_per_mm, sigma)
    corners, ids, _, marker_ids = cv2.aruco.CharucoDetector(board.cv_board()).detectBoard(image)
    assert len(marker_ids) == 54
    ids = ids.ravel()
    np.testing.assert_array_equal(np.sort(ids), board.ids())
    error = corners.reshape(-1, 2) - predicted_px(board, px_per_mm)[ids]
    assert np.abs(error).max() < TOLERANCE_PX


# ---------------------------------------------------------------------------------- construction
def test_factory_builds_by_kind_or_code_with_overrides():
    assert pattern_from_config("checkerboard") == Checkerboard()
    board = pattern_from_config("Cu", marker_mm=10.0, dictionary="DICT_7X7_1000")
    assert isinstance(board, Charuco) and board.marker_mm == 10.0
    assert {cls.code for cls in PATTERNS.values()} == {"Ch", "Sc", "Ac", "Cu"}
    assert [p().name for p in PATTERNS.values()] == list(PATTERNS)


def test_factory_rejects_unknown_kind_and_field():
    with pytest.raises(ValueError, match="available: checkerboard.*symmetric_circles.*charuco"):
        pattern_from_config("hexagons")
    with pytest.raises(ValueError, match="'marker_mm'"):
        pattern_from_config("checkerboard", marker_mm=11.0)


@pytest.mark.parametrize(
    "kind, overrides, field",
    [
        ("checkerboard", {"square_mm": -15.0}, "square_mm"),
        ("checkerboard", {"squares_x": 2}, "squares_x"),
        ("symmetric_circles", {"diameter_mm": 15.0}, "diameter_mm"),
        ("asymmetric_circles", {"rows": 10}, "rows"),
        ("charuco", {"marker_mm": 15.0}, "marker_mm"),
        ("charuco", {"dictionary": "DICT_4X4_50", "squares_x": 20}, "dictionary"),
        ("charuco", {"dictionary": "DICT_NOPE"}, "dictionary"),
    ],
)
def test_invalid_geometry_names_the_field(kind, overrides, field):
    with pytest.raises(ValueError, match=field):
        pattern_from_config(kind, **overrides)


def test_a_charuco_board_seen_with_too_few_corners_ends_the_search(monkeypatch):
    """A board read in one polarity (two of its markers or more) but with too few corners between
    them is not looked for again in the other polarity or mirrored, and the failure says what
    was seen: one marker search as printed; seen inverted or mirrored, the searches stop at the
    print it is (each search before it, and the one that tells whether any marker is there)."""
    board, px_per_mm = Charuco(), 6.61
    image = view(board, px_per_mm, 1.0)
    corner = round((2 * board.square_mm + board.margin_mm) * px_per_mm)  # two squares a side
    covered = np.full_like(image, 255)
    covered[:corner, :corner] = image[:corner, :corner]
    searches = []
    real = boards.detect_markers
    monkeypatch.setattr(boards, "detect_markers",
                        lambda *args, **kwargs: searches.append(1) or real(*args, **kwargs))
    for seen, expected in ((covered, 1), (255 - covered, 3), (covered[:, ::-1], 4)):
        searches.clear()
        found = detect(np.ascontiguousarray(seen), board)
        assert not found.found and found.board_seen
        assert found.error == "only 1 ChArUco corners (2 markers) found, need 6"
        assert np.isnan(found.points).all() and len(searches) == expected
