"""The batched measurements (all discs, all corners at once) against a plain computation of one
feature at a time, straight from their definitions on the whole image: equal to 1e-6 px.

Images: a board texture warped by a homography into 640 x 480 (the views need not be a camera's;
only the arithmetic is compared).
"""

import math

import cv2
import numpy as np
import pytest

from stereo_bench.core.patterns import AsymmetricCircles, Checkerboard, SymmetricCircles
from stereo_bench.detect import discs
from stereo_bench.detect.boards import _find_circle_grid, _SearchImage
from stereo_bench.detect.saddle import (_bilinear_in_boxes, _Blurred, _blurred_patches,
                                        _leave_one_out, _saddle_fit, local_affines, nearest_mm)

BOUND_PX = 1e-6
H = (np.array([[0.9, 0.2, 60.0], [-0.12, 0.85, 90.0], [0.0, 0.0, 1.0]])
     @ np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [4e-4, 2e-4, 1.0]]))


def warped(pattern, px_per_mm):
    """The board's texture through ``H`` into a 640 x 480 8-bit image, and the map board mm ->
    image px."""
    texture = cv2.GaussianBlur(pattern.texture(px_per_mm).astype(np.float32), (0, 0), 1.0)
    image = cv2.warpPerspective(texture, H, (640, 480), flags=cv2.INTER_LINEAR, borderValue=110)

    def to_image(xy_mm):
        texel = (xy_mm - pattern.texture_origin_mm) * px_per_mm - 0.5
        return cv2.perspectiveTransform(texel.reshape(-1, 1, 2), H).reshape(-1, 2)
    return np.rint(image).astype(np.uint8), to_image


def disc_one_by_one(gray, centre, A, r_disc, r_outer, room, edge_lo, edge_hi, iterations=3):
    """One disc's darkness centroid and diameter (mm) as ``_measure_discs`` defines them, on a
    meshgrid of its window with lstsq on the ring's pixels (for a disc well inside the image
    and the print)."""
    A_inv, r_inner = np.linalg.inv(A), 1.25 * r_disc
    reach = r_outer * np.linalg.norm(A, 2)
    for _ in range(iterations):
        (x0, y0), (x1, y1) = np.floor(centre - reach).astype(int), np.ceil(centre + reach) + 1
        ys, xs = np.mgrid[y0:int(y1), x0:int(x1)]
        offset = np.stack([xs - centre[0], ys - centre[1]], -1)
        board = offset @ A_inv.T
        radius2 = (board**2).sum(-1)
        values = gray[y0:int(y1), x0:int(x1)].astype(float)
        ring = ((radius2 >= r_inner**2) & (radius2 <= r_outer**2)
                & np.all((board >= edge_lo) & (board <= edge_hi), -1))
        disc = (radius2 < r_inner**2) & np.all(np.abs(board) <= room, -1)
        design = np.column_stack([np.ones(ring.sum()), offset[ring]])
        plane = np.linalg.lstsq(design, values[ring], rcond=None)[0]
        weight = plane[0] + offset[disc] @ plane[1:] - values[disc]
        centre = centre + weight @ offset[disc] / weight.sum()
    # The last window's: its darkness over the disc in units of the core's median darkness.
    core = (radius2 < (0.5 * r_disc) ** 2) & np.all(np.abs(board) <= room, -1)
    darkness = plane[0] + offset @ plane[1:] - values
    area_px = darkness[radius2 < r_inner**2].sum() / np.median(darkness[core])
    return centre, 2 * math.sqrt(area_px * abs(np.linalg.det(A_inv)) / math.pi)


