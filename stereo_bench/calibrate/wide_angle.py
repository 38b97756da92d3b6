"""The start of a fisheye or omnidirectional calibration, where Zhang's closed form does not hold.

A plane seen through a wide lens is no homography of the image, so the pinhole closed form has
nothing to fit. The papers of the models start from the lens's base projection with a nominal
focal length and the principal point at the image centre: Kannala & Brandt 2006 (section 4.1)
from the equidistant projection r = f theta (k1..k4 = 0); Mei & Rives 2007 (section 4) from the
unit sphere with xi = 1 and no distortion, estimating the one generalized focal length gamma;
Usenko et al. 2018 from xi = 0, alpha = 0.5 (the same sphere model: alpha / (1 - alpha) = 1).
Where the papers take f from the lens's nominal field of view or from a line image marked by
hand, here it is the value whose base camera best explains every view as a plane: for each f
on a log grid over 1/40 to 2 image diagonals (4.5 % steps), every detected point is unprojected
to its ray, each view's board-to-ray homography is fitted (homography.py, in normalized
coordinates), and the pixel residual of the plane's points projected back is summed. The f of
least residual gives the poses (Zhang's section 3.1 with K = I) and the start of refine.py.
"""

from __future__ import annotations

import numpy as np

from ..core.camera import Camera
from .base import Observations
from .homography import apply_homography, fit_homographies
from .homography import extrinsics_from_homography

BASE_LENS = {"kannala_brandt": (0.0, 0.0, 0.0, 0.0), "mei": (1.0, 0.0, 0.0, 0.0, 0.0),
             "double_sphere": (0.0, 0.5)}
_FOCAL_STEPS = 81
_MIN_DEPTH = 0.05  # rays within 87 degrees of the axis serve a homography in normalized units


def _plane_fit(camera: Camera, obs: Observations, refine: bool):
    """(residual sum of squares in px^2, board-to-normalized homographies (V, 3, 3)) of the
    views under ``camera``; inf when a view has fewer than 4 points with a ray ahead."""
    src, dst = [], []
    for o, p in zip(obs.object_points, obs.image_points):
        rays, valid = camera.rays(p)
        ahead = valid & (rays[:, 2] > _MIN_DEPTH)
        if ahead.sum() < 4:
            return np.inf, None
        src.append(o[ahead, :2])
        dst.append(rays[ahead, :2] / rays[ahead, 2:])
    Hs = fit_homographies(src, dst, refine=refine)
    cost = 0.0
    for H, s, p, o in zip(Hs, src, obs.image_points, obs.object_points):
        uv = camera.normalized_to_pixels(apply_homography(H, o[:, :2]))
        cost += float(np.sum((uv - p) ** 2))
    return cost, Hs


def wide_angle_start(obs: Observations, lens: str) -> tuple[Camera, np.ndarray, np.ndarray, dict]:
    """(start camera, rvecs (V, 3), tvecs (V, 3), log) for ``lens`` (a core lens model other
    than OpenCV's) from the views of ``obs`` (module docstring)."""
    w, h = obs.image_size
    diagonal = float(np.hypot(w, h))

    def camera(f):
        return Camera(obs.camera_name, w, h, f, f, (w - 1) / 2, (h - 1) / 2, 0.0,
                      np.array(BASE_LENS[lens]), model=lens)

    focals = np.geomspace(diagonal / 40, 2 * diagonal, _FOCAL_STEPS)
    with np.errstate(divide="ignore", invalid="ignore"):  # a degenerate fit costs NaN: inf
        costs = np.nan_to_num([_plane_fit(camera(f), obs, refine=False)[0] for f in focals],
                              nan=np.inf)
    best = int(np.argmin(costs))
    if not np.isfinite(costs[best]):
        raise ValueError(f"observations of {obs.camera_name!r}: no focal length of the {lens} "
                         f"lens sees every view's points ahead of the camera; no start")
    start = camera(float(focals[best]))
    _, Hs = _plane_fit(start, obs, refine=True)
    rvecs, tvecs = extrinsics_from_homography(np.eye(3), Hs)
    log = {"lens": lens, "focal_px": float(focals[best]), "base": list(BASE_LENS[lens]),
           "plane_rms_px": float(np.sqrt(costs[best] / obs.n_points))}
    return start, rvecs, tvecs, log
