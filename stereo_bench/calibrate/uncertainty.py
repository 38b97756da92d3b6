"""What the noise of the detections leaves uncertain in a single-camera calibration.

Without ground truth, the spread of a calibration can still be predicted from the calibration
itself, under the assumption that the residuals are independent, isotropic, zero-mean noise of
one standard deviation per pixel coordinate (``diagnostics.py`` tests that assumption).

* ``parameter_covariance``: the Gauss-Newton covariance sigma^2 (J^T J)^-1 of the full problem
  refine.py solves, the estimated intrinsics plus one 6-DOF pose per view, with sigma^2 the
  residuals' sum of squares over their degrees of freedom (2 N - F - 6 V). The intrinsic block
  is the inverse of refine.py's Schur complement (poses marginalized); the pose blocks follow
  from the same factorization.
* ``projection_uncertainty``: mrcal's "mean-frames" projection uncertainty (mrcal documentation,
  "Projection uncertainty" and "Projection uncertainty: mean-frames"). The camera frame of a
  calibration is not a physical thing that could be held fixed while the parameters move; the
  boards are. So a pixel q is unprojected with the estimate to the point p at a working distance,
  p is carried into every view's board frame with the estimated poses, carried back with the
  perturbed poses, the results are averaged over the views, and projected through the perturbed
  intrinsics: q+(b) = project(intrinsics+, mean_i T+_cam_from_board_i T_board_i_from_cam p).
  Its linearization dq+/db propagates the covariance of ALL the parameters, so a shift of the
  camera frame that the poses absorb is not counted as projection uncertainty. The map reports,
  per pixel, the 1-sigma of the worst direction: the square root of the largest eigenvalue of the
  2 x 2 covariance of q+ (mrcal's "worstdirection-stdev").

Both predict the scatter of the estimate under re-noised detections only: model error (a lens
model too simple, a bent board, a biased detector) is not in them.

Parameters are the OpenCV-model names a calibrator declares as ``model_parameters``
(calibrate/base.py); the poses are its CalibrationResult.rvecs / tvecs (cam_from_board).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from .base import Observations
from .refine import CameraModel, free_mask, linearize, rank_info
from ..core.camera import POSE_NAMES, Camera
from ..core.poses import rodrigues_to_matrix, rotate_jacobian
from ..core.files import strict

def check_poses(obs: Observations, rvecs, tvecs) -> tuple[np.ndarray, np.ndarray]:
    """(rvecs, tvecs) as (V, 3) float arrays, or a ValueError naming the one that is not one
    finite cam_from_board pose per view of ``obs``."""
    rv, tv = np.asarray(rvecs, dtype=np.float64), np.asarray(tvecs, dtype=np.float64)
    for name, a in (("rvecs", rv), ("tvecs", tv)):
        if a.shape != (obs.n_views, 3) or not np.all(np.isfinite(a)):
            raise ValueError(f"{name}: expected ({obs.n_views}, 3) finite cam_from_board values "
                             f"(one per view of {obs.camera_name!r}), got shape {a.shape}")
    return rv, tv


def _free(camera: Camera, parameters) -> np.ndarray:
    if parameters is None:
        raise ValueError("parameters: the method's model is not a subset of the camera core's "
                         "(model_parameters is None); its covariance cannot be expressed in it")
    return free_mask(CameraModel(camera.model).param_names, tuple(parameters))


def _linearized(camera: Camera, obs: Observations, rvecs, tvecs, parameters):
    """(linearization of refine.py, free parameter names, sigma^2, degrees of freedom)."""
    rv, tv = check_poses(obs, rvecs, tvecs)
    free = _free(camera, parameters)
    if tuple(camera.size) != tuple(obs.image_size):
        raise ValueError(f"camera {camera.name!r} is {camera.width}x{camera.height} but the "
                         f"observations' image_size is {obs.image_size}")
    model = CameraModel(camera.model)
    lin = linearize(model, model.params_of(camera), free, obs.object_points, obs.image_points,
                    rv, tv)
    r = lin["residuals"]
    dof = r.size - int(free.sum()) - 6 * obs.n_views
    if dof <= 0:
        raise ValueError(f"observations of {obs.camera_name!r}: {r.size} residuals for "
                         f"{int(free.sum())} intrinsics and {6 * obs.n_views} pose parameters; "
                         f"the noise variance needs more residuals than parameters")
    names = [n for n, f in zip(model.param_names, free) if f]
    return lin, names, float(np.sum(r * r)) / dof, dof


def _pose_covariances(lin: dict) -> np.ndarray:
    """(V, 6, 6) diagonal pose blocks of (J^T J)^-1: V^-1 + V^-1 W^T S^-1 W V^-1."""
    V_inv = np.linalg.inv(lin["V"])
    WV = lin["W"] @ V_inv  # (V, F, 6)
    return V_inv + np.einsum("vfi,fg,vgj->vij", WV, lin["S_inv"], WV)


def parameter_covariance(camera: Camera, obs: Observations, rvecs, tvecs,
                         parameters: Sequence[str]) -> dict:
    """Covariance of the estimated intrinsics and standard deviations of the poses (JSON-ready).

    ``parameters``: the names the method estimated (its ``model_parameters``), F of them.
    Returns ``parameters`` (F names, OpenCV-model order), ``values`` and ``std`` (name -> value;
    fx..skew in px, coefficients unitless; a parameter the views cannot identify, see
    refine.rank_info, has std None with ``<name>_reason`` "infinite"), ``covariance`` and
    ``correlation`` (F x F lists; pseudo-inverse in the null space), ``pose_std`` (V x 6 lists over
    rx, ry, rz in rad and tx, ty, tz in mm, cam_from_board), ``view_ids``, ``sigma_px`` (the
    per-coordinate residual standard deviation), ``dof``, ``n_residuals`` and ``rank``.
    """
    lin, names, sigma2, dof = _linearized(camera, obs, rvecs, tvecs, parameters)
    cov = sigma2 * lin["S_inv"]
    std = np.sqrt(np.maximum(np.diag(cov), 0.0))
    rank = rank_info(lin["S"], names)
    std[[n in rank["unidentifiable"] for n in names]] = np.inf
    d = np.where(std > 0, std, 1.0)
    correlation = cov / np.outer(d, d)
    pose_std = np.sqrt(sigma2 * np.diagonal(_pose_covariances(lin), axis1=1, axis2=2))
    model = CameraModel(camera.model)
    values = dict(zip(model.param_names, model.params_of(camera)))
    return strict({
        "parameters": names,
        "values": {n: values[n] for n in names},
        "std": dict(zip(names, std)),
        "covariance": cov,
        "correlation": np.where(np.isfinite(std[:, None] * std[None, :]), correlation, np.nan),
        "pose_names": list(POSE_NAMES),
        "pose_std": pose_std,
        "view_ids": obs.view_ids,
        "sigma_px": float(np.sqrt(sigma2)),
        "dof": dof,
        "n_residuals": int(lin["residuals"].size),
        "rank": rank,
    })


# ----------------------------------------------------------------------------------------------
# Projection uncertainty (mean-frames)
# ----------------------------------------------------------------------------------------------

def median_board_distance(obs: Observations, rvecs, tvecs) -> float:
    """Median over the views of the distance (mm) from the camera centre to the board points'
    centroid: the working distance the calibration data speak for."""
    rv, tv = check_poses(obs, rvecs, tvecs)
    R = rodrigues_to_matrix(rv)
    centroids = np.array([o.mean(0) for o in obs.object_points])
    return float(np.median(np.linalg.norm(np.einsum("vij,vj->vi", R, centroids) + tv, axis=1)))


def _check_distance(distance_mm) -> float:
    d = float(distance_mm)
    if not (np.isfinite(d) and d > 0):
        raise ValueError(f"distance_mm: expected a positive finite distance, got {distance_mm}")
    return d


def _points_at(camera: Camera, uv: np.ndarray, distance_mm: float) -> np.ndarray:
    """Camera-frame points (M, 3) at ``distance_mm`` along the estimate's rays of pixels (M, 2)."""
    distance_mm = _check_distance(distance_mm)
    # Unit rays: a wide lens's past 90 degrees too (behind the camera's plane).
    return camera.unproject_rays(uv) * distance_mm


