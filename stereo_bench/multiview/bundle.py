"""Rig calibration: the relative poses of two or more calibrated cameras that watch one board.

Input: per camera an intrinsic estimate (a ``Camera`` from any calibration method; its pose is
ignored), synchronized board observations ``image_points (C, F, N, 2)`` of ``object_points
(N, 3)`` (NaN = not detected), and per camera per frame the cam_from_board pose found by that
camera's own calibration, ``board_rvecs, board_tvecs (C, F, 3)`` (NaN where not found).

1. Initialization (camera 0 is the reference). For a pair of cameras every frame both see gives
   one estimate of b_from_a; the rotations are averaged robustly: the medoid (the frame rotation
   with the least summed geodesic distance to the others) fixes a robust centre, frames farther
   than 3 robust standard deviations (1.4826 x the median distance, at least 0.1 deg) are dropped
   (e.g. a flipped PnP solution), and the chordal L2 mean of the rest is the SVD projection of
   their summed matrices onto SO(3) (Hartley, Trumpf, Dai & Li, "Rotation averaging", IJCV 2013).
   The translation is the coordinate-wise median of ``t_b - R t_a`` over the kept frames, with the
   averaged R. Cameras are joined to camera 0 along a maximum spanning tree of the shared-frame
   counts (Prim), so a camera that shares no frame with camera 0 is chained through others.
2. Joint refinement, a bundle adjustment over one cam0_from_board pose per frame and one
   cam_from_cam0 per camera (camera 0's is the identity: the gauge; the board's known geometry
   fixes the scale), residuals = pixel reprojection errors through
   ``camera.project_with_jacobians``. Intrinsics are fixed by default, and then only frames seen
   by two or more cameras are used (a frame seen by one camera says nothing about the rig): the
   cost cv2.stereoCalibrate minimizes with CALIB_FIX_INTRINSIC, for any number of cameras.
   Optionally each camera's intrinsics join the adjustment (the OpenCV-model parameters its
   method estimates), and then every frame any camera saw is used, since each constrains that
   camera's intrinsics. The Jacobian is analytic and sparse (a frame pose touches only that
   frame's residuals, a camera's intrinsics only that camera's) and goes to scipy's
   ``least_squares`` ('trf', x_scale='jac'), with an optional robust loss (soft_l1, huber,
   cauchy: a wrong corner then pulls the rig less than its square would).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
import scipy.sparse
from scipy.optimize import least_squares
from threadpoolctl import threadpool_limits

from ..calibrate.base import MIN_POINTS_PER_VIEW
from ..core.camera import (INTRINSIC_NAMES, Camera, project_points,
                           project_with_jacobians)
from ..core.poses import (compose, geodesic_distance, invert, matrix_to_rodrigues, nearest_rotation,
                          rodrigues_to_matrix, rotate_jacobian)
from ..core.poses import cam_from_cam0

MIN_OUTLIER_DEG = 0.1  # rotation-averaging inlier radius never goes below this


@dataclass(frozen=True, eq=False)
class RigCalibration:
    """A calibrated rig; the world frame is camera 0's.

    cameras: the input intrinsics with cam_from_world = cam_from_cam0.
    board_rvecs, board_tvecs: (F, 3) cam0_from_board per frame; NaN for frames not used.
    frames_used: (F,) bool, the frames in the adjustment (seen by two or more cameras; by one or
    more when intrinsics are refined).
    rms_px: RMS reprojection error (px per point) over all observations; rms_px_per_camera (C,).
    iterations: Jacobian evaluations of the solver; time_s: wall time of the whole calibration.
    log: initial_rms_px, nfev, status and message of the solver, n_observations, loss,
    refined_intrinsics (per camera the parameters adjusted), "covisibility" (frames each pair of
    cameras saw together, C x C; the diagonal: frames each camera saw) and "initialization": per
    camera its name, the camera it was chained from ("parent"), the frames they share and the
    frames kept by the rotation average.
    """

    cameras: list[Camera]
    board_rvecs: np.ndarray
    board_tvecs: np.ndarray
    frames_used: np.ndarray
    rms_px: float
    rms_px_per_camera: np.ndarray
    iterations: int
    time_s: float
    log: dict = field(default_factory=dict)


# ----------------------------------------------------------------------------------------------
# Initialization
# ----------------------------------------------------------------------------------------------

def average_rotations(R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Robust mean of rotations (K, 3, 3) -> (R (3, 3), inliers (K,) bool); see the module notes."""
    d = geodesic_distance(R[:, None], R[None, :])
    medoid = int(np.argmin(d.sum(axis=1)))
    dm = d[medoid]
    inliers = dm <= max(3 * 1.4826 * np.median(dm), np.radians(MIN_OUTLIER_DEG))
    return nearest_rotation(R[inliers].sum(axis=0)), inliers


