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
chain rule. The iterations step each rotation on the left, R <- exp([w]x) R (the local
parametrization of Ceres' and COLMAP's rotation manifolds), whose Jacobian d(R p)/dw = -[R p]x
is one batched product for all views, where the Jacobian in rvec (``camera.rotate_jacobian``)
takes one call per view. Both describe the same cost over the same poses, so the minimum, and
the Schur complement on the intrinsics (invariant under an invertible change of each pose's
parameters), are the same; :func:`linearize` and :func:`intrinsic_information` give rvec
Jacobians, as their callers expect.

With ``board`` (a BoardShape giving the feature grid's centre and half-size), the board's shape
joins the shared parameters, after the model's: its warp (mrcal's two-parabola deflection w_x,
w_y in mm) and the stretch of its y axis against its x axis (a misprint along the paper feed, %),
core/board_shape.py's FIT_NAMES; d uv / d shape = d uv / d points_cam . R . d points / d shape.
A flat, true board is the same problem with the shape held at 0.

An iteration costs one Jacobian, the per-view blocks of the normal equations as batched
(V, 6, 6) products, and per trial step one projection without Jacobians. At the cost's floor a
rejected step whose predicted decrease rounding could not resolve ends the iterations, instead
of ~30 more trials raising the damping to its limit (benchmarks/calibration_speed.py times it).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from ..core.board_shape import BoardShape
from ..core.camera import INTRINSIC_NAMES, Camera, project_cam_with_jacobians
from ..core.lens import lens_model
from ..core.poses import matrix_to_rodrigues, rodrigues_to_matrix, rotate_jacobian


EPS = np.finfo(np.float64).eps
BOARD_NAMES = BoardShape.FIT_NAMES


class ProjectionModel(Protocol):
    param_names: tuple[str, ...]

    def project(self, params: np.ndarray, points_cam: np.ndarray, jacobians: bool = True
                ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        """points in the camera frame (N,3) -> uv (N,2), d uv/d params (N,2,P),
        d uv/d points_cam (N,2,3); both Jacobians None when ``jacobians`` is False"""
        ...


class CameraModel:
    """The camera core's model: params [fx, fy, cx, cy, skew] followed by the parameters of the
    lens model ``lens`` (core/lens.py; OpenCV's k1, k2, p1, p2, k3, k4, k5, k6 by default)."""

    def __init__(self, lens: str = "opencv"):
        self.lens = lens
        self.param_names = INTRINSIC_NAMES + lens_model(lens).param_names

    def project(self, params, points_cam, jacobians=True):
        uv, J = project_cam_with_jacobians(points_cam, params[:5], params[5:], jacobians,
                                           self.lens)
        if not jacobians:
            return uv, None, None
        return uv, np.concatenate([J["intrinsics"], J["dist"]], -1), J["point"]

    @staticmethod
    def params_of(camera: Camera) -> np.ndarray:
        return np.concatenate([camera.intrinsics, camera.dist])

    def camera(self, params: np.ndarray, name: str, image_size: tuple[int, int]) -> Camera:
        fx, fy, cx, cy, skew = params[:5]
        return Camera(name, image_size[0], image_size[1], fx, fy, cx, cy, skew, params[5:],
                      model=self.lens)


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
        NaN for fixed parameters, inf for parameters in the numerical null space; with a
        fitted board shape, P includes its FIT_NAMES last (``param_names`` names them).
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
    board: np.ndarray | None = None  # (w_x, w_y, aspect %) when the board's shape was fitted
    board_grid: list | None = None   # the feature grid it is about: [centre x, y, half x, y] mm

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
            **({} if self.board is None else {"board_warp_mm": self.board[:2].tolist(),
                                              "board_aspect_error_pct": float(self.board[2]),
                                              "board_grid_mm": self.board_grid}),
        }


