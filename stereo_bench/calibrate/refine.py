"""The one nonlinear least-squares stage shared by every calibration method.

Maximum-likelihood refinement (Zhang 2000, section 3.2; Bouguet's toolbox main optimization;
Tsai 1987 step 3) is a small bundle adjustment: shared intrinsic parameters of a pluggable
``ProjectionModel`` plus one 6-DOF pose (rvec, tvec; cam_from_board) per view, minimizing the sum
of squared pixel residuals.

The solver is Levenberg-Marquardt (Marquardt's diagonal scaling, so fx ~ 3000 px and k1 ~ 0.05
share one damping) on the normal equations, exploiting their block structure: each pose touches
only its own view's residuals, so the pose blocks are eliminated view by view and only the small
Schur complement on the intrinsic block is solved (Triggs et al., "Bundle adjustment - a modern
synthesis", 2000, section 6.1). That Schur complement at the optimum is also the Gauss-Newton
information of the intrinsics with the poses marginalized out; its inverse times the residual
variance gives the parameter standard deviations, and its (scale-normalized) spectrum reveals
parameters the data cannot identify (e.g. the rational k1..k6 of TRAPS.md).

A model supplies only d uv / d params and d uv / d points_cam; the pose Jacobians follow by the
chain rule through ``camera.rotate_jacobian``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from ..camera import (DIST_NAMES, INTRINSIC_NAMES, Camera, project_with_jacobians,
                      rodrigues_to_matrix, rotate_jacobian)


class ProjectionModel(Protocol):
    param_names: tuple[str, ...]

    def project(self, params: np.ndarray, points_cam: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """points in the camera frame (N,3) -> uv (N,2), d uv/d params (N,2,P),
        d uv/d points_cam (N,2,3)"""
        ...


class OpenCVModel:
    """The camera core's model: params [fx, fy, cx, cy, skew, k1, k2, p1, p2, k3, k4, k5, k6]."""

    param_names = INTRINSIC_NAMES + DIST_NAMES
    _zero = np.zeros(3)

    def project(self, params, points_cam):
        uv, J = project_with_jacobians(points_cam, params[:5], params[5:], self._zero, self._zero)
        return uv, np.concatenate([J["intrinsics"], J["dist"]], -1), J["point"]

    @staticmethod
    def params_of(camera: Camera) -> np.ndarray:
        return np.concatenate([camera.intrinsics, camera.dist])

    @staticmethod
    def camera(params: np.ndarray, name: str, image_size: tuple[int, int]) -> Camera:
        fx, fy, cx, cy, skew = params[:5]
        return Camera(name, image_size[0], image_size[1], fx, fy, cx, cy, skew, params[5:13])


def free_mask(param_names: tuple[str, ...], free_names) -> np.ndarray:
    """Boolean mask over ``param_names`` that is True for the names in ``free_names``."""
    unknown = set(free_names) - set(param_names)
    if unknown:
        raise ValueError(f"unknown parameters {sorted(unknown)}; expected some of {param_names}")
    return np.array([n in free_names for n in param_names])


@dataclass(frozen=True)
class RefineResult:
    """Outcome of :func:`refine`.

    cost0, cost: 0.5 * sum of squared residuals (px^2) before and after.
    rms_px: sqrt(mean over points of |residual|^2), the paper's RPE_RMS.
    residuals: (N_total, 2) projected - observed pixels, views concatenated in order.
    param_std: (P,) standard deviations (residual variance times the inverse information);
        NaN for fixed parameters, inf for parameters in the numerical null space.
    jacobian_rank_info: rank, n_free, condition, rcond and the unidentifiable parameter names of
        the intrinsic information matrix (scale-normalized, poses marginalized).
    """

    params: np.ndarray
    rvecs: np.ndarray
    tvecs: np.ndarray
    cost0: float
    cost: float
    iterations: int
    rms_px: float
    residuals: np.ndarray
    param_std: np.ndarray
    jacobian_rank_info: dict
    param_names: tuple[str, ...]
    stop_reason: str

    def log(self) -> dict:
        """The fields every refining method puts in CalibrationResult.log."""
        return {
            "iterations": self.iterations,
            "initial_cost": self.cost0,
            "final_cost": self.cost,
            "rms_px": self.rms_px,
            "stop_reason": self.stop_reason,
            "param_std": {n: float(s) for n, s in zip(self.param_names, self.param_std)
                          if not np.isnan(s)},
            "rank": self.jacobian_rank_info,
        }