def relative_pose(Ra, ta, Rb, tb) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """b_from_a from per-frame a_from_board (Ra (K,3,3), ta (K,3)) and b_from_board (Rb, tb).

    Returns (R (3,3), t (3,), inlier frames (K,) bool).
    """
    R, inliers = average_rotations(Rb @ np.swapaxes(Ra, -1, -2))
    t = np.median((tb - ta @ R.T)[inliers], axis=0)
    return R, t, inliers


def initial_rig(board_R: np.ndarray, board_t: np.ndarray, seen: np.ndarray,
                names: Sequence[str]) -> tuple[np.ndarray, np.ndarray, list[dict]]:
    """cam_from_cam0 for every camera from per-camera cam_from_board poses.

    board_R (C, F, 3, 3), board_t (C, F, 3), seen (C, F) bool -> (R (C,3,3), t (C,3), per-camera
    log). Raises ValueError naming the cameras that cannot be connected to camera 0.
    """
    C = len(seen)
    shared = covisibility(seen)
    R, t = np.tile(np.eye(3), (C, 1, 1)), np.zeros((C, 3))
    log = [{"camera": names[0], "parent": None, "shared_frames": int(seen[0].sum()),
            "kept_frames": None}] + [None] * (C - 1)
    joined = [0]
    while len(joined) < C:
        free = [j for j in range(C) if j not in joined]
        i, j = max(((i, j) for i in joined for j in free), key=lambda ij: shared[ij])
        if shared[i, j] == 0:
            raise ValueError(
                f"rig calibration: cameras {[names[k] for k in free]} share no frame with camera "
                f"{names[0]!r} or any camera connected to it; expected every camera to see the "
                f"board together with another camera in at least one frame")
        both = seen[i] & seen[j]
        Rji, tji, inl = relative_pose(board_R[i, both], board_t[i, both],
                                      board_R[j, both], board_t[j, both])
        R[j], t[j] = compose(Rji, tji, R[i], t[i])
        log[j] = {"camera": names[j], "parent": names[i], "shared_frames": int(both.sum()),
                  "kept_frames": int(inl.sum())}
        joined.append(j)
    return R, t, log


# ----------------------------------------------------------------------------------------------
# Joint refinement
# ----------------------------------------------------------------------------------------------



def model_parameters(camera: Camera) -> tuple[str, ...]:
    """A camera's intrinsics as the adjustment sees them: INTRINSIC_NAMES then its lens's."""
    return INTRINSIC_NAMES + camera.dist_names


