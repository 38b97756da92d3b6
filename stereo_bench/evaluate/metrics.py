"""Accuracy of a calibration against exact ground truth.

* ``rpe_rms``: the paper's RPE_RMS (SynthCal, section 4.2), sqrt(mean over points of the squared
  residual norm), in px. It measures the fit to the detections, not the camera: at 0.5 px noise
  it sits near 0.7 px for every estimate (TRAPS.md).
* ``parameter_rmse``: the paper's RMSE over [fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6]. It
  mixes units (px with unitless coefficients, so the focal lengths and principal point dominate)
  and is meaningless when the coefficients are not identifiable (rational model); it is kept only
  to compare with the paper's tables. ``parameter_errors`` gives each error on its own.
* ``projection_difference``: how far the estimated camera projects the true camera's rays, over a
  grid covering the image (px) -- the error a user of the estimate sees. Reported as is, and after
  the best-fit rotation between the two camera frames (as mrcal's projection_diff does), which
  removes what a change of extrinsics would absorb.
* ``validity``: where an estimate has one ray per pixel (a fit can fold inside the image).
* ``pose_errors``: board pose errors per view, rotation (deg) and translation (mm).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from ..core.camera import (DIST_NAMES, INTRINSIC_NAMES, Camera, project_points,
                           project_with_jacobians)
from ..core.poses import geodesic_distance, rodrigues_to_matrix

PAPER_PARAMS = ("fx", "fy", "cx", "cy") + DIST_NAMES


def rpe_rms(camera: Camera, rvecs, tvecs, object_points, image_points) -> float:
    """RPE_RMS (px) of board views: per view (N_i, 3) board points and (N_i, 2) detections, with
    cam_from_board poses rvecs, tvecs (V, 3) and the camera's intrinsics and distortion."""
    squared = [np.sum((project_points(o, camera.intrinsics, camera.dist, r, t, camera.model) - p) ** 2, axis=1)
               for o, p, r, t in zip(object_points, image_points, rvecs, tvecs)]
    return float(np.sqrt(np.mean(np.concatenate(squared))))


def _params(camera: Camera) -> dict:
    return dict(zip(INTRINSIC_NAMES + camera.dist_names, np.append(camera.intrinsics,
                                                                   camera.dist)))


def _paraxial(camera: Camera) -> dict:
    """fx..skew with fx, fy (and skew) as the focal lengths on the axis: a Mei or double-sphere
    lens images a ray near its axis at fx / (1 + xi) px per radian (its fx is not the focal
    length); OpenCV's pinhole and the Kannala-Brandt lens at fx."""
    p = {k: v for k, v in _params(camera).items() if k in INTRINSIC_NAMES}
    if camera.model in ("mei", "double_sphere"):
        scale = 1.0 / (1.0 + camera.dist[0])
        p.update(fx=p["fx"] * scale, fy=p["fy"] * scale, skew=p["skew"] * scale)
    return p


def parameter_errors(estimate: Camera, truth: Camera) -> dict:
    """estimate - truth for fx, fy, cx, cy, skew (px) and the lens's parameters (unitless);
    between lens models (core/lens.py) only fx..skew, with fx, fy and skew as the focal lengths
    on the axis (:func:`_paraxial`), since the other parameters of two models are not the same
    quantities (projection_difference compares the lenses)."""
    if estimate.model == truth.model:
        est, true = _params(estimate), _params(truth)
    else:
        est, true = _paraxial(estimate), _paraxial(truth)
    return {k: float(est[k] - true[k]) for k in est}


def parameter_rmse(estimate: Camera, truth: Camera) -> float:
    """The paper's RMSE over PAPER_PARAMS (mixed units; see the module docstring); over the
    parameters both lenses have where they are of different models."""
    err = parameter_errors(estimate, truth)
    return float(np.sqrt(np.mean([err[k] ** 2 for k in PAPER_PARAMS if k in err])))


def grid_pixels(camera: Camera, n: tuple[int, int]) -> np.ndarray:
    """(nu * nv, 2) pixels from corner to corner of the image (OpenCV pixel centres)."""
    u = np.linspace(0.0, camera.width - 1, n[0])
    v = np.linspace(0.0, camera.height - 1, n[1])
    return np.stack(np.meshgrid(u, v), -1).reshape(-1, 2)


def projection_difference_map(estimate: Camera, truth: Camera,
                              grid: tuple[int, int] = (160, 120)) -> np.ndarray:
    """(rows, columns) px: per grid pixel, how far the estimate projects the true camera's ray
    (intrinsics only, no rotation compensation); the map behind ``projection_difference``, NaN
    where the estimate is not valid."""
    uv = grid_pixels(truth, grid)
    rays, valid = _true_rays(estimate, truth, uv)
    diff = np.full(len(uv), np.nan)  # NaN where the estimate is invalid (see below)
    diff[valid] = np.linalg.norm(estimate.project_cam(rays[valid]) - uv[valid], axis=1)
    return diff.reshape(grid[1], grid[0])


def _true_rays(estimate: Camera, truth: Camera, uv: np.ndarray):
    """(the true camera's rays of pixels uv (N, 3), valid (N,)): valid where the true camera
    has a ray, the estimate projects it one to one (inside its radial fold, or its wide lens's
    field) and the pixel has one ray through the estimate: where comparing the two projections
    means something. A pinhole truth's rays are (x, y, 1); a wide lens's unit rays, beyond 90
    degrees where it sees there."""
    if truth.model == "opencv":
        xy = truth.unproject(uv)
        valid = ((np.linalg.norm(xy, axis=-1) < estimate.max_normalized_radius)
                 & estimate.invertible(uv))
        return np.column_stack([xy, np.ones(len(uv))]), valid
    rays, valid = truth.rays(uv)
    rays = np.where(valid[:, None], rays, [0.0, 0.0, 1.0])
    return rays, valid & estimate.sees(rays) & estimate.invertible(uv)


