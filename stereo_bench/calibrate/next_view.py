"""Which board view to shoot next: where a camera's projection is least certain, and the board
pose that would most reduce that uncertainty there.

The idea is the next-best-pose search of Peng & Sturm ("Calibration Wizard: a guidance system
for camera calibration based on modelling geometric and corner uncertainty", ICCV 2019): a
candidate view is judged by the uncertainty the calibration would have with it, predicted from
the estimate, before any image is taken. Here the uncertainty is mrcal's mean-frames projection
uncertainty (uncertainty.py), the same map the capture report shows.

* **Where.** The image is cut in ninths (3 x 3), each sampled on a 3 x 3 grid from its outer
  corner to its inner one. A ninth's σ is the largest worst-direction 1σ of the projection, at
  the calibration's median board distance, among its samples (usually at its outer corner). A
  ninth is a target when no feature reached it, or when its σ is over TARGET_FACTOR times the
  most certain ninth's; the least certain is taken first.
* **Which view.** For a target, candidate board poses: the board's centre on the estimate's ray
  through the ninth's least certain pixel, at 1, 1.5 or 2.2 times the median board distance,
  facing the camera or turned by TILT_DEG about its horizontal or its vertical axis, either way
  (15 candidates). A board that does not fit whole in the image (a checkerboard is found only
  whole) is slid towards the image's centre. Each candidate's projected points join the views
  as one more (its corners as noisy as the fit's residuals), the σ at that pixel is predicted
  again, and the candidate that lowers it most is the suggestion.
* **In order.** The chosen view is then counted as taken and the next target sought, so the
  MAX_TARGETS suggestions are a sequence to shoot, not three answers to one question.

The prediction is for detection noise only, like the map: a view also guards against model
error (a lens model too simple shows most where nothing was seen), which no prediction holds.
"""

from __future__ import annotations

import numpy as np

from .base import Observations
from ..core.camera import Camera
from ..core.poses import matrix_to_rodrigues, rodrigues_to_matrix
from .uncertainty import median_board_distance, residual_sigma, worst_sigma

#: A ninth whose σ is over this many times the most certain ninth's is a target.
TARGET_FACTOR = 2.0
MAX_TARGETS = 3
TILT_DEG = 35.0
REGIONS = (("top-left", "top", "top-right"), ("left", "centre", "right"),
            ("bottom-left", "bottom", "bottom-right"))
#: Board points must lie this far inside the image (px) for the board to count as found.
_MARGIN_PX = 4.0


def empty_ninths(counts) -> np.ndarray:
    """(9,) bool, row by row: the ninths of the image (the coverage grid's feature counts, rows x
    columns, split 3 x 3) where no feature was detected in any view."""
    c = np.asarray(counts)
    rows = np.array_split(np.arange(c.shape[0]), 3)
    cols = np.array_split(np.arange(c.shape[1]), 3)
    return np.array([c[np.ix_(r, k)].sum() == 0 for r in rows for k in cols])


def ninth_samples(width: int, height: int) -> np.ndarray:
    """(9, 9, 2) px: per ninth of the image (row by row), a 3 x 3 grid of pixels from its
    outer corner to its inner one (OpenCV pixel centres), so that a ninth's least certain pixel,
    usually its outermost, is among them."""
    out = np.empty((9, 9, 2))
    for i in range(9):
        r, c = divmod(i, 3)
        u = np.linspace(c * (width - 1) / 3, (c + 1) * (width - 1) / 3, 3)
        v = np.linspace(r * (height - 1) / 3, (r + 1) * (height - 1) / 3, 3)
        out[i] = np.stack(np.meshgrid(u, v), -1).reshape(-1, 2)
    return out


def _facing(ray: np.ndarray) -> np.ndarray:
    """cam_from_board rotation of a board whose normal (+z, away from the camera) lies along
    ``ray``, its x axis along the image's rows as far as it can."""
    z = ray / np.linalg.norm(ray)
    x = np.array([1.0, 0.0, 0.0]) - z[0] * z
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


def _axis_rotation(axis: int, angle: float) -> np.ndarray:
    v = np.zeros(3)
    v[axis] = angle
    return rodrigues_to_matrix(v)


def _inside(camera: Camera, uv: np.ndarray, depth: np.ndarray) -> bool:
    return bool((depth > 0).all() and (uv >= _MARGIN_PX).all()
                and (uv[:, 0] <= camera.width - 1 - _MARGIN_PX).all()
                and (uv[:, 1] <= camera.height - 1 - _MARGIN_PX).all())