class _RigProblem:
    """Residuals and sparse Jacobian of the rig's reprojection errors.

    x = [cam_from_cam0 (rvec, tvec) of cameras 1..C-1, the free intrinsics of each camera in
    turn (``free[c]``, a mask over model_parameters(camera)), with ``board`` the board's shape
    (BoardShape.FIT_NAMES), cam0_from_board of each used frame]. Residuals are ordered camera by
    camera, observation by observation, (u, v).
    """

    def __init__(self, cameras, object_points, image_points, valid, free, board=None):
        self.cameras, self.obj = cameras, object_points
        self.C, self.F = len(cameras), valid.shape[1]
        self.n_rig = 6 * (self.C - 1)
        self.free = free
        self.params0 = [np.concatenate([c.intrinsics, c.dist]) for c in cameras]
        sizes = [int(m.sum()) for m in free]
        self.intr_at = self.n_rig + np.concatenate([[0], np.cumsum(sizes)])
        # The board's shape, after the intrinsics: its grid and d points / d shape (N, 3, 3).
        self.board = board
        self.shape_jac = None if board is None else board.fit_jacobian(object_points[:, :2])
        n_shape = 0 if board is None else len(board.FIT_NAMES)
        self.n_head = int(self.intr_at[-1]) + n_shape
        self.valid = valid  # (C, F, N)
        self.obs = [image_points[c][valid[c]] for c in range(self.C)]
        rows, cols, self.offsets = [], [], [0]
        for c in range(self.C):
            f = np.nonzero(valid[c])[0]
            k = len(f)
            blocks = [self.n_head + 6 * f[:, None] + np.arange(6)]  # (K, 6) board columns
            if board is not None:
                blocks.insert(0, np.broadcast_to(self.intr_at[-1] + np.arange(n_shape),
                                                 (k, n_shape)))
            if sizes[c]:
                blocks.insert(0, np.broadcast_to(self.intr_at[c] + np.arange(sizes[c]),
                                                 (k, sizes[c])))
            if c > 0:
                blocks.insert(0, np.broadcast_to(6 * (c - 1) + np.arange(6), (k, 6)))
            cb = np.concatenate(blocks, axis=1)  # (K, ncol)
            r = self.offsets[-1] + 2 * np.arange(k)[:, None] + np.arange(2)  # (K, 2)
            rows.append(np.broadcast_to(r[:, :, None], (k, 2, cb.shape[1])).ravel())
            cols.append(np.broadcast_to(cb[:, None, :], (k, 2, cb.shape[1])).ravel())
            self.offsets.append(self.offsets[-1] + 2 * k)
        self.rows, self.cols = np.concatenate(rows), np.concatenate(cols)
        self.shape = (self.offsets[-1], self.n_head + 6 * self.F)

    def initial_intrinsics(self) -> np.ndarray:
        return np.concatenate([p[m] for p, m in zip(self.params0, self.free)])

    def unpack(self, x):
        """(rig poses (C, 6), per-camera model parameters (5 intrinsics + the camera's lens
        parameters each), board poses (F, 6))."""
        rig = np.vstack([np.zeros(6), x[: self.n_rig].reshape(-1, 6)])
        params = []
        for c, (p, m) in enumerate(zip(self.params0, self.free)):
            p = p.copy()
            p[m] = x[self.intr_at[c]: self.intr_at[c + 1]]
            params.append(p)
        return rig, params, x[self.n_head:].reshape(-1, 6)

    def board_shape(self, x) -> np.ndarray | None:
        """The board's shape parameters in x (None without a board)."""
        return None if self.board is None else x[int(self.intr_at[-1]):self.n_head]

    def evaluate(self, x, jacobian: bool):
        rig, params, boards = self.unpack(x)
        obj = self.obj if self.board is None else self.board.with_fit(self.board_shape(x)).points(
            self.obj)
        R_b = rodrigues_to_matrix(boards[:, :3])
        Y = np.einsum("fij,nj->fni", R_b, obj) + boards[:, None, 3:]  # camera 0's frame
        if jacobian:  # d Y / d (rvec, tvec) of cam0_from_board, (F, N, 3, 6)
            dY = np.concatenate([np.stack([rotate_jacobian(b[:3], obj) for b in boards]),
                                 np.broadcast_to(np.eye(3), Y.shape + (3,))], axis=-1)
            if self.board is not None:  # d Y / d shape (F, N, 3, 3)
                dS = np.einsum("fij,njk->fnik", R_b, self.shape_jac)
        res, data = [], []
        for c in range(self.C):
            uv, J = project_with_jacobians(Y[self.valid[c]], params[c][:5], params[c][5:],
                                           rig[c, :3], rig[c, 3:], jacobians=jacobian,
                                           model=self.cameras[c].model)
            res.append((uv - self.obs[c]).ravel())
            if jacobian:
                blocks = [J["point"] @ dY[self.valid[c]]]
                if self.board is not None:
                    blocks.insert(0, J["point"] @ dS[self.valid[c]])
                if self.free[c].any():
                    blocks.insert(0, np.concatenate([J["intrinsics"], J["dist"]],
                                                    -1)[..., self.free[c]])
                if c > 0:
                    blocks.insert(0, J["pose"])
                data.append(np.concatenate(blocks, -1).ravel())
        r = np.concatenate(res)
        if not jacobian:
            return r
        return scipy.sparse.csr_matrix((np.concatenate(data), (self.rows, self.cols)),
                                       shape=self.shape)

    def rms(self, x) -> tuple[float, np.ndarray]:
        r = self.evaluate(x, False)
        per = [np.sqrt(np.mean(r[a:b] ** 2) * 2) if b > a else float("nan")
               for a, b in zip(self.offsets, self.offsets[1:])]
        return float(np.sqrt(np.mean(r**2) * 2)), np.array(per)