def reprojected(camera: Camera, rvecs, tvecs, uv, distance_mm: float, perturbed: Camera,
                perturbed_rvecs, perturbed_tvecs) -> np.ndarray:
    """q+ (M, 2): pixels ``uv`` (M, 2) unprojected by ``camera`` to ``distance_mm``, carried into
    each view's board frame with (rvecs, tvecs) (V, 3), back with the perturbed poses, averaged
    over the views and projected through ``perturbed`` (mean-frames; see the module docstring).
    With perturbed = camera and the same poses it returns ``uv``."""
    p = _points_at(camera, np.asarray(uv, dtype=np.float64).reshape(-1, 2), distance_mm)
    R = rodrigues_to_matrix(np.asarray(rvecs, dtype=np.float64))
    Rp = rodrigues_to_matrix(np.asarray(perturbed_rvecs, dtype=np.float64))
    boards = np.einsum("vji,mvj->mvi", R, p[:, None, :] - np.asarray(tvecs)[None])  # (M, V, 3)
    p_new = np.mean(np.einsum("vij,mvj->mvi", Rp, boards) + np.asarray(perturbed_tvecs)[None],
                    axis=1)
    return perturbed.project_cam(p_new)


def reprojection_jacobian(camera: Camera, rvecs, tvecs, uv, distance_mm: float,
                          parameters: Sequence[str]):
    """Linearization of :func:`reprojected` at the estimate: (q (M, 2), dq/d intrinsics
    (M, 2, F) over ``parameters`` in OpenCV-model order, dq/d poses (M, V, 2, 6) over each view's
    [rvec, tvec])."""
    free = _free(camera, parameters)
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    rv, tv = np.asarray(rvecs, dtype=np.float64), np.asarray(tvecs, dtype=np.float64)
    p = _points_at(camera, uv, distance_mm)
    model = CameraModel(camera.model)
    q, J_params, J_point = model.project(model.params_of(camera), p)
    R = rodrigues_to_matrix(rv)
    boards = np.einsum("vji,mvj->vmi", R, p[:, None, :] - tv[None])  # (V, M, 3)
    # p+ = mean_i (R_i+ b_i + t_i+): d p+ / d rvec_i = d(R_i b_i)/d rvec_i / V, d p+/d t_i = I / V
    J_rot = np.stack([rotate_jacobian(r, b) for r, b in zip(rv, boards)], 1)  # (M, V, 3, 3)
    J_p = np.concatenate([J_rot, np.broadcast_to(np.eye(3), J_rot.shape)], -1) / len(rv)
    return q, J_params[:, :, free], np.einsum("mij,mvjk->mvik", J_point, J_p)