class _Problem:
    """Board points of all views concatenated, with each view's (start, end) among them."""

    def __init__(self, model, free, object_points, image_points, board=None):
        self.model = model
        self.free = np.asarray(free, dtype=bool)
        self.n_model = len(model.param_names)
        self.points = np.concatenate(object_points)
        # The board's shape (its grid) and d point / d shape (N, 3, 3); None for a true board.
        self.shape = board
        self.basis = None if board is None else board.fit_jacobian(self.points[:, :2])
        self.observed = np.concatenate(image_points)
        self.magnitude = np.abs(self.observed).ravel() + 1.0  # (2N,) for refine's resolution
        counts = np.array([len(p) for p in object_points])
        self.view = np.repeat(np.arange(len(counts)), counts)
        self.bounds = list(zip(np.cumsum(counts) - counts, np.cumsum(counts)))
        # Per-view products are batched over the points of each view laid out as (V, n_max);
        # slots past a view's count take a zero row (index N) and are dropped after. Views of
        # one board all have its count, and then the layout is a plain reshape.
        n_max = int(counts.max())
        slots = np.arange(n_max)
        self.padding = (None if np.all(counts == n_max) else
                        np.where(slots < counts[:, None], (np.cumsum(counts) - counts)[:, None]
                                 + slots, len(self.points)))
        self.layout = (len(counts), 2 * n_max)
        self.board = self._laid(self.points)

    def _laid(self, points):
        """(N, k) per point -> (V, n_max, k), each view's points together (zeros past its end)."""
        if self.padding is not None:
            points = np.concatenate([points, np.zeros((1,) + points.shape[1:])])[self.padding]
        return points.reshape(self.layout[0], -1, points.shape[-1])

    def _board_points(self, params):
        """The board's points (N, 3) as the shared parameters shape them (or the nominal ones)."""
        if self.shape is None:
            return self.points
        return self.shape.with_fit(params[self.n_model:]).points(self.points)

    def _points_cam(self, params, rvecs, tvecs):
        """Each point in its view's camera frame (N, 3), through one (n_max, 3) x (3, 3)
        product per view instead of a gathered (N, 3, 3) rotation per point."""
        board = self.board if self.basis is None else self._laid(self._board_points(params))
        Pc = board @ rodrigues_to_matrix(rvecs).transpose(0, 2, 1) + tvecs[:, None, :]
        return Pc.reshape(-1, 3) if self.padding is None else Pc[self.padding < len(self.points)]

    def _project(self, params, Pc, rvecs, jacobians=True):
        """The model's projection; its parameter Jacobian with the board shape's columns
        appended."""
        uv, J_params, J_point = self.model.project(params[:self.n_model], Pc, jacobians)
        if jacobians and self.basis is not None:
            R = rodrigues_to_matrix(rvecs)[self.view]  # (N, 3, 3): each point's view
            J_shape = np.einsum("nij,njk,nkl->nil", J_point, R, self.basis)
            J_params = np.concatenate([J_params, J_shape], -1)
        return uv, J_params, J_point

    def residuals(self, params, rvecs, tvecs, jacobians=False):
        """r (N, 2) = projected - observed; with ``jacobians`` also d r / d free params
        (N, 2, F) and d r / d each point's own view's [rvec, tvec] (N, 2, 6)."""
        uv, J_params, J_point = self._project(params, self._points_cam(params, rvecs, tvecs),
                                              rvecs, jacobians)
        r = uv - self.observed
        if not jacobians:
            return r
        points = self._board_points(params)
        J_rot = np.concatenate([rotate_jacobian(rv, points[a:b])
                                for rv, (a, b) in zip(rvecs, self.bounds)])
        J_pose = np.concatenate([J_point @ J_rot, J_point], -1)  # (N,2,6) over [rvec, tvec]
        return r, J_params[:, :, self.free], J_pose

    def local_residuals(self, params, rvecs, tvecs):
        """r and its Jacobians as :meth:`residuals` gives them, the rotation part over the left
        increment w of R <- exp([w]x) R (module docstring): d(R p)/dw = -[R p]x, and a row j of
        d uv / d points_cam times -[q]x is the cross product q x j."""
        Pc = self._points_cam(params, rvecs, tvecs)
        uv, J_params, J_point = self._project(params, Pc, rvecs)
        J_rot = np.cross((Pc - tvecs[self.view])[:, None, :], J_point)
        return (uv - self.observed, J_params[:, :, self.free],
                np.concatenate([J_rot, J_point], -1))

    def _per_view(self, J):
        """(N, 2, k) -> (V, 2 n_max, k), each view's rows together (zero rows past its end)."""
        if self.padding is not None:
            J = np.concatenate([J, np.zeros((1,) + J.shape[1:])])[self.padding]
        return J.reshape(self.layout + J.shape[-1:])

    def normal_equations(self, r, Ja, Jb):
        """Blocks of J^T J and J^T r: U (F,F), V (V,6,6), W (V,F,6), ga (F,), gb (V,6)."""
        Jbv = self._per_view(Jb)
        JbT = Jbv.transpose(0, 2, 1)
        Jav, rv = self._per_view(Ja), self._per_view(r[:, :, None])
        Ja, r = Ja.reshape(r.size, Ja.shape[-1]), r.reshape(-1)
        return (Ja.T @ Ja, JbT @ Jbv, Jav.transpose(0, 2, 1) @ Jbv, Ja.T @ r,
                (JbT @ rv)[:, :, 0])