def covisibility(seen: np.ndarray) -> np.ndarray:
    """(C, C) int: frames each pair of cameras saw together (diagonal: frames each saw), from
    seen (C, F) bool."""
    seen = np.asarray(seen, dtype=bool)
    return (seen[:, None, :] & seen[None, :, :]).sum(-1)


def unreachable(seen: np.ndarray) -> list[int]:
    """Indices of the cameras not joined to camera 0 through frames two cameras saw together
    (seen (C, F) bool): a rig with any cannot be calibrated as one."""
    linked = covisibility(seen) > 0
    joined, todo = {0}, [0]
    while todo:
        for j in np.flatnonzero(linked[todo.pop()]):
            if int(j) not in joined:
                joined.add(int(j))
                todo.append(int(j))
    return [c for c in range(len(linked)) if c not in joined]


def reprojection_rms(cameras: Sequence[Camera], object_points, image_points, board_rvecs,
                     board_tvecs, observed) -> tuple[float, np.ndarray]:
    """RMS reprojection error (px per point) of a calibrated rig through the camera core, over
    all observations and per camera (C,): cameras with cam_from_world = cam_from_cam0,
    board_rvecs/tvecs (F, 3) cam0_from_board, observed (C, F, N) bool the observations to count
    in image_points (C, F, N, 2). A camera with none gets NaN."""
    obj = np.asarray(object_points, dtype=np.float64)
    R0b = rodrigues_to_matrix(np.where(np.isfinite(board_rvecs), board_rvecs, 0.0))
    t0b = np.where(np.isfinite(board_tvecs), board_tvecs, 0.0)
    per, squares = [], []
    for c, cam in enumerate(cameras):
        e = []
        for f in np.flatnonzero(np.asarray(observed[c]).any(-1)):
            Rc, tc = compose(cam.R, cam.tvec, R0b[f], t0b[f])
            pts = observed[c, f]
            uv = project_points(obj[pts], cam.intrinsics, cam.dist, matrix_to_rodrigues(Rc), tc,
                                cam.model)
            e.append(np.sum((uv - image_points[c, f, pts]) ** 2, axis=-1))
        e = np.concatenate(e) if e else np.zeros(0)
        squares.append(e)
        per.append(np.sqrt(np.mean(e)) if len(e) else np.nan)
    return float(np.sqrt(np.mean(np.concatenate(squares)))), np.array(per)


@dataclass(frozen=True, eq=False)
class RigStart:
    """Where a rig's bundle adjustment starts (``rig_start``).

    R, t (C, 3, 3), (C, 3): cam_from_cam0 from ``initial_rig``; board_rvecs, board_tvecs (F, 3):
    cam0_from_board through the lowest-numbered camera that sees each frame (NaN for frames no
    camera sees); seen (C, F) bool; log: ``initial_rig``'s per-camera log.
    """

    R: np.ndarray
    t: np.ndarray
    board_rvecs: np.ndarray
    board_tvecs: np.ndarray
    seen: np.ndarray
    log: list[dict]


