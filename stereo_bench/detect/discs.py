"""Circle-grid centres re-measured at full resolution: each disc's darkness centroid in a window
sized by the discs' imaged diameter, NaN where a disc is cut by the image or lacks paper around
it (the package notes).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from .saddle import nearest_mm


DISC_GUARD_PX = 2.0


# Window pixels measured at once: all the wide camera's discs fit in one batch; the 4096 x 3072
# camera's (10^4-10^5 px each) go in batches of 2 MB float arrays (2^16-2^20 px per batch
# measured: 2^18 was fastest there, 10 % ahead of 2^17 and 2^19).
_BATCH_PX = 1 << 18


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
    The discs are measured together, in batches of similar window size (``_measure_batch``): one
    disc at a time cost more in numpy calls than in arithmetic on the wide camera's small windows.
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
    todo = np.flatnonzero(np.isfinite(refined).all(axis=1))
    side = 2 * np.ceil(r_outer * stretch[todo]).astype(int) + 2  # px across a window, at most
    todo, side = todo[np.argsort(side)], np.sort(side)
    for batch in np.split(np.arange(len(todo)),
                          np.flatnonzero(np.diff(np.cumsum(side**2) // _BATCH_PX)) + 1):
        if len(batch):
            i = todo[batch]
            refined[i], diameters[i] = _measure_batch(
                gray, refined[i], A_inv[i], stretch[i], room[i], edges[i], side[batch[-1]],
                r_disc, r_outer, iterations)
    return refined, diameters


def _measure_batch(gray, centres, A_inv, stretch, room, edges, side: int, r_disc: float,
                   r_outer: float, iterations: int) -> tuple[np.ndarray, np.ndarray]:
    """``_measure_discs`` for n discs at once, on windows at most ``side`` px across: centres
    (n, 2) px and diameters (n,) mm, from the starting ``centres``, the maps px -> board mm
    ``A_inv`` (n, 2, 2), their largest ``stretch`` (n,) px per mm, the ``room`` (n, 2) mm to
    the print's outline and its ``edges`` (n, 2, 2) mm from each disc's centre."""
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
        patch, ox, oy, valid, half = _windows(gray, c, reach[live], side)
        # Board mm from the disc's centre, the window's x (a row) and y (a column) broadcast.
        a = A_inv[live, :, :, None, None]
        bx = a[:, 0, 0] * ox[:, None, :] + a[:, 0, 1] * oy[:, :, None]
        by = a[:, 1, 0] * ox[:, None, :] + a[:, 1, 1] * oy[:, :, None]
        radius2 = bx * bx + by * by  # mm^2
        # Paper: the ring, inside the print; the disc window: point-symmetric about the
        # estimate and inside both the print and the image, so what lies beyond the board
        # or the image never enters, and what is cut is cut on both sides.
        box_mm = np.einsum("nij,nj->ni", np.abs(A_inv[live]), half)
        inside = _within(bx, by, -room[live], room[live], box_mm) & valid
        ring = ((radius2 >= r_inner**2) & (radius2 <= r_outer**2) & valid
                & _within(bx, by, edges[live, 0], edges[live, 1], box_mm))
        disc = (radius2 < r_inner**2) & inside
        ring_normal, ring_rhs = _plane_sums(ring, patch, ox, oy)
        disc_normal, disc_rhs = _plane_sums(disc, patch, ox, oy)
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
            diameters[live] = _diameters(radius2[good], inside[good], valid[good], patch[good],
                                         ox[good], oy[good], plane[..., 0], r_disc,
                                         np.abs(np.linalg.det(A_inv[live])))
    diameters[~np.isfinite(centres).all(axis=1)] = np.nan
    return centres, diameters


def _diameters(radius2, inside, valid, patch, ox, oy, plane, r_disc, det_inv):
    """Disc diameters (n,) mm from the last window: its darkness below the white ``plane``
    (n, 3) over the disc (radius 1.25 ``r_disc``), in units of the median darkness of its core
    (inside half the radius), is its area in px^2; ``det_inv`` (n,) board mm^2 per px^2.  NaN
    where the core is empty or the print's outline cuts the disc."""
    r_inner = 1.25 * r_disc
    core = (radius2 < (0.5 * r_disc) ** 2) & inside
    whole = (radius2 < r_inner**2) & valid
    n, y, x = np.nonzero(core)
    weight = plane[n, 0] + plane[n, 1] * ox[n, x] + plane[n, 2] * oy[n, y] - patch[n, y, x]
    contrast = _medians(weight, n, len(patch))
    normal, rhs = _plane_sums(whole, patch, ox, oy)
    area_px = ((normal @ plane[..., None])[:, 0, 0] - rhs[:, 0]) / contrast
    cut = (whole & ~inside).any(axis=(1, 2))
    return np.where(np.isfinite(contrast) & ~cut,
                    2 * np.sqrt(area_px * det_inv / math.pi), np.nan)


