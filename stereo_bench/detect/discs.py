"""Circle-grid centres re-measured at full resolution: each disc's darkness centroid in a window
sized by the discs' imaged diameter, NaN where a disc is cut by the image or lacks paper around
it (the package notes).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from .saddle import nearest_mm


DISC_GUARD_PX = 2.0


def measured_discs(gray, points: np.ndarray, affines: np.ndarray, pattern, passes: int = 4):
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
    The discs are measured together (``_measure_all``), each window's pixels in one compiled
    pass.
    """
    object_xy = pattern.object_points()[:, :2]
    r_disc = diameter_mm / 2
    r_outer = 0.5 * nearest_mm(object_xy)
    print_lo, print_hi = pattern.outline_mm()[0], pattern.outline_mm()[2]
    A_inv = np.linalg.inv(affines)
    stretch = np.linalg.norm(affines, 2, axis=(1, 2))  # px per board mm, at most
    # Board mm per px across the print's sides (x = const, y = const lines).
    guard_mm = DISC_GUARD_PX * np.linalg.norm(A_inv, axis=2)
    room = np.minimum(object_xy - print_lo, print_hi - object_xy) - guard_mm
    # The print's edges (less the guard) in mm from each disc's centre: (N, 2 [lo, hi], 2).
    edges = np.stack([print_lo + guard_mm - object_xy, print_hi - guard_mm - object_xy], 1)
    # A disc whose rim touches the print's edge has no paper around it.
    refined = np.where(np.all(room >= r_disc, axis=1)[:, None], points, np.nan)
    diameters = np.full(len(points), np.nan)
    i = np.flatnonzero(np.isfinite(refined).all(axis=1))
    refined[i], diameters[i] = _measure_all(gray, refined[i], A_inv[i], stretch[i], room[i],
                                            edges[i], r_disc, r_outer, iterations)
    return refined, diameters


def _measure_all(gray, centres, A_inv, stretch, room, edges, r_disc: float, r_outer: float,
                 iterations: int) -> tuple[np.ndarray, np.ndarray]:
    """``_measure_discs`` for n discs: centres (n, 2) px and diameters (n,) mm, from the
    starting ``centres``, the maps px -> board mm ``A_inv`` (n, 2, 2), their largest
    ``stretch`` (n,) px per mm, the ``room`` (n, 2) mm to the print's outline and its ``edges``
    (n, 2, 2) mm from each disc's centre."""
    height, width = gray.shape
    r_inner = 1.25 * r_disc
    reach, disc_reach = r_outer * stretch, r_inner * stretch  # px
    centres, diameters = centres.copy(), np.full(len(centres), np.nan)
    live = np.arange(len(centres))
    for k in range(iterations):
        c = centres[live]
        held = np.all((disc_reach[live, None] <= c)
                      & (c <= [width - 1, height - 1] - disc_reach[live, None]), axis=1)
        centres[live[~held]] = np.nan
        live, c = live[held], c[held]
        if not len(live):
            break
        # Each window: the pixels within ``reach`` of the estimate, cut to the image.
        lo = np.maximum(np.floor(c - reach[live, None]), 0).astype(np.int64)
        hi = np.minimum(np.ceil(c + reach[live, None]) + 1, [width, height]).astype(np.int64)
        # Paper: the ring, inside the print; the disc window: point-symmetric about the
        # estimate and inside both the print and the image, so what lies beyond the board
        # or the image never enters, and what is cut is cut on both sides.  A window whose
        # box lies inside the print, as most do, is inside at every pixel (no test made).
        box_mm = np.einsum("nij,nj->ni", np.abs(A_inv[live]),
                           np.maximum(c - lo, hi - 1 - c))
        inside_print = np.concatenate([-room[live], room[live]], 1)
        sure_inside = _surely_within(inside_print, box_mm)
        ring_print = edges[live].reshape(-1, 4)
        sums = _window_sums(gray, c, A_inv[live], lo, hi, inside_print, sure_inside, ring_print,
                            _surely_within(ring_print, box_mm), r_inner**2, r_outer**2)
        ring_normal, ring_rhs = _normal_equations(sums[:, 0])
        disc_normal, disc_rhs = _normal_equations(sums[:, 1])
        good = (ring_normal[:, 0, 0] >= 3) & (disc_normal[:, 0, 0] > 0)  # pixel counts
        centres[live[~good]] = np.nan
        live = live[good]
        # The white plane over the ring, least squares through its normal equations (with
        # lstsq's cut-off of small singular values); the disc's darkness below it.
        plane = np.linalg.pinv(ring_normal[good], rtol=3 * np.finfo(float).eps) @ ring_rhs[
            good, :, None]
        dark = (disc_normal[good] @ plane)[..., 0] - disc_rhs[good]  # sums of 1, x, y darkness
        centres[live] = c[good] + dark[:, 1:] / dark[:, :1]
        if k == iterations - 1:
            diameters[live] = _diameters(gray, c[good], A_inv[live], lo[good], hi[good],
                                         inside_print[good], sure_inside[good],
                                         plane[..., 0], r_disc)
    diameters[~np.isfinite(centres).all(axis=1)] = np.nan
    return centres, diameters