def rig_cameras(cameras: Sequence[Camera]) -> list[Camera]:
    """The cameras of a rig calibration as a list, refused (ValueError naming the entry) unless
    there are two or more stereo_bench Cameras."""
    cameras = list(cameras)
    if len(cameras) < 2:
        raise ValueError(f"cameras: expected at least 2 cameras, got {len(cameras)}")
    for c, cam in enumerate(cameras):
        if not isinstance(cam, Camera):
            raise ValueError(f"cameras[{c}]: expected a stereo_bench Camera, got "
                             f"{type(cam).__name__}")
    return cameras


def rig_start(cameras: Sequence[Camera], image_points, board_rvecs, board_tvecs,
              found=None) -> RigStart:
    """The start of a rig calibration from each camera's own board poses (module notes, 1).

    image_points (C, F, N, 2) px, NaN where a point was not detected; board_rvecs, board_tvecs
    (C, F, 3) each camera's own cam_from_board, NaN where not found; found (C, F) bool, optional
    (default: finite pose). A camera sees a frame if found, its pose is finite and it detected
    at least MIN_POINTS_PER_VIEW points. Shared by ``calibrate_rig`` and the pycolmap reference
    (colmap_ref.py), so that both solvers start from the same values.
    """
    cameras = rig_cameras(cameras)
    C = len(cameras)
    img = np.asarray(image_points, dtype=np.float64)
    rv, tv = np.asarray(board_rvecs, dtype=np.float64), np.asarray(board_tvecs, dtype=np.float64)
    if img.ndim != 4 or img.shape[0] != C or img.shape[-1] != 2:
        raise ValueError(f"image_points: expected shape (C={C}, F, N, 2), got {img.shape}")
    F = img.shape[1]
    for name, a in (("board_rvecs", rv), ("board_tvecs", tv)):
        if a.shape != (C, F, 3):
            raise ValueError(f"{name}: expected shape {(C, F, 3)}, got {a.shape}")
    found = np.ones((C, F), bool) if found is None else np.asarray(found, dtype=bool)
    if found.shape != (C, F):
        raise ValueError(f"found: expected shape {(C, F)}, got {found.shape}")
    detected = np.all(np.isfinite(img), axis=-1)  # (C, F, N)
    seen = (found & np.all(np.isfinite(rv), -1) & np.all(np.isfinite(tv), -1)
            & (detected.sum(-1) >= MIN_POINTS_PER_VIEW))
    board_R = rodrigues_to_matrix(np.where(seen[..., None], rv, 0.0))
    R, t, log = initial_rig(board_R, np.where(seen[..., None], tv, 0.0), seen,
                            [cam.name for cam in cameras])
    frames = np.flatnonzero(seen.any(axis=0))
    first = np.argmax(seen[:, frames], axis=0)
    R0c, t0c = invert(R[first], t[first])
    rv0, tv0 = np.full((F, 3), np.nan), np.full((F, 3), np.nan)
    rv0[frames] = matrix_to_rodrigues(R0c @ board_R[first, frames])
    tv0[frames] = np.einsum("fij,fj->fi", R0c, tv[first, frames]) + t0c
    return RigStart(R, t, rv0, tv0, seen, log)


