"""Circle-grid centres re-measured at full resolution: each disc's darkness centroid in a window
sized by the discs' imaged diameter, NaN where a disc is cut by the image or lacks paper around
it (the package notes).
"""

from __future__ import annotations

import math

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
    """
    object_xy = pattern.object_points()[:, :2]
    r_disc = diameter_mm / 2
    r_inner, r_outer = 1.25 * r_disc, 0.5 * nearest_mm(object_xy)
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