def _medians(values: np.ndarray, groups: np.ndarray, n: int) -> np.ndarray:
    """The median (as np.median) of ``values`` in each of the ``n`` groups numbered by ``groups``
    (sorted): (n,), NaN for an empty group.  One sort for all groups, not a call per disc."""
    order = np.lexsort((values, groups))
    ranked = values[order]
    count = np.bincount(groups, minlength=n)
    start = np.cumsum(count) - count
    low, high = start + np.maximum(count - 1, 0) // 2, start + count // 2
    some = count > 0
    out = np.full(n, np.nan)
    out[some] = (ranked[low[some]] + ranked[high[some]]) / 2
    return out


def _windows(gray, centres: np.ndarray, reach: np.ndarray, side: int):
    """Each estimate's window of ``gray``, ``reach`` (n,) px about ``centres`` (n, 2) px and cut
    to the image, in a stack of equal boxes ``side`` px across (fewer if the image is smaller).

    Returns float64 copies (n, rows, columns), the offsets of the columns (n, columns) and of the
    rows (n, rows) from each estimate, which pixels belong to the window (n, rows, columns), and
    its largest offsets (n, 2) px.  One gather from the 8-bit image for all windows.
    """
    height, width = gray.shape
    lo = np.maximum(np.floor(centres - reach[:, None]), 0).astype(int)
    hi = np.minimum(np.ceil(centres + reach[:, None]) + 1, [width, height]).astype(int)
    size = np.minimum(side, [width, height])
    start = np.minimum(lo, [width, height] - size)
    patch = sliding_window_view(gray, (size[1], size[0]))[start[:, 1], start[:, 0]]
    x = start[:, :1] + np.arange(size[0])
    y = start[:, 1:] + np.arange(size[1])
    valid = (((y >= lo[:, 1:]) & (y < hi[:, 1:]))[:, :, None]
             & ((x >= lo[:, :1]) & (x < hi[:, :1]))[:, None, :])
    half = np.maximum(centres - lo, hi - 1 - centres)
    return patch.astype(float), x - centres[:, :1], y - centres[:, 1:], valid, half


def _within(bx, by, lo, hi, box_mm):
    """Which pixels' board offsets ``bx``, ``by`` (n, rows, columns) mm lie within [lo, hi]
    (n, 2) mm.  A window whose box (half-extents ``box_mm`` (n, 2)) lies inside, as most do,
    is inside at every pixel: when all do, no per-pixel test is made."""
    sure = np.all((lo <= -box_mm) & (box_mm <= hi), axis=1)
    if sure.all():
        return np.True_
    lo, hi = lo[:, :, None, None], hi[:, :, None, None]
    return sure[:, None, None] | ((bx >= lo[:, 0]) & (bx <= hi[:, 0])
                                  & (by >= lo[:, 1]) & (by <= hi[:, 1]))


def _plane_sums(mask, values, ox, oy):
    """Over each window's ``mask`` (n, rows, columns): the normal matrix (n, 3, 3), sums of
    d d^T with d = (1, x, y), and the sums of ``values`` d (n, 3), x and y the offsets of the
    columns ``ox`` (n, columns) and rows ``oy`` (n, rows).

    A plane p fitted to the values over the mask solves normal p = rhs, and normal p - rhs sums
    the plane less the values with d.  The sums go along rows against 1, x, x^2, then down the
    rows against 1, y, y^2: two products, no pixels gathered.
    """
    m = mask.astype(float)
    xs = np.stack([np.ones_like(ox), ox, ox * ox], -1)
    ys = np.stack([np.ones_like(oy), oy, oy * oy], -1)
    s = np.einsum("nrk,nrj->nkj", ys, m @ xs)  # s[k, j]: sum of y^k x^j
    v = np.einsum("nrk,nrj->nkj", ys[..., :2], (m * values) @ xs[..., :2])
    power_y, power_x = np.array([0, 0, 1]), np.array([0, 1, 0])  # of d's entries
    normal = s[:, power_y[:, None] + power_y, power_x[:, None] + power_x]
    return normal, v[:, power_y, power_x]