def _diameters(gray, c, A_inv, lo, hi, inside_print, sure_inside, plane, r_disc):
    """Disc diameters (n,) mm from the last windows (about ``c``, pixels ``lo`` to ``hi``):
    the darkness below the white ``plane`` (n, 3) over the disc (radius 1.25 ``r_disc``), in
    units of the median darkness of its core (inside half the radius), is its area in px^2;
    |det A_inv| takes it to board mm^2.  NaN where the core is empty or the print's outline
    cuts the disc."""
    contrast, below, cut = _disc_darkness(gray, c, A_inv, lo, hi, inside_print, sure_inside,
                                          plane, (0.5 * r_disc) ** 2, (1.25 * r_disc) ** 2)
    area_px = below / contrast
    return np.where(np.isfinite(contrast) & ~cut,
                    2 * np.sqrt(area_px * np.abs(np.linalg.det(A_inv)) / math.pi), np.nan)


def _surely_within(bounds: np.ndarray, box_mm: np.ndarray) -> np.ndarray:
    """(n,) whether each window's box (half-extents ``box_mm`` (n, 2) mm) lies within its
    ``bounds`` (n, 4): (x lo, y lo, x hi, y hi) mm, so that every pixel of it does."""
    return np.all((bounds[:, :2] <= -box_mm) & (box_mm <= bounds[:, 2:]), axis=1)


def _normal_equations(sums: np.ndarray):
    """From ``_window_sums``' (n, 9) sums over a mask (1, x, y, xx, xy, yy, v, vx, vy): the
    normal matrix (n, 3, 3) of d = (1, x, y) and the sums of v d (n, 3).
    A plane p fitted to the values over the mask solves normal p = rhs, and normal p - rhs
    sums the plane less the values with d."""
    one, x, y, xx, xy, yy, v, vx, vy = np.moveaxis(sums, -1, 0)
    normal = np.stack([np.stack([one, x, y], -1), np.stack([x, xx, xy], -1),
                       np.stack([y, xy, yy], -1)], -2)
    return normal, np.stack([v, vx, vy], -1)


# The per-pixel work, compiled: one pass over each window's pixels, with no window-sized
# arrays (the vectorised numpy form spent most of a 12 MP circle grid's detection making and
# reading them).  Each pixel's board offset and masks are computed by the same operations, in
# the same order, as the definitions in ``_measure_discs``; only the order of the sums differs.
@numba.njit(cache=True, nogil=True)
def _to_board(a00, a01, a10, a11, ox, oy):
    """A pixel's offset (ox, oy) px from the estimate in board mm through A_inv, and r^2."""
    bx = a00 * ox + a01 * oy
    by = a10 * ox + a11 * oy
    return bx, by, bx * bx + by * by


@numba.njit(cache=True, nogil=True)
def _in_bounds(bx, by, x_lo, y_lo, x_hi, y_hi, sure):
    return sure or (x_lo <= bx <= x_hi and y_lo <= by <= y_hi)