@pytest.mark.parametrize("pattern", [SymmetricCircles(), AsymmetricCircles()])
def test_discs_measured_together_equal_discs_measured_one_by_one(pattern):
    gray, _ = warped(pattern, 1.8)
    points, affines = _find_circle_grid(_SearchImage.of(gray), pattern)
    centres, diameters = discs._measure_discs(gray, points, affines, pattern, pattern.diameter_mm)
    assert np.isfinite(centres).all() and np.isfinite(diameters).all()
    object_xy = pattern.object_points()[:, :2]
    lo, hi = pattern.outline_mm()[0], pattern.outline_mm()[2]
    for i, A in enumerate(affines):
        guard = discs.DISC_GUARD_PX * np.linalg.norm(np.linalg.inv(A), axis=1)
        reference, diameter = disc_one_by_one(
            gray, points[i], A, pattern.diameter_mm / 2, 0.5 * nearest_mm(object_xy),
            np.minimum(object_xy[i] - lo, hi - object_xy[i]) - guard,
            lo + guard - object_xy[i], hi - guard - object_xy[i])
        assert np.abs(centres[i] - reference).max() < BOUND_PX, i
        assert abs(diameters[i] - diameter) < 1e-9, i


def saddle_step_one_by_one(gradient, q, A_inv, lim, box_lo, box_hi, band_mm):
    """One corner's step of the Förstner fit as ``refine_saddles`` defines it, pixel by pixel
    over its window, with ``gradient`` (2, H, W) of the whole image blurred."""
    height, width = gradient.shape[1:]
    ys, xs = np.mgrid[box_lo[1]:box_hi[1], box_lo[0]:box_hi[0]]
    p = np.stack([xs, ys], -1).reshape(-1, 2).astype(float)
    theta = 0.5 * np.pi * ((p - q) @ A_inv.T) / lim
    use = (np.all(np.abs(p - q) <= np.minimum(q, [width - 1, height - 1] - q), axis=1)
           & np.all(np.abs(theta) <= 0.5 * np.pi, axis=1))
    if band_mm is not None:
        use &= np.any(np.abs(theta) < 0.5 * np.pi * band_mm / lim, axis=1)
    w = np.prod(np.cos(theta) ** 2, axis=1) * use
    g = gradient[:, ys.ravel(), xs.ravel()].T
    normal = (w[:, None] * g).T @ g
    rhs = (w[:, None] * g).T @ (g * (p - q)).sum(1)
    return np.linalg.solve(normal, rhs)


@pytest.mark.parametrize("band_mm", [None, 2.0])
def test_saddle_steps_of_all_corners_equal_one_corner_at_a_time(band_mm):
    pattern, sigma = Checkerboard(), 1.2
    gray, to_image = warped(pattern, 1.8)
    object_xy = pattern.object_points()[:, :2]
    truth = to_image(object_xy)
    start = truth + np.random.default_rng(1).uniform(-0.5, 0.5, truth.shape)
    A = local_affines(object_xy, truth, 1.5 * pattern.square_mm)[0]
    lim = np.full((len(A), 2), 0.4 * pattern.square_mm)
    half = np.einsum("mij,mj->mi", np.abs(A), lim)
    box_lo = np.floor(start - half).astype(int)
    box_hi = np.ceil(start + half).astype(int) + 1
    assert box_lo.min() >= 1 and np.all(box_hi <= [639, 479])
    origin = box_lo - 3
    size = int((box_hi - origin).max()) + 3
    # The corners' rows of a stack that holds them in reverse order after one other square.
    stack = _blurred_patches(_Blurred(gray, sigma, 0), np.concatenate([origin[:1], origin[::-1]]),
                             size)
    rows = np.arange(len(origin), 0, -1)
    q, steps, ok = start.copy(), np.zeros(len(A), np.int64), np.zeros(len(A), bool)
    moved_out = _saddle_fit(stack, rows, origin, size, np.arange(len(A)), q, half,
                            np.linalg.inv(A), lim, np.inf if band_mm is None else band_mm, 640,
                            480, steps, ok, 1)
    assert len(moved_out) == 0 and np.all(steps == 1)  # one step each, every one solved
    shift = q - start
    blurred = cv2.GaussianBlur(gray.astype(np.float32), (0, 0), sigma).astype(float)
    gradient = np.zeros((2,) + gray.shape)
    gradient[0, :, 1:-1] = 0.5 * (blurred[:, 2:] - blurred[:, :-2])
    gradient[1, 1:-1] = 0.5 * (blurred[2:] - blurred[:-2])
    for m in range(len(A)):
        reference = saddle_step_one_by_one(gradient, start[m], np.linalg.inv(A[m]), lim[m],
                                           box_lo[m], box_hi[m], band_mm)
        assert math.dist(shift[m], reference) < BOUND_PX, m
    # The step goes most of the way to the corner from half a pixel off.
    assert np.linalg.norm(start + shift - truth, axis=1).mean() < 0.1