def projection_covariance(camera: Camera, obs: Observations, rvecs, tvecs,
                          parameters: Sequence[str], uv, distance_mm: float) -> np.ndarray:
    """(M, 2, 2) px^2: covariance of the mean-frames projection q+ of pixels ``uv`` (M, 2) at
    ``distance_mm``, sigma^2 dq/db (J^T J)^-1 dq/db^T over all intrinsics and poses b."""
    lin, _, sigma2, _ = _linearized(camera, obs, rvecs, tvecs, parameters)
    return _propagate(lin, sigma2, camera, rvecs, tvecs, uv, distance_mm, parameters)


def _propagate(lin, sigma2, camera, rvecs, tvecs, uv, distance_mm, parameters) -> np.ndarray:
    """sigma^2 dq/db (J^T J)^-1 dq/db^T with the blocks of (J^T J)^-1 from refine.py's Schur
    factorization: with h = dq/da - sum_i dq/db_i V_i^-1 W_i^T, it is
    h S^-1 h^T + sum_i dq/db_i V_i^-1 dq/db_i^T (no dense (F + 6 V)^2 inverse)."""
    _, Ja, Jb = reprojection_jacobian(camera, rvecs, tvecs, uv, distance_mm, parameters)
    JbV = np.einsum("mvij,vjk->mvik", Jb, np.linalg.inv(lin["V"]))
    h = Ja - np.einsum("mvik,vfk->mif", JbV, lin["W"])
    return sigma2 * (np.einsum("mif,fg,mjg->mij", h, lin["S_inv"], h)
                     + np.einsum("mvik,mvjk->mij", JbV, Jb))