@numba.njit(cache=True, nogil=True)
def _window_sums(gray, c, A_inv, lo, hi, inside_print, sure_inside, ring_print, sure_ring,
                 r_inner2, r_outer2):
    """(n, 2 [ring, disc], 9) sums over each window's ring and disc pixels of 1, x, y, x^2,
    xy, y^2 and the grey level v, vx, vy (x, y: offsets from the estimate ``c``), row by row."""
    out = np.zeros((len(c), 2, 9))
    row = np.zeros((2, 5))  # a row's sums of 1, x, x^2, v, vx per mask
    for i in range(len(c)):
        a00, a01, a10, a11 = A_inv[i, 0, 0], A_inv[i, 0, 1], A_inv[i, 1, 0], A_inv[i, 1, 1]
        cx, cy = c[i, 0], c[i, 1]
        # Scalars, not rows of the bounds: a view per pixel costs more than the pixel's work.
        in_x0, in_y0, in_x1, in_y1 = inside_print[i, 0], inside_print[i, 1], \
            inside_print[i, 2], inside_print[i, 3]
        ring_x0, ring_y0, ring_x1, ring_y1 = ring_print[i, 0], ring_print[i, 1], \
            ring_print[i, 2], ring_print[i, 3]
        in_sure, ring_sure = sure_inside[i], sure_ring[i]
        for y in range(lo[i, 1], hi[i, 1]):
            oy = y - cy
            row[:] = 0.0
            for x in range(lo[i, 0], hi[i, 0]):
                ox = x - cx
                bx, by, r2 = _to_board(a00, a01, a10, a11, ox, oy)
                if r2 < r_inner2:
                    if not _in_bounds(bx, by, in_x0, in_y0, in_x1, in_y1, in_sure):
                        continue
                    m = 1
                elif r2 <= r_outer2 and _in_bounds(bx, by, ring_x0, ring_y0, ring_x1, ring_y1,
                                                   ring_sure):
                    m = 0
                else:
                    continue
                v = float(gray[y, x])
                row[m, 0] += 1.0
                row[m, 1] += ox
                row[m, 2] += ox * ox
                row[m, 3] += v
                row[m, 4] += v * ox
            for m in range(2):
                out[i, m, 0] += row[m, 0]
                out[i, m, 1] += row[m, 1]
                out[i, m, 2] += oy * row[m, 0]
                out[i, m, 3] += row[m, 2]
                out[i, m, 4] += oy * row[m, 1]
                out[i, m, 5] += oy * oy * row[m, 0]
                out[i, m, 6] += row[m, 3]
                out[i, m, 7] += row[m, 4]
                out[i, m, 8] += oy * row[m, 3]
    return out


@numba.njit(cache=True, nogil=True)
def _disc_darkness(gray, c, A_inv, lo, hi, inside_print, sure_inside, plane, r_core2,
                   r_inner2):
    """Per window: the median darkness (plane - v) of the core (r^2 < ``r_core2``, inside the
    print; NaN if empty), the darkness summed over the whole disc (r^2 < ``r_inner2``, in the
    image), and whether the print's outline cuts that disc."""
    n = len(c)
    contrast, below, cut = np.full(n, np.nan), np.zeros(n), np.zeros(n, np.bool_)
    for i in range(n):
        a00, a01, a10, a11 = A_inv[i, 0, 0], A_inv[i, 0, 1], A_inv[i, 1, 0], A_inv[i, 1, 1]
        cx, cy = c[i, 0], c[i, 1]
        p0, p1, p2 = plane[i, 0], plane[i, 1], plane[i, 2]
        in_x0, in_y0, in_x1, in_y1 = inside_print[i, 0], inside_print[i, 1], \
            inside_print[i, 2], inside_print[i, 3]
        in_sure = sure_inside[i]
        core = np.empty((hi[i, 1] - lo[i, 1]) * (hi[i, 0] - lo[i, 0]))
        k = 0
        for y in range(lo[i, 1], hi[i, 1]):
            oy = y - cy
            for x in range(lo[i, 0], hi[i, 0]):
                ox = x - cx
                bx, by, r2 = _to_board(a00, a01, a10, a11, ox, oy)
                if r2 >= r_inner2:
                    continue
                weight = p0 + p1 * ox + p2 * oy - float(gray[y, x])
                below[i] += weight
                if not _in_bounds(bx, by, in_x0, in_y0, in_x1, in_y1, in_sure):
                    cut[i] = True
                elif r2 < r_core2:
                    core[k] = weight
                    k += 1
        if k:
            ranked = np.sort(core[:k])
            contrast[i] = (ranked[(k - 1) // 2] + ranked[k // 2]) / 2
    return contrast, below, cut