def _schur(U, V, W):
    """U - sum_v W_v V_v^-1 W_v^T and the pieces to back-substitute the poses."""
    V_inv = np.linalg.inv(V)
    WV = W @ V_inv
    shape = (len(U), 6 * len(W))  # the sum over views and pose coordinates as one product
    return (U - WV.transpose(1, 0, 2).reshape(shape) @ W.transpose(1, 0, 2).reshape(shape).T,
            V_inv, WV)


def _solve_damped(U, V, W, ga, gb, lam):
    """Solve (J^T J + lam diag(J^T J)) delta = -J^T r for (delta_intrinsics, delta_poses)."""
    Ud = U + lam * np.diag(np.diag(U))
    Vd = V + lam * np.diagonal(V, axis1=1, axis2=2)[:, :, None] * np.eye(6)
    S, V_inv, WV = _schur(Ud, Vd, W)
    da = np.linalg.solve(S, -ga + WV.transpose(1, 0, 2).reshape(len(U), gb.size) @ gb.ravel())
    db = -(V_inv @ (gb + da @ W)[:, :, None])[:, :, 0]
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
    # The Schur complement does not depend on the poses' parametrization: the batched one.
    r, Ja, Jb = problem.local_residuals(np.asarray(params, float), np.asarray(rvecs, float),
                                        np.asarray(tvecs, float))
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
           rcond: float = 1e-10, board: BoardShape | None = None,
           fit_warp: bool = True) -> RefineResult:
    """Levenberg-Marquardt over the free intrinsics and all poses; see the module docstring.

    params0 (P,), free (P,) bool, object_points / image_points per view, rvecs0 / tvecs0 (V, 3)
    cam_from_board. ``board``: the board's shape (warp and aspect error, BoardShape.FIT_NAMES)
    about its feature grid's centre and half-size, starting at ``board``'s own; fitted with
    ``fit_warp`` (the result's ``board`` and its ``param_std``), else held. Stops when a step
    changes the cost by less than ``ftol`` relative or the parameters by less than ``xtol``
    relative (in Marquardt's scaling), when no damping gives a decrease, or the linear model
    predicts none by more than ``ftol`` relative or than rounding resolves (the cost is at its
    floating-point floor), or after ``max_iter`` Jacobians.
    """
    warp = board is not None
    if warp:
        params0 = np.r_[np.asarray(params0, dtype=np.float64), board.fit_params]
        free = np.r_[np.asarray(free, dtype=bool), [fit_warp] * len(BOARD_NAMES)]
    param_names = tuple(model.param_names) + (BOARD_NAMES if warp else ())
    problem = _Problem(model, free, object_points, image_points, board)
    x = np.array(params0, dtype=np.float64)
    rv, tv = np.array(rvecs0, dtype=np.float64), np.array(tvecs0, dtype=np.float64)
    if len(x) != len(param_names) or problem.free.shape != x.shape:
        raise ValueError(f"params0 and free must have {len(model.param_names)} entries "
                         f"{model.param_names}, got {len(x) - len(BOARD_NAMES) * warp} and "
                         f"{problem.free.shape[0] - len(BOARD_NAMES) * warp}")
    if rv.shape != (len(object_points), 3) or tv.shape != rv.shape:
        raise ValueError(f"rvecs0 and tvecs0 must be ({len(object_points)}, 3), "
                         f"got {rv.shape} and {tv.shape}")

    r, Ja, Jb = problem.local_residuals(x, rv, tv)
    normal = problem.normal_equations(r, Ja, Jb)
    cost = cost0 = 0.5 * float(np.sum(r * r))
    lam, iterations, reason = 1e-3, 0, "max_iter"
    while iterations < max_iter:
        if cost == 0.0:
            reason = "zero cost"
            break
        iterations += 1
        U, V, W, ga, gb = normal
        D = np.concatenate([np.diag(U), np.diagonal(V, axis1=1, axis2=2).ravel()])
        g = np.concatenate([ga, gb.ravel()])
        R = rodrigues_to_matrix(rv)
        # What rounding leaves unresolved in a cost change: each residual carries ~eps times the
        # pixel coordinate it is the difference of, independently (on exact data this is all
        # that is left of the cost).
        resolution = max(ftol * cost, EPS * float(np.linalg.norm(r.ravel() * problem.magnitude)))
        while True:  # raise the damping until a step decreases the cost (NaN does not)
            da, db = _solve_damped(U, V, W, ga, gb, lam)
            delta = np.concatenate([da, db.ravel()])
            x_new = x.copy()
            x_new[problem.free] += da
            rv_new = matrix_to_rodrigues(rodrigues_to_matrix(db[:, :3]) @ R)
            tv_new = tv + db[:, 3:]
            r_new = problem.residuals(x_new, rv_new, tv_new)
            cost_new = 0.5 * float(np.sum(r_new * r_new))
            if cost_new < cost:
                break
            # The decrease the linear model predicts, 0.5 (lam delta^T D delta - g^T delta),
            # only shrinks as the damping grows: once it is below ftol relative or below what
            # rounding resolves, no further damping can give a decrease that counts.
            if not 0.5 * (lam * delta @ (D * delta) - g @ delta) > resolution or lam >= 1e16:
                reason = "no decrease (cost at its floor)"
                break
            lam *= 10.0
        if not cost_new < cost:
            break
        # Marquardt's scaling sqrt(diag(J^T J)) makes the step test unit-free (MINPACK's xtol);
        # a left increment w and the rvec change it makes have comparable sizes (equal near 0).
        scale = np.sqrt(D)
        step = np.linalg.norm(scale * delta)
        size = np.linalg.norm(scale * np.concatenate([x[problem.free], rv.ravel(), tv.ravel()]))
        decrease = cost - cost_new
        x, rv, tv, cost = x_new, rv_new, tv_new, cost_new
        lam = max(lam / 10.0, 1e-15)
        r, Ja, Jb = problem.local_residuals(x, rv, tv)
        normal = problem.normal_equations(r, Ja, Jb)
        if decrease <= ftol * (cost + decrease):
            reason = "ftol"
            break
        if step <= xtol * size:
            reason = "xtol"
            break

    # The Schur complement on the intrinsics does not depend on how the poses are parametrized.
    U, V, W = normal[:3]
    S = _schur(U, V, W)[0]
    names = [n for n, f in zip(param_names, problem.free) if f]
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
    n = len(model.param_names)
    return RefineResult(x[:n], rv, tv, cost0, cost, iterations,
                        float(np.sqrt(2.0 * cost / n_points)), r, std, info, param_names, reason,
                        x[n:] if warp else None,
                        [*board.centre_mm, *board.half_mm] if warp else None)