def calibrate_rig(
    cameras: Sequence[Camera],
    object_points,
    image_points,
    board_rvecs,
    board_tvecs,
    found=None,
    tolerance: float = 1e-12,
    refine_intrinsics: Sequence[Sequence[str] | None] | None = None,
    loss: str = "linear",
    loss_scale_px: float = 1.0,
    board=None,
) -> RigCalibration:
    """Calibrate the relative poses of a rig; see the module notes.

    cameras: C >= 2 intrinsic estimates. object_points (N, 3) mm. image_points (C, F, N, 2) px,
    NaN where a point was not detected. board_rvecs, board_tvecs (C, F, 3): each camera's own
    cam_from_board, NaN where not found. found (C, F) bool, optional (default: finite pose).
    A camera sees a frame if found, its pose is finite and it detected at least
    MIN_POINTS_PER_VIEW points. ``tolerance`` is least_squares' ftol, xtol and gtol.
    refine_intrinsics: per camera the names (of model_parameters(camera)) to adjust with the rig, or
    None to keep that camera's intrinsics; None for all: intrinsics fixed. ``loss`` and
    ``loss_scale_px``: least_squares' robust loss and f_scale. ``board``: a BoardShape whose
    shape (warp and aspect error, its FIT_NAMES) joins the adjustment, starting at its own, with
    ``object_points`` the nominal ones; the result's log gives the fitted ``board_shape``.
    """
    t0 = time.perf_counter()
    C = len(cameras)
    obj = np.asarray(object_points, dtype=np.float64)
    if obj.ndim != 2 or obj.shape[1] != 3:
        raise ValueError(f"object_points: expected shape (N, 3), got {obj.shape}")
    start = rig_start(cameras, image_points, board_rvecs, board_tvecs, found)
    img = np.asarray(image_points, dtype=np.float64)
    if img.shape[2] != len(obj):
        raise ValueError(f"image_points: expected N={len(obj)} points per frame (object_points),"
                         f" got {img.shape[2]}")
    seen, names = start.seen, [cam.name for cam in cameras]
    parameters = [model_parameters(cam) for cam in cameras]
    free = [np.zeros(len(n), bool) if not refine_intrinsics or not p else np.isin(n, list(p))
            for n, p in zip(parameters, refine_intrinsics or [None] * C)]
    if refine_intrinsics is not None and len(refine_intrinsics) != C:
        raise ValueError(f"refine_intrinsics: expected one entry per camera ({C}), got "
                         f"{len(refine_intrinsics)}")
    for p, n in zip(refine_intrinsics or [], parameters):
        unknown = set(p or []) - set(n)
        if unknown:
            raise ValueError(f"refine_intrinsics: unknown parameters {sorted(unknown)}; "
                             f"expected some of {n}")

    # A frame one camera saw constrains only that camera's intrinsics (and its own pose).
    used = seen.sum(axis=0) >= (1 if any(m.any() for m in free) else 2)
    frames = np.flatnonzero(used)
    R, t = start.R, start.t
    R0b, t0b = start.board_rvecs[frames], start.board_tvecs[frames]
    detected = np.all(np.isfinite(img), axis=-1)  # (C, F, N)
    F = img.shape[1]
    valid = detected[:, frames] & seen[:, frames, None]
    problem = _RigProblem(cameras, obj, img[:, frames], valid, free, board)
    x0 = np.concatenate([np.hstack([matrix_to_rodrigues(R[1:]), t[1:]]).ravel(),
                         problem.initial_intrinsics(),
                         [] if board is None else board.fit_params,
                         np.hstack([R0b, t0b]).ravel()])
    rms0, _ = problem.rms(x0)
    # One BLAS thread: LSMR's many small products stall when threaded (2.5x slower measured
    # on an 8-camera studio with 2 cores).
    with threadpool_limits(1, user_api="blas"):
        sol = least_squares(lambda x: problem.evaluate(x, False), x0,
                            jac=lambda x: problem.evaluate(x, True), method="trf",
                            x_scale="jac", ftol=tolerance, xtol=tolerance, gtol=tolerance,
                            loss=loss, f_scale=loss_scale_px,
                            # Tight inner LSMR solves: with its default 1e-6 a noisy 3-camera
                            # rig took 61 inexact steps instead of 5.
                            tr_options={"atol": 1e-10, "btol": 1e-10})
    rms, rms_per = problem.rms(sol.x)
    rig, params, boards = problem.unpack(sol.x)
    board_rvecs_out, board_tvecs_out = np.full((F, 3), np.nan), np.full((F, 3), np.nan)
    board_rvecs_out[frames], board_tvecs_out[frames] = boards[:, :3], boards[:, 3:]
    return RigCalibration(
        cameras=[cam.with_params(**{n: float(v) for n, v in zip(INTRINSIC_NAMES, params[c][:5])},
                                 dist=params[c][5:], rvec=rig[c, :3], tvec=rig[c, 3:])
                 for c, cam in enumerate(cameras)],
        board_rvecs=board_rvecs_out, board_tvecs=board_tvecs_out, frames_used=used,
        rms_px=rms, rms_px_per_camera=rms_per, iterations=int(sol.njev),
        time_s=time.perf_counter() - t0,
        log={"initial_rms_px": rms0, "nfev": int(sol.nfev), "status": int(sol.status),
             "message": sol.message, "n_observations": int(valid.sum()), "loss": loss,
             "loss_scale_px": loss_scale_px,
             "refined_intrinsics": {n: [p for p, f in zip(ps, m) if f]
                                    for n, ps, m in zip(names, parameters, free) if m.any()},
             "covisibility": covisibility(seen),
             "initialization": start.log,
             **({} if board is None else {"board_shape": dict(zip(
                 board.FIT_NAMES, problem.board_shape(sol.x).tolist()))})})


