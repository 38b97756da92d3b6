"""The imaging model (imaging.py) fitted to real images of a checkerboard: its inverse.

Given a camera's images of a board and a calibration of it (the camera and each view's pose),
every effect is measured on the board itself, where the calibration says each square and each
edge lies:

* **print levels**: the black squares' grey level (median over the views), the white squares'
  on the axis (below), and the background (pixels off the board, the vignetting divided out);
* **noise against signal** (photon transfer, EMVA 1288): the inner half of each square is a
  patch of one grey level under smooth light; after removing a plane (the shading across it) the
  variance of its pixels against their mean gives ``var = read^2 + gain * mean`` by least squares
  over every square of every view: the gain (grey levels per electron) and the read noise;
* **vignetting**: the white squares' level against their rays' angle to the optical axis,
  ``W = W0 cos^(4a)`` (the renderer's law, imaging.vignetting_gain) by least squares on the
  logarithms: the relative illumination at the image's farthest corner, and W0 the white level;
* **blur**: the edge spread across the middle of every edge between two inner corners, sampled
  along the edge's normal in the image and fitted with an error function: its width sigma (px);
* **JPEG quality**: the file's luminance quantisation table against the IJG tables of qualities
  1-100 (the tables libjpeg, and OpenCV through it, write).

These are measurements of the images, not yet the settings that reproduce them: a rendered edge
has a width of its own (the pixel's area) and JPEG smooths noise, so ``stereo-bench twin``
renders the twin, measures it the same way and corrects the settings by the difference.
Motion blur and the board's warp are not measured here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.special import erf

from ..core.camera import Camera
from ..core.patterns import Checkerboard
from ..core.poses import rodrigues_to_matrix

_INNER = 0.5          # share of a square's side sampled for its level and noise (its middle)
_MIN_PIXELS = 16      # pixels a square's patch needs to count
_PROFILE_PX = 4.0     # half-length of an edge profile, px
_PROFILE_STEP = 0.25  # its sampling step, px

# libjpeg's standard luminance quantisation table (ITU-T T.81 Annex K, Table K.1), natural order.
_IJG_LUMINANCE = np.array([
    16, 11, 10, 16, 24, 40, 51, 61, 12, 12, 14, 19, 26, 58, 60, 55,
    14, 13, 16, 24, 40, 57, 69, 56, 14, 17, 22, 29, 51, 87, 80, 62,
    18, 22, 37, 56, 68, 109, 103, 77, 24, 35, 55, 64, 81, 104, 113, 92,
    49, 64, 78, 87, 103, 121, 120, 101, 72, 92, 95, 98, 112, 100, 103, 99], dtype=np.float64)


def ijg_table(quality: int) -> np.ndarray:
    """The luminance table libjpeg writes at ``quality`` (1-100), natural order."""
    scale = 5000 / quality if quality < 50 else 200 - 2 * quality
    return np.clip(np.floor((_IJG_LUMINANCE * scale + 50) / 100), 1, 255)


def jpeg_quality(path) -> int | None:
    """The IJG quality whose luminance table the JPEG file at ``path`` carries (the nearest one,
    by the sum of absolute differences), None for a file that is not a JPEG."""
    from PIL import Image

    with Image.open(path) as im:
        tables = getattr(im, "quantization", None) if im.format == "JPEG" else None
    if not tables:
        return None
    # Pillow gives the table in natural (row-major) order.
    table = np.asarray(tables[min(tables)], dtype=np.float64)
    errors = [np.abs(ijg_table(q) - table).sum() for q in range(1, 101)]
    return int(np.argmin(errors)) + 1


def squares(board: Checkerboard) -> tuple[np.ndarray, np.ndarray]:
    """(centres (M, 2) mm in the board frame, black (M,) bool) of a checkerboard's squares."""
    s = board.square_mm
    i, j = np.meshgrid(np.arange(board.squares_x), np.arange(board.squares_y))
    centres = np.column_stack([(i.ravel() - 0.5) * s, (j.ravel() - 0.5) * s])
    ppm = 4.0 / s  # four texels per square: the centre texel is the square's colour
    texture = board.texture(ppm)
    ij = np.floor((centres - board.texture_origin_mm) * ppm).astype(int)
    return centres, texture[ij[:, 1], ij[:, 0]] < 128