class _Problem:
    """Board points of all views concatenated, with each view's (start, end) among them."""

    def __init__(self, model, free, object_points, image_points):
        self.model = model
        self.free = np.asarray(free, dtype=bool)
        self.points = np.concatenate(object_points)
        self.observed = np.concatenate(image_points)
        counts = np.array([len(p) for p in object_points])
        self.view = np.repeat(np.arange(len(counts)), counts)
        self.bounds = list(zip(np.cumsum(counts) - counts, np.cumsum(counts)))

    def residuals(self, params, rvecs, tvecs, jacobians=False):
        R = rodrigues_to_matrix(rvecs)[self.view]
        points_cam = (R @ self.points[:, :, None])[:, :, 0] + tvecs[self.view]
        uv, J_params, J_point = self.model.project(params, points_cam)
        r = uv - self.observed
        if not jacobians:
            return r
        J_rot = np.concatenate([rotate_jacobian(rv, self.points[a:b])
                                for rv, (a, b) in zip(rvecs, self.bounds)])
        J_pose = np.concatenate([J_point @ J_rot, J_point], -1)  # (N,2,6) over [rvec, tvec]
        return r, J_params[:, :, self.free], J_pose

    def normal_equations(self, r, Ja, Jb):
        """Blocks of J^T J and J^T r: U (F,F), V (V,6,6), W (V,F,6), ga (F,), gb (V,6)."""
        Ja, Jb, r = Ja.reshape(r.size, Ja.shape[-1]), Jb.reshape(r.size, 6), r.reshape(-1)
        blocks = [(Jb[2 * a:2 * b].T @ Jb[2 * a:2 * b], Ja[2 * a:2 * b].T @ Jb[2 * a:2 * b],
                   Jb[2 * a:2 * b].T @ r[2 * a:2 * b]) for a, b in self.bounds]
        V, W, gb = (np.array(x) for x in zip(*blocks))
        return Ja.T @ Ja, V, W, Ja.T @ r, gb


def _schur(U, V, W):
    """U - sum_v W_v V_v^-1 W_v^T and the pieces to back-substitute the poses."""
    V_inv = np.linalg.inv(V)
    WV = W @ V_inv
    return U - np.einsum("vij,vkj->ik", WV, W), V_inv, WV


def _solve_damped(U, V, W, ga, gb, lam):
    """Solve (J^T J + lam diag(J^T J)) delta = -J^T r for (delta_intrinsics, delta_poses)."""
    eye6 = np.eye(6)
    Ud = U + lam * np.diag(np.diag(U))
    Vd = V + lam * np.diagonal(V, axis1=1, axis2=2)[:, :, None] * eye6
    S, V_inv, WV = _schur(Ud, Vd, W)
    rhs = -ga + np.einsum("vij,vj->i", WV, gb)
    da = np.linalg.solve(S, rhs)
    db = -np.einsum("vij,vj->vi", V_inv, gb + np.einsum("vji,j->vi", W, da))
    return da, db