# ----------------------------------------------------------------------------------------------
# Comparison with a true rig
# ----------------------------------------------------------------------------------------------


def _centres(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Camera centres (C, 3) in the reference frame from cam_from_cam0 (R (C,3,3), t (C,3))."""
    return -np.einsum("cji,cj->ci", R, t)


def rig_errors(estimated: Sequence[Camera], truth: Sequence[Camera]) -> dict[str, np.ndarray]:
    """Per camera (C,), the estimated cam_from_cam0 against the true one (both from cam_from_world).

    rotation_deg: angle of R_est R_true^T; translation_mm: |t_est - t_true|; baseline_mm: signed
    |t_est| - |t_true|, the error of the distance between the camera's centre and camera 0's;
    centre_mm: the distance between the estimated and the true camera centre, both in the
    reference camera's frame. Camera 0 scores 0 by construction.
    """
    if len(estimated) != len(truth):
        raise ValueError(f"rig_errors: {len(estimated)} estimated and {len(truth)} true cameras")
    Re, te = cam_from_cam0(estimated)
    Rt, tt = cam_from_cam0(truth)
    centre_e, centre_t = _centres(Re, te), _centres(Rt, tt)
    return {"rotation_deg": np.degrees(geodesic_distance(Rt, Re)),
            "translation_mm": np.linalg.norm(te - tt, axis=-1),
            "baseline_mm": np.linalg.norm(te, axis=-1) - np.linalg.norm(tt, axis=-1),
            "centre_mm": np.linalg.norm(centre_e - centre_t, axis=-1)}


def similarity_transform(src: np.ndarray, dst: np.ndarray, scale: bool = True
                         ) -> tuple[float, np.ndarray, np.ndarray]:
    """(s, R, t) minimizing sum |s R src_i + t - dst_i|^2 over points (K, 3), K >= 3 not on a
    line (Umeyama, "Least-squares estimation of transformation parameters between two point
    patterns", PAMI 1991, eq. 40-42); ``scale=False``: the rigid motion (s = 1), whose
    rotation is the same."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    var = np.mean(np.sum(a * a, axis=1))
    U, D, Vt = np.linalg.svd(b.T @ a / len(src))
    if len(src) < 3 or D[1] <= 1e-9 * D[0]:
        raise ValueError("similarity_transform: expected at least 3 points not on a line")
    S = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ S @ Vt
    s = float(np.trace(np.diag(D) @ S) / var) if scale else 1.0
    return s, R, mu_d - s * R @ mu_s


def aligned_rig_errors(estimated: Sequence[Camera], truth: Sequence[Camera]) -> dict:
    """Per camera, the rig's errors after the similarity that best maps the estimated camera
    centres onto the true ones (both in their reference camera's frame): what is left of a
    geometry once its choice of reference camera and its scale are forgiven. rotation_deg,
    centre_mm (C,), and the alignment's ``scale``. Needs 3 cameras whose centres are not on a
    line (ValueError otherwise)."""
    Re, te = cam_from_cam0(estimated)
    Rt, tt = cam_from_cam0(truth)
    centre_e, centre_t = _centres(Re, te), _centres(Rt, tt)
    s, R, t = similarity_transform(centre_e, centre_t)
    # The aligned camera maps true-frame points by cam_from_ref_est o (ref_est_from_ref_true).
    return {"rotation_deg": np.degrees(geodesic_distance(Rt, Re @ R.T)),
            "centre_mm": np.linalg.norm(s * centre_e @ R.T + t - centre_t, axis=-1),
            "scale": s}