def _worst_direction(cov: np.ndarray) -> np.ndarray:
    return np.sqrt(np.maximum(np.linalg.eigvalsh(cov)[..., -1], 0.0))


def residual_sigma(camera: Camera, obs: Observations, rvecs, tvecs, parameters) -> float:
    """The per-coordinate residual standard deviation of a fit (px), over its degrees of
    freedom: the noise every propagation here scales with."""
    return float(np.sqrt(_linearized(camera, obs, rvecs, tvecs, parameters)[2]))


def worst_sigma(camera: Camera, obs: Observations, rvecs, tvecs, parameters: Sequence[str], uv,
                distance_mm: float, sigma_px: float | None = None) -> np.ndarray:
    """(M,) px: the worst-direction 1-sigma of the mean-frames projection of pixels ``uv``
    (M, 2) at ``distance_mm``, the detections' noise ``sigma_px`` (default: the fit's own, as
    ``residual_sigma``). With a view that was not fitted among ``obs`` (its projected points as
    observed), it predicts what that view would leave (next_view.py)."""
    lin, _, sigma2, _ = _linearized(camera, obs, rvecs, tvecs, parameters)
    sigma2 = sigma2 if sigma_px is None else float(sigma_px) ** 2
    return _worst_direction(_propagate(lin, sigma2, camera, rvecs, tvecs,
                                       np.asarray(uv, np.float64).reshape(-1, 2), distance_mm,
                                       parameters))


def projection_uncertainty(camera: Camera, obs: Observations, rvecs, tvecs,
                           parameters: Sequence[str], distance_mm: float | None = None,
                           grid: tuple[int, int] = (16, 12)) -> dict:
    """Map of the 1-sigma projection uncertainty over the image (JSON-ready).

    ``grid`` (columns, rows) of pixels from corner to corner of the image (OpenCV centres);
    ``distance_mm`` the range along each ray, default :func:`median_board_distance`.
    Returns ``measure`` (what the numbers are: the worst-direction 1-sigma in px, sqrt of the
    largest eigenvalue of the 2 x 2 covariance of the projected pixel), ``u`` (columns,) and
    ``v`` (rows,) the grid's pixel coordinates, ``map_px`` (rows x columns lists; None where the
    estimate has no unique ray, see Camera.invertible), ``centre_px`` at the image centre
    ((W-1)/2, (H-1)/2), ``worst_px`` and ``worst_at`` ([u, v]) over the grid, ``distance_mm``,
    ``sigma_px`` (the residual standard deviation it scales with) and ``parameters``.
    """
    nu, nv = (int(g) for g in grid)
    if nu < 2 or nv < 2:
        raise ValueError(f"grid: expected (columns, rows) of at least 2 each, got {grid}")
    distance_mm = _check_distance(median_board_distance(obs, rvecs, tvecs)
                                  if distance_mm is None else distance_mm)
    u = np.linspace(0.0, camera.width - 1, nu)
    v = np.linspace(0.0, camera.height - 1, nv)
    centre = np.array([[(camera.width - 1) / 2, (camera.height - 1) / 2]])
    uv = np.concatenate([centre, np.stack(np.meshgrid(u, v), -1).reshape(-1, 2)])
    lin, names, sigma2, _ = _linearized(camera, obs, rvecs, tvecs, parameters)
    valid = camera.invertible(uv)
    sigma = np.full(len(uv), np.nan)
    if valid.any():
        sigma[valid] = _worst_direction(_propagate(lin, sigma2, camera, rvecs, tvecs, uv[valid],
                                                   distance_mm, parameters))
    on_grid = sigma[1:]
    worst = int(np.nanargmax(on_grid)) if np.isfinite(on_grid).any() else None
    return strict({
        "measure": "worst-direction 1-sigma (px): sqrt of the largest eigenvalue of the 2x2 "
                   "covariance of the mean-frames projection",
        "parameters": names,
        "distance_mm": distance_mm,
        "u": u, "v": v,
        "map_px": on_grid.reshape(nv, nu),
        "centre_px": float(sigma[0]),
        "worst_px": None if worst is None else float(on_grid[worst]),
        "worst_at": None if worst is None else uv[1 + worst],
        "sigma_px": float(np.sqrt(sigma2)),
    })