def rank_info(S: np.ndarray, names: list[str], rcond: float = 1e-10) -> dict:
    """Numerical rank and null space of an information matrix, after scaling to unit diagonal.

    The scaling makes the test independent of units (px for fx, unitless for k1). A parameter is
    reported unidentifiable when it has a component above 0.1 in an eigenvector whose eigenvalue
    is below ``rcond`` times the largest.
    """
    if len(names) == 0:
        return {"rank": 0, "n_free": 0, "condition": 1.0, "rcond": rcond, "unidentifiable": []}
    diag = np.diag(S)
    # A parameter the data do not touch at all (zero information) is unidentifiable as it is;
    # scaling by its zero diagonal would overflow the rest of the matrix.
    untouched = ~(diag > 0) | ~np.isfinite(diag)
    d = np.sqrt(np.where(untouched, 1.0, diag))
    scaled = np.where(np.outer(untouched, untouched) | np.eye(len(d), dtype=bool), 0.0,
                      S / np.outer(d, d))
    scaled[np.diag_indices(len(d))] = np.where(untouched, 0.0, 1.0)
    if not np.all(np.isfinite(scaled)):
        return {"rank": 0, "n_free": len(names), "condition": float("inf"), "rcond": rcond,
                "unidentifiable": list(names)}
    ev, vec = np.linalg.eigh(scaled)
    null = ev < rcond * ev[-1]
    weak = (np.abs(vec[:, null]).max(axis=1, initial=0.0) > 0.1) | untouched
    return {
        "rank": int(np.sum(~null)),
        "n_free": len(names),
        "condition": float(ev[-1] / ev[0]) if ev[0] > 0 else float("inf"),
        "rcond": rcond,
        "unidentifiable": [n for n, w in zip(names, weak) if w],
    }


def intrinsic_information(model: ProjectionModel, params, free, object_points, rvecs, tvecs
                          ) -> np.ndarray:
    """J^T J of the free intrinsics with the poses marginalized (Schur complement), (F, F).

    Divided by the per-coordinate noise variance it is the Fisher information, so
    sqrt(diag(inv(.))) * sigma is the Cramer-Rao bound on the intrinsics' standard deviations.
    Only the geometry matters: the residuals are evaluated against the model's own projections.
    """
    problem = _Problem(model, free, object_points, [np.zeros((len(p), 2)) for p in object_points])
    r, Ja, Jb = problem.residuals(np.asarray(params, float), np.asarray(rvecs, float),
                                  np.asarray(tvecs, float), jacobians=True)
    U, V, W, _, _ = problem.normal_equations(r, Ja, Jb)
    return _schur(U, V, W)[0]


def linearize(model: ProjectionModel, params, free, object_points, image_points, rvecs, tvecs,
              rcond: float = 1e-10) -> dict:
    """The problem of :func:`refine` linearized at given parameters (usually a solution), for
    what follows a fit: covariances, leverages, uncertainty propagation.

    ``residuals`` (N, 2) projected - observed, views concatenated; ``J_params`` (N, 2, F) over
    the free intrinsics; ``J_pose`` (N, 2, 6) over each point's own view's [rvec, tvec];
    ``bounds`` each view's (start, end) among the N points; the normal-equation blocks ``V``
    (V, 6, 6) and ``W`` (V, F, 6); ``S`` (F, F) their Schur complement (the intrinsic
    information with the poses marginalized) and ``S_inv`` its inverse as refine's param_std
    takes it: a pseudo-inverse after scaling to unit diagonal, so null-space directions (see
    :func:`rank_info`) get no variance instead of an overflow.
    """
    problem = _Problem(model, free, object_points, image_points)
    r, Ja, Jb = problem.residuals(np.asarray(params, float), np.asarray(rvecs, float),
                                  np.asarray(tvecs, float), jacobians=True)
    U, V, W, _, _ = problem.normal_equations(r, Ja, Jb)
    S = _schur(U, V, W)[0]
    d = np.sqrt(np.maximum(np.diag(S), 1e-300))
    S_inv = (np.linalg.pinv(S / np.outer(d, d), rcond=rcond, hermitian=True) / np.outer(d, d)
             if len(S) else S)
    return {"residuals": r, "J_params": Ja, "J_pose": Jb, "bounds": problem.bounds, "V": V,
            "W": W, "S": S, "S_inv": S_inv}