@pytest.mark.parametrize("sigma", [0.8, 1.2, 2.5])
def test_a_box_blurred_alone_equals_the_whole_image_blurred(sigma):
    """The saddle fit blurs either each box alone (a large image) or the whole image once (a
    small one): the same values, in the image and at each of its borders, to float32 rounding
    (OpenCV's blur of a box and of the whole image differ by up to 2 ulp of a level near 255,
    3.1e-5, over 2079 random boxes at 7 sigmas; the bound is 3 of them)."""
    gray, _ = warped(Checkerboard(), 1.8)
    alone, whole = _Blurred(gray, sigma, 0), _Blurred(gray, sigma, 10 ** 6)
    assert alone.whole is None and whole.whole is not None
    for box in [(200, 150, 260, 230), (-5, -7, 40, 33), (600, 440, 700, 520), (0, 300, 1, 301),
                (639, 0, 640, 480), (700, 10, 720, 20)]:
        a, b = alone.box(*box), whole.box(*box)
        if a is None:
            assert b is None
            continue
        assert a[1] == b[1] and a[0].dtype == b[0].dtype == np.float32
        assert np.abs(a[0] - b[0]).max() <= 3 * np.spacing(np.float32(255)), box


@pytest.mark.parametrize("sigma", [0.8, 1.5])
def test_patches_cut_from_the_whole_blur_equal_those_cut_box_by_box(sigma):
    """A small image's patches come from its whole blur in one compiled pass: squares of the
    whole blur with one pixel more on every side, zero off the image, at every border."""
    gray, _ = warped(Checkerboard(), 1.8)
    whole = _Blurred(gray, sigma, 10 ** 6)
    origin = np.array([[200, 150], [-9, -4], [620, 460], [-30, 100], [300, 490]])
    size, pad = 24, 40
    framed = np.pad(whole.whole.astype(float), pad)  # zeros beyond the image
    expected = np.stack([framed[pad + y - 1:pad + y + size + 1, pad + x - 1:pad + x + size + 1]
                         for x, y in origin])
    assert np.array_equal(_blurred_patches(whole, origin, size), expected)


def fits_one_point_at_a_time(object_xy, points, radius_mm):
    """``local_affines`` and ``_leave_one_out`` by their definitions, one point at a time with
    lstsq and matrix_rank over its neighbours."""
    n = len(points)
    affines, misfit, loo = np.full((n, 2, 2), np.nan), np.full(n, np.nan), np.full(n, np.nan)
    seen = np.isfinite(points).all(axis=1)
    for i in np.flatnonzero(seen):
        near = [j for j in np.flatnonzero(seen) if j != i
                and np.linalg.norm(object_xy[j] - object_xy[i]) <= radius_mm]
        d_obj, d_img = object_xy[near] - object_xy[i], points[near] - points[i]
        # Rank as matrix_rank decides it over the N x 2 offsets (zero rows for the others).
        rows = np.zeros((n, 2))
        rows[:len(near)] = d_obj
        if np.linalg.matrix_rank(rows) == 2:
            A = np.linalg.lstsq(d_obj, d_img, rcond=None)[0].T
            affines[i] = A
            misfit[i] = (np.linalg.norm(d_obj @ A.T - d_img, axis=1).max()
                         / np.linalg.norm(A, 2))
        if len(near) >= 3:
            sol = np.linalg.lstsq(np.column_stack([d_obj, np.ones(len(near))]), points[near],
                                  rcond=None)[0]
            loo[i] = np.linalg.norm(sol[2] - points[i]) / np.linalg.norm(sol[:2], 2)
    return affines, misfit, loo