def validity(estimate: Camera, truth: Camera | None = None, grid: tuple[int, int] = (64, 48)
             ) -> dict:
    """Where an estimate can be used over its image: the fraction of a grid of pixels (corner to
    corner) that have exactly one ray through it, and the normalized radius where its radial
    distortion folds or has a pole (None when it has neither within 87 degrees). A fitted
    high-order model can fold inside the image (TRAPS.md); triangulation and projection through
    it are meaningless there. Given the ``truth``, only the pixels where the true lens sees
    count: a circular fisheye's black surround is not a fault of its estimate."""
    uv = grid_pixels(estimate, grid)
    if truth is not None and truth.model != "opencv":  # a true pinhole sees every pixel
        uv = uv[truth.has_ray(uv)]
    ok = estimate.invertible(uv)
    fold = estimate.max_normalized_radius
    return {"valid_fraction": float(ok.mean()), "fold_radius": fold if np.isfinite(fold) else None,
            "usable": bool(ok.all())}


def projection_difference(estimate: Camera, truth: Camera, grid: tuple[int, int] = (64, 48),
                          rotation=None) -> dict:
    """Mean and max pixel distance between the two cameras' projections of the same rays.

    Each pixel of a ``grid`` (columns, rows) spanning the image corner to corner is unprojected
    with the TRUE camera (exact Newton inversion) and projected with the estimate's intrinsics and
    distortion. Only intrinsics are compared (cam_from_world is ignored: a single-camera
    calibration has its own frame); ``rotation``, a Rodrigues vector estimate_cam_from_true_cam
    (e.g. from a rig calibration), rotates the rays in between.

    The statistics cover only the pixels where the estimate is valid: the true ray lies inside
    the estimate's radial fold, and the pixel has one ray through the estimate. Beyond its fold
    (or pole) an estimate's projection is not a small error but a different branch of its
    polynomial (thousands of px near a pole), so including those pixels made the mean depend on
    how close the grid came to the pole. ``points_left_out`` / ``fraction_left_out`` say how much
    of the grid was excluded; with all of it excluded the statistics are None.

    ``mean_px`` / ``max_px``: the frames as given.
    ``rotation_compensated_mean_px`` / ``..._max_px``: after the extra rotation (``rotation_deg``)
    of the rays that minimizes the squared pixel differences -- what remains when a rotation of
    the camera frame, which extrinsics would absorb, is explained away (as mrcal's projection_diff).
    """
    uv = grid_pixels(truth, grid)
    rays, valid = _true_rays(estimate, truth, uv)
    left_out = {"points_left_out": int((~valid).sum()),
                "fraction_left_out": float((~valid).mean())}
    if not valid.any():
        return {"mean_px": None, "max_px": None, "rotation_compensated_mean_px": None,
                "rotation_compensated_max_px": None, "rotation_deg": None, **left_out}
    uv, rays = uv[valid], rays[valid]
    if rotation is not None:
        rays = rays @ rodrigues_to_matrix(rotation).T
    zero = np.zeros(3)

    def residuals(rvec):
        return (project_points(rays, estimate.intrinsics, estimate.dist, rvec, zero,
                               estimate.model) - uv).ravel()

    def jacobian(rvec):
        J = project_with_jacobians(rays, estimate.intrinsics, estimate.dist, rvec, zero,
                                   model=estimate.model)[1]
        return J["pose"][:, :, :3].reshape(-1, 3)

    direct = np.linalg.norm(residuals(zero).reshape(-1, 2), axis=1)
    fit = least_squares(residuals, zero, jac=jacobian, method="lm", xtol=1e-15, ftol=1e-15)
    rotated = np.linalg.norm(fit.fun.reshape(-1, 2), axis=1)
    return {
        "mean_px": float(direct.mean()),
        "max_px": float(direct.max()),
        "rotation_compensated_mean_px": float(rotated.mean()),
        "rotation_compensated_max_px": float(rotated.max()),
        "rotation_deg": float(np.degrees(np.linalg.norm(fit.x))),
        **left_out,
    }


def pose_errors(rvecs, tvecs, true_rvecs, true_tvecs) -> dict:
    """Per-view errors of estimated cam_from_board poses against the true ones (all (V, 3)).

    rotation_deg: angle of R_est R_true^T; translation_mm: |t_est - t_true|; plus mean and max.
    """
    R = rodrigues_to_matrix(np.asarray(rvecs, dtype=np.float64))
    R_true = rodrigues_to_matrix(np.asarray(true_rvecs, dtype=np.float64))
    rot = np.degrees(geodesic_distance(R_true, R))
    trans = np.linalg.norm(np.asarray(tvecs, float) - np.asarray(true_tvecs, float), axis=-1)
    return {
        "rotation_deg": rot.tolist(),
        "translation_mm": trans.tolist(),
        "rotation_deg_mean": float(rot.mean()),
        "rotation_deg_max": float(rot.max()),
        "translation_mm_mean": float(trans.mean()),
        "translation_mm_max": float(trans.max()),
    }