def _project(camera: Camera, rvec, tvec, points_mm: np.ndarray) -> np.ndarray:
    P = np.column_stack([points_mm, np.zeros(len(points_mm))])
    return camera.project_cam(P @ rodrigues_to_matrix(np.asarray(rvec)).T + np.asarray(tvec))


@dataclass
class ViewSamples:
    """What one view of the board gives: per square patch its mean, its variance about a plane,
    its image position and colour; per edge its fitted width."""

    means: np.ndarray
    variances: np.ndarray
    positions: np.ndarray
    black: np.ndarray
    edge_sigmas: np.ndarray
    background: np.ndarray            # (K, 3): u, v, grey level of pixels off the board
    depth_mm: float                   # the board's centre along the optical axis


def view_samples(image: np.ndarray, camera: Camera, rvec, tvec, board: Checkerboard
                 ) -> ViewSamples:
    """Measure one grey image (H, W) of ``board`` seen at cam_from_board (rvec, tvec)."""
    img = image.astype(np.float64)
    H, W = img.shape
    centres, black = squares(board)
    half = 0.5 * _INNER * board.square_mm
    corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=np.float64) * half
    means, variances, positions, colours = [], [], [], []
    for centre, is_black in zip(centres, black):
        quad = _project(camera, rvec, tvec, centre + corners)
        if not np.all(np.isfinite(quad)) or quad.min() < 1 or (quad[:, 0] > W - 2).any() \
                or (quad[:, 1] > H - 2).any():
            continue
        x0, y0 = np.floor(quad.min(0)).astype(int)
        x1, y1 = np.ceil(quad.max(0)).astype(int) + 1
        mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
        cv2.fillConvexPoly(mask, np.round(quad - [x0, y0]).astype(np.int32), 1)
        mask = cv2.erode(mask, np.ones((3, 3), np.uint8))  # off the blurred edges
        v, u = np.nonzero(mask)
        if len(u) < _MIN_PIXELS:
            continue
        values = img[v + y0, u + x0]
        A = np.column_stack([np.ones(len(u)), u, v]).astype(np.float64)
        coef, *_ = np.linalg.lstsq(A, values, rcond=None)
        resid = values - A @ coef
        means.append(values.mean())
        variances.append(resid @ resid / (len(u) - 3))
        positions.append([u.mean() + x0, v.mean() + y0])
        colours.append(is_black)
    return ViewSamples(np.array(means), np.array(variances), np.array(positions).reshape(-1, 2),
                       np.array(colours, bool), _edge_sigmas(img, camera, rvec, tvec, board),
                       _off_board(img, camera, rvec, tvec, board),
                       float((rodrigues_to_matrix(np.asarray(rvec))
                              @ np.r_[board.object_points().mean(0)[:2], 0.0]
                              + np.asarray(tvec))[2]))