@pytest.mark.parametrize("pattern", [Checkerboard(), SymmetricCircles(), AsymmetricCircles()])
def test_local_fits_of_all_points_equal_one_point_at_a_time(pattern):
    """The compiled local fits against lstsq point by point: perspective views with noise,
    points missing at random, and lone rows (neighbours on a line: no map, the prediction
    lstsq's minimum-norm answer): the same points fitted, equal to 1e-9 of their scale."""
    object_xy = pattern.object_points()[:, :2]
    radius = 1.5 * nearest_mm(object_xy)
    rng = np.random.default_rng(3)
    for trial in range(40):
        H = np.array([[3 + rng.normal(0, 0.5), rng.normal(0, 0.5), 300.0],
                      [rng.normal(0, 0.5), 3 + rng.normal(0, 0.5), 200.0],
                      [rng.normal(0, 1e-3), rng.normal(0, 1e-3), 1.0]])
        image = np.column_stack([object_xy, np.ones(len(object_xy))]) @ H.T
        points = image[:, :2] / image[:, 2:] + rng.normal(0, 0.3, object_xy.shape)
        points[rng.random(len(points)) < [0.0, 0.3, 0.6, 0.85][trial % 4]] = np.nan
        if trial % 5 == 0:
            points[5:] = np.nan  # the first row's start alone
        affines, misfit = local_affines(object_xy, points, radius)
        loo = _leave_one_out(object_xy, points, radius)
        ref_affines, ref_misfit, ref_loo = fits_one_point_at_a_time(object_xy, points, radius)
        for ours, ref in [(affines, ref_affines), (misfit, ref_misfit), (loo, ref_loo)]:
            assert np.array_equal(np.isnan(ours), np.isnan(ref)), trial
            fitted = np.isfinite(ref)
            assert np.all(np.abs(ours[fitted] - ref[fitted])
                          <= 1e-9 * np.maximum(np.abs(ref[fitted]), 1.0)), trial


def test_samples_read_from_the_whole_blur_equal_opencvs_remap_of_each_box():
    """The print's extents sample a small image's boxes in one compiled pass: cv2.remap's
    bilinear values on each box alone, NaN where a tap leaves the box, over boxes cut by every
    border and samples on and between the 1/64 px grid; equal to float32 rounding (bit for bit
    where OpenCV's lerps are fused multiply-adds, as the compiled pass computes them)."""
    gray, _ = warped(Checkerboard(), 1.8)
    whole = cv2.GaussianBlur(gray.astype(np.float32), (0, 0), 1.2)
    rng = np.random.default_rng(7)
    lo = np.column_stack([rng.integers(-20, 640, 400), rng.integers(-20, 480, 400)])
    hi = lo + rng.integers(1, 60, (400, 2))
    xy = lo[:, None] - 2 + rng.random((400, 80, 2)) * (hi - lo + 3)[:, None]
    xy[::3] = np.round(xy[::3] * 64) / 64
    start, end = np.maximum(lo, 0), np.minimum(hi, [640, 480])
    inside = np.all(end > start, axis=1)
    local = (xy - start[:, None]).astype(np.float32)
    ours = _bilinear_in_boxes(whole, start, end, inside, local)
    assert inside.sum() > 300 and np.isnan(ours[~inside]).all()
    for r in np.flatnonzero(inside):
        box = whole[start[r, 1]:end[r, 1], start[r, 0]:end[r, 0]]
        ref = cv2.remap(box, local[r, :, :1], local[r, :, 1:], cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan).ravel()
        assert np.array_equal(np.isnan(ours[r]), np.isnan(ref)), r
        assert np.nanmax(np.abs(ours[r] - ref), initial=0.0) <= np.spacing(np.float32(255)), r