def refine(model: ProjectionModel, params0, free, object_points, image_points, rvecs0, tvecs0,
           max_iter: int = 100, xtol: float = 1e-15, ftol: float = 1e-15,
           rcond: float = 1e-10) -> RefineResult:
    """Levenberg-Marquardt over the free intrinsics and all poses; see the module docstring.

    params0 (P,), free (P,) bool, object_points / image_points per view, rvecs0 / tvecs0 (V, 3)
    cam_from_board. Stops when a step changes the cost by less than ``ftol`` relative or the
    parameters by less than ``xtol`` relative (in Marquardt's scaling), when no damping gives a
    decrease (the cost is at its floating-point floor), or after ``max_iter`` Jacobians.
    """
    problem = _Problem(model, free, object_points, image_points)
    x = np.array(params0, dtype=np.float64)
    rv, tv = np.array(rvecs0, dtype=np.float64), np.array(tvecs0, dtype=np.float64)
    if len(x) != len(model.param_names) or problem.free.shape != x.shape:
        raise ValueError(f"params0 and free must have {len(model.param_names)} entries "
                         f"{model.param_names}, got {len(x)} and {problem.free.shape}")
    if rv.shape != (len(object_points), 3) or tv.shape != rv.shape:
        raise ValueError(f"rvecs0 and tvecs0 must be ({len(object_points)}, 3), "
                         f"got {rv.shape} and {tv.shape}")

    r, Ja, Jb = problem.residuals(x, rv, tv, jacobians=True)
    cost = cost0 = 0.5 * float(np.sum(r * r))
    lam, iterations, reason = 1e-3, 0, "max_iter"
    while iterations < max_iter:
        if cost == 0.0:
            reason = "zero cost"
            break
        iterations += 1
        U, V, W, ga, gb = problem.normal_equations(r, Ja, Jb)
        while lam <= 1e16:  # raise the damping until a step decreases the cost (NaN does not)
            da, db = _solve_damped(U, V, W, ga, gb, lam)
            x_new = x.copy()
            x_new[problem.free] += da
            rv_new, tv_new = rv + db[:, :3], tv + db[:, 3:]
            r_new = problem.residuals(x_new, rv_new, tv_new)
            cost_new = 0.5 * float(np.sum(r_new * r_new))
            if cost_new < cost:
                break
            lam *= 10.0
        else:
            reason = "no decrease (cost at its floor)"
            break
        # Marquardt's scaling sqrt(diag(J^T J)) makes the step test unit-free (MINPACK's xtol).
        scale = np.sqrt(np.concatenate([np.diag(U), np.diagonal(V, axis1=1, axis2=2).ravel()]))
        step = np.linalg.norm(scale * np.concatenate([da, db.ravel()]))
        size = np.linalg.norm(scale * np.concatenate([x[problem.free], rv.ravel(), tv.ravel()]))
        decrease = cost - cost_new
        x, rv, tv, cost = x_new, rv_new, tv_new, cost_new
        lam = max(lam / 10.0, 1e-15)
        r, Ja, Jb = problem.residuals(x, rv, tv, jacobians=True)
        if decrease <= ftol * (cost + decrease):
            reason = "ftol"
            break
        if step <= xtol * size:
            reason = "xtol"
            break

    U, V, W, _, _ = problem.normal_equations(r, Ja, Jb)
    S = _schur(U, V, W)[0]
    names = [n for n, f in zip(model.param_names, problem.free) if f]
    info = rank_info(S, names, rcond)
    dof = r.size - len(names) - 6 * len(rv)
    sigma2 = 2.0 * cost / dof if dof > 0 else float("nan")
    std = np.full(len(x), np.nan)
    if names:
        # Pseudo-inverse: null-space directions get no variance here and are marked inf below,
        # so an unidentifiable parameter never passes for a well-determined one.
        d = np.sqrt(np.maximum(np.diag(S), 1e-300))
        cov = np.linalg.pinv(S / np.outer(d, d), rcond=rcond, hermitian=True) / np.outer(d, d)
        free_std = np.sqrt(np.maximum(np.diag(cov), 0.0) * sigma2)
        free_std[[n in info["unidentifiable"] for n in names]] = np.inf
        std[problem.free] = free_std
    n_points = len(r)
    return RefineResult(x, rv, tv, cost0, cost, iterations, float(np.sqrt(2.0 * cost / n_points)),
                        r, std, info, tuple(model.param_names), reason)