def _off_board(img: np.ndarray, camera: Camera, rvec, tvec, board: Checkerboard,
               count: int = 4000) -> np.ndarray:
    """(K, 3) u, v, grey level of pixels on a regular lattice that lie well off the board's
    outline (the background; a twentieth of the board's size beyond it)."""
    outline = board.outline_mm()
    centre = outline.mean(0)
    grown = _project(camera, rvec, tvec, centre + 1.1 * (outline - centre))
    H, W = img.shape
    step = max(1, int(math.sqrt(H * W / count)))
    v, u = np.mgrid[step // 2:H:step, step // 2:W:step]
    mask = np.zeros((H, W), np.uint8)
    if np.all(np.isfinite(grown)):
        cv2.fillPoly(mask, [np.round(grown).astype(np.int32)], 1)
    off = mask[v, u] == 0
    return np.column_stack([u[off], v[off], img[v[off], u[off]]]).astype(np.float64)


def _edge_sigmas(img: np.ndarray, camera: Camera, rvec, tvec, board: Checkerboard) -> np.ndarray:
    """The fitted edge-spread width (px) at the middle of every edge between two inner corners
    (NaN where the fit fails)."""
    obj = board.object_points()[:, :2]
    cols, rows = board.pattern_size
    grid = obj.reshape(rows, cols, 2)
    # Edge midpoints and, in the board's plane, a step across each edge.
    mids = [(0.5 * (grid[:, 1:] + grid[:, :-1])).reshape(-1, 2),
            (0.5 * (grid[1:] + grid[:-1])).reshape(-1, 2)]
    across = [np.array([0.0, 1.0]), np.array([1.0, 0.0])]
    t = np.arange(-_PROFILE_PX, _PROFILE_PX + 1e-9, _PROFILE_STEP)
    sigmas = []
    for mid, step in zip(mids, across):
        a = _project(camera, rvec, tvec, mid)
        b = _project(camera, rvec, tvec, mid + 0.05 * board.square_mm * step)
        normal = b - a
        length = np.linalg.norm(normal, axis=1, keepdims=True)
        ok = np.all(np.isfinite(a), axis=1) & (length[:, 0] > 0)
        normal = normal / np.where(length > 0, length, 1.0)
        for p, n in zip(a[ok], normal[ok]):
            pts = (p + t[:, None] * n).astype(np.float32)
            if pts.min() < 0 or (pts[:, 0] > img.shape[1] - 1).any() \
                    or (pts[:, 1] > img.shape[0] - 1).any():
                continue
            profile = cv2.remap(img.astype(np.float32), pts[:, None, 0], pts[:, None, 1],
                                cv2.INTER_LINEAR)[:, 0]
            sigmas.append(_fit_edge(t, profile.astype(np.float64)))
    return np.array(sigmas)


def _fit_edge(t: np.ndarray, profile: np.ndarray) -> float:
    """The width sigma (px) of an error-function edge fitted to ``profile`` over offsets t."""
    lo, hi = profile[:4].mean(), profile[-4:].mean()
    if abs(hi - lo) < 10:  # no contrast to measure
        return np.nan

    def residual(x):
        level, height, centre, log_sigma = x
        return level + height * erf((t - centre) / (np.sqrt(2) * np.exp(log_sigma))) - profile

    fit = least_squares(residual, [0.5 * (lo + hi), 0.5 * (hi - lo), 0.0, np.log(0.7)],
                        bounds=([-np.inf, -np.inf, -1.5, np.log(0.05)],
                                [np.inf, np.inf, 1.5, np.log(3.0)]))
    return float(np.exp(fit.x[3])) if fit.success else np.nan


@dataclass
class ImagingFit:
    """One camera's imaging as measured on its board (module notes); grey levels in 0..255."""

    black_level: float
    white_level: float
    background: float
    gain_dn_per_e: float | None     # None: no shot noise measurable
    read_noise_dn: float
    corner_illumination: float
    edge_sigma_px: float
    jpeg_quality: int | None
    defocus: dict | None            # the edge width against depth (fit_defocus), or None
    patches: int
    edges: int

    def as_dict(self) -> dict:
        return dict(vars(self))


def _cos2(camera: Camera, uv: np.ndarray) -> np.ndarray:
    """cos^2 of the angle between each pixel's ray and the optical axis, at most 85 degrees
    (a wide lens sees further; the renderer's cos^4a law has no light left there); NaN
    without a ray."""
    rays, valid = camera.rays(uv)
    cos = np.maximum(rays[..., 2], math.cos(math.radians(85.0)))
    return np.where(valid, cos * cos, np.nan)


def fit_imaging(samples: list[ViewSamples], camera: Camera, quality: int | None
                ) -> ImagingFit:
    """The camera's imaging from its views' samples (module notes). ValueError when no square
    could be measured."""
    means = np.concatenate([s.means for s in samples])
    variances = np.concatenate([s.variances for s in samples])
    black = np.concatenate([s.black for s in samples])
    positions = np.concatenate([s.positions for s in samples])
    if (~black).sum() < 3 or black.sum() < 3:
        raise ValueError(f"camera {camera.name!r}: fewer than 3 black and 3 white squares "
                         f"could be measured on the board")
    # Photon transfer: var = read^2 + gain * mean, robustly (a square crossed by a glare or a
    # shadow edge is an outlier).
    fit = least_squares(lambda x: x[0] + x[1] * means - variances, [1.0, 0.01], loss="soft_l1",
                        f_scale=max(float(np.median(variances)), 1e-3))
    read2, gain = fit.x
    # Vignetting from the white squares, with the renderer's law (imaging.vignetting_gain):
    # level = W0 cos^(4a) of the ray's angle, i.e. log level linear in log cos^2; the corner's
    # relative illumination is that of the image's farthest corner.
    cos2 = _cos2(camera, positions[~black])
    ok = np.isfinite(cos2)
    A = np.column_stack([np.ones(ok.sum()), np.log(cos2[ok])])
    (log_w0, two_a), *_ = np.linalg.lstsq(A, np.log(np.maximum(means[~black][ok], 1e-3)),
                                          rcond=None)
    w, h = camera.width - 1, camera.height - 1
    # A circular fisheye's corners see nothing: its image circle's edge stands in for them.
    corners = camera.within_image_circle(np.array([[0, 0], [w, 0], [0, h], [w, h]], float))
    corner_cos2 = np.nanmin(_cos2(camera, corners))
    corner = float(np.clip(corner_cos2 ** two_a, 0.05, 1.0))
    # The background behind the vignetting.
    bg = np.concatenate([s.background for s in samples])
    gain_bg = _cos2(camera, bg[:, :2]) ** two_a
    use = np.isfinite(gain_bg) & (bg[:, 2] > 0) & (bg[:, 2] < 255)
    background = float(np.median(bg[use, 2] / gain_bg[use])) if use.any() else float("nan")
    sig = np.concatenate([s.edge_sigmas for s in samples])
    sig = sig[np.isfinite(sig)]
    return ImagingFit(
        black_level=float(np.median(means[black])), white_level=float(np.exp(log_w0)),
        background=background,
        gain_dn_per_e=float(gain) if gain > 1e-4 else None,
        read_noise_dn=float(np.sqrt(max(read2, 0.0))),
        corner_illumination=corner,
        edge_sigma_px=float(np.median(sig)) if sig.size else float("nan"),
        jpeg_quality=quality,
        defocus=fit_defocus(np.array([s.depth_mm for s in samples]),
                            np.array([np.nanmedian(s.edge_sigmas) if np.isfinite(
                                s.edge_sigmas).any() else np.nan for s in samples])),
        patches=int(means.size), edges=int(sig.size))


DEFOCUS_MIN_PX = 0.15  # a depth-dependent part of the edge width below this is not reported


def fit_defocus(depth_mm: np.ndarray, sigma_px: np.ndarray) -> dict | None:
    """The thin lens's defocus (imaging.Optics) from each view's edge width against its depth:
    sigma^2 = s0^2 + (c / 4)^2, c = K |1/d_f - 1/d| the blur disc's diameter (px; a disc of
    radius c/2 spreads an edge by c/4), K = fx f / N (px mm). Returns {sigma0_px, k_px_mm,
    focus_mm} when the depth explains at least DEFOCUS_MIN_PX of width over the views' depths,
    else None (the width is then a lens blur alone)."""
    ok = np.isfinite(depth_mm) & np.isfinite(sigma_px) & (depth_mm > 0)
    d, sig = depth_mm[ok], sigma_px[ok]
    if len(d) < 5 or d.max() < 1.2 * d.min():
        return None
    inv = 1.0 / d

    def residual(x):
        s0, log_k, inv_f = x
        c = np.exp(log_k) * np.abs(inv_f - inv)
        return np.sqrt(s0 ** 2 + (c / 4) ** 2) - sig

    best = None
    for inv_f in np.linspace(inv.min(), inv.max(), 5):  # the focus: try starts across the views
        fit = least_squares(residual, [float(np.min(sig)), np.log(10 * d.mean()), inv_f],
                            loss="soft_l1", f_scale=0.05,
                            bounds=([0.0, np.log(1e-3), 0.2 * inv.min()],
                                    [5.0, np.log(1e9), 5 * inv.max()]))
        if best is None or fit.cost < best.cost:
            best = fit
    s0, log_k, inv_f = best.x
    c = np.exp(log_k) * np.abs(inv_f - inv)
    if np.sqrt(s0 ** 2 + (c.max() / 4) ** 2) - np.sqrt(s0 ** 2 + (c.min() / 4) ** 2) \
            < DEFOCUS_MIN_PX:
        return None
    return {"sigma0_px": float(s0), "k_px_mm": float(np.exp(log_k)),
            "focus_mm": float(1.0 / inv_f)}