def placed(camera: Camera, board: np.ndarray, pixel: np.ndarray, distance_mm: float,
           R_tilt: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """A board pose (rvec, tvec) at ``distance_mm`` with its centre on the ray through
    ``pixel``, slid towards the image's centre until the whole board is in the image, and its
    projected points (K, 2); None when it does not fit even at the centre."""
    centre = np.array([(camera.width - 1) / 2, (camera.height - 1) / 2])
    middle = board.mean(axis=0)
    for slide in np.linspace(1.0, 0.0, 21):
        target = centre + slide * (pixel - centre)
        xy = camera.unproject(target[None])[0]
        ray = np.array([xy[0], xy[1], 1.0])
        R = _facing(ray) @ R_tilt
        t = ray / np.linalg.norm(ray) * distance_mm - R @ middle
        p_cam = board @ R.T + t
        uv = camera.project_cam(p_cam)
        if _inside(camera, uv, p_cam[:, 2]):
            return matrix_to_rodrigues(R), t, uv
    return None


def _turn_words(camera: Camera, board: np.ndarray, rvec, tvec, axis: int | None) -> str:
    """How the board is turned, in words a person holding it understands."""
    if axis is None:
        return "facing the camera"
    p = board @ rodrigues_to_matrix(rvec).T + tvec
    uv = camera.project_cam(p)
    i = 0 if axis == 1 else 1  # about the vertical axis: left/right edges; else top/bottom
    low, high = uv[:, i] < np.median(uv[:, i]), uv[:, i] >= np.median(uv[:, i])
    near_low = p[low, 2].mean() < p[high, 2].mean()
    edge = ("left" if near_low else "right") if axis == 1 else ("top" if near_low else "bottom")
    about = "its vertical axis" if axis == 1 else "its horizontal axis"
    return f"turned {TILT_DEG:.0f} degrees about {about}, {edge} edge nearer"


def _worst_per_ninth(camera, obs, rvecs, tvecs, parameters, samples, distance):
    """(9,) the largest σ among each ninth's samples (NaN where the estimate has no unique ray
    at any) and (9, 2) the pixel it is at."""
    flat = samples.reshape(-1, 2)
    valid = camera.invertible(flat)
    sigma = np.full(len(flat), np.nan)
    sigma[valid] = worst_sigma(camera, obs, rvecs, tvecs, parameters, flat[valid], distance)
    sigma = sigma.reshape(9, 9)
    where = np.array([s[np.nanargmax(g)] if np.isfinite(g).any() else s[4]
                      for s, g in zip(samples, sigma)])
    return np.nanmax(np.where(np.isfinite(sigma), sigma, -np.inf), axis=1), where


def suggest(camera: Camera, obs: Observations, rvecs, tvecs, parameters, board: np.ndarray,
            counts=None) -> list[dict]:
    """The views to add (module notes), in the order to shoot them: each is chosen with the
    ones before it already added. Each a dict (JSON-ready) with ``region``, ``pixel`` (the
    ninth's least certain pixel), ``empty`` (no feature reached the ninth), ``sigma_px`` (there,
    before the view), ``sigma_after_px`` (with it), ``sigma_best_px`` (the most certain ninth's,
    now), ``distance_mm``, ``turn`` (words), ``rvec``/``tvec`` (cam_from_board) and
    ``outline_px`` (the board's convex hull in the image). ``board`` (K, 3): the pattern's
    points; ``counts``: the coverage grid's feature counts (rows x columns)."""
    import cv2

    rvecs, tvecs = np.asarray(rvecs, float), np.asarray(tvecs, float)
    distance = median_board_distance(obs, rvecs, tvecs)
    samples = ninth_samples(camera.width, camera.height)
    empty = np.zeros(9, bool) if counts is None else empty_ninths(counts)
    fit_sigma = residual_sigma(camera, obs, rvecs, tvecs, parameters)
    out, done = [], set()
    for _ in range(MAX_TARGETS):
        sigma, where = _worst_per_ninth(camera, obs, rvecs, tvecs, parameters, samples,
                                        distance)
        finite = sigma[np.isfinite(sigma) & (sigma > -np.inf)]
        if finite.size == 0:
            break
        best = float(finite.min())
        wanted = [i for i in np.argsort(-sigma) if i not in done and np.isfinite(sigma[i])
                  and (empty[i] or sigma[i] > TARGET_FACTOR * best)]
        if not wanted:
            break
        i = int(wanted[0])
        done.add(i)
        choices = []
        for scale in (1.0, 1.5, 2.2):
            for axis, sign in ((None, 0), (0, 1), (0, -1), (1, 1), (1, -1)):
                R_tilt = (np.eye(3) if axis is None
                          else _axis_rotation(axis, sign * np.radians(TILT_DEG)))
                pose = placed(camera, board, where[i], scale * distance, R_tilt)
                if pose is None:
                    continue
                rvec, tvec, uv = pose
                more = Observations(list(obs.object_points) + [board],
                                    list(obs.image_points) + [uv], obs.image_size,
                                    list(obs.view_ids) + [-1], obs.camera_name)
                rv, tv = np.vstack([rvecs, rvec]), np.vstack([tvecs, tvec])
                after = worst_sigma(camera, more, rv, tv, parameters, where[i:i + 1], distance,
                                    sigma_px=fit_sigma)[0]
                choices.append((after, axis, rvec, tvec, uv, more, rv, tv))
        if not choices:
            continue
        after, axis, rvec, tvec, uv, obs, rvecs, tvecs = min(choices, key=lambda c: c[0])
        hull = cv2.convexHull(uv.astype(np.float32))[:, 0]
        out.append({"region": REGIONS[i // 3][i % 3], "pixel": where[i].tolist(),
                    "empty": bool(empty[i]), "sigma_px": float(sigma[i]),
                    "sigma_after_px": float(after), "sigma_best_px": best,
                    "distance_mm": float(np.linalg.norm(tvec + rodrigues_to_matrix(rvec)
                                                        @ board.mean(axis=0))),
                    "turn": _turn_words(camera, board, rvec, tvec, axis),
                    "rvec": rvec.tolist(), "tvec": tvec.tolist(),
                    "outline_px": hull.astype(float).tolist()})
    return out


def in_words(camera_name: str, s: dict, order: int) -> str:
    """The ``order``-th suggestion (from 1) as a recapture line."""
    why = ("no board feature reached" if s["empty"]
           else "the projection is among the least certain")
    when = "" if order == 1 else f"then (with view {order - 1} taken) "
    return (f"camera {camera_name}, view {order}: {when}the {s['region']} of the image, where "
            f"{why} (1σ "
            f"{s['sigma_px']:.3g} px; {s['sigma_best_px']:.3g} px where it is most certain): one "
            f"view with the board there at {s['distance_mm']:.0f} mm, {s['turn']}, would bring "
            f"it to {s['sigma_after_px']:.3g} px (the board's outline is drawn on "
            f"plots/capture_{camera_name}.png)")
