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
2. Joint refinement over all frames seen by two or more cameras (a frame seen by one camera says
   nothing about the rig once intrinsics are fixed): one cam0_from_board pose per frame, one
   cam_from_cam0 per camera (camera 0's is the identity), intrinsics fixed, residuals = pixel
   reprojection errors through ``camera.project_with_jacobians``. The Jacobian is analytic and
   sparse (a frame pose touches only that frame's residuals) and goes to scipy's
   ``least_squares`` ('trf', x_scale='jac'). This is the cost cv2.stereoCalibrate minimizes with
   CALIB_FIX_INTRINSIC, for any number of cameras.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
import scipy.sparse
from scipy.optimize import least_squares

from .calibrate.base import MIN_POINTS_PER_VIEW
from .camera import (Camera, compose, geodesic_distance, invert, matrix_to_rodrigues,
                     nearest_rotation, project_with_jacobians, rodrigues_to_matrix,
                     rotate_jacobian)

MIN_OUTLIER_DEG = 0.1  # rotation-averaging inlier radius never goes below this


@dataclass(frozen=True, eq=False)
class RigCalibration:
    """A calibrated rig; the world frame is camera 0's.

    cameras: the input intrinsics with cam_from_world = cam_from_cam0.
    board_rvecs, board_tvecs: (F, 3) cam0_from_board per frame; NaN for frames not used.
    frames_used: (F,) bool, the frames seen by two or more cameras.
    rms_px: RMS reprojection error (px per point) over all observations; rms_px_per_camera (C,).
    iterations: Jacobian evaluations of the solver; time_s: wall time of the whole calibration.
    log: initial_rms_px, nfev, status and message of the solver, n_observations, and
    "initialization": per camera its name, the camera it was chained from ("parent"), the frames
    they share and the frames kept by the rotation average.
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
    shared = (seen[:, None, :] & seen[None, :, :]).sum(axis=-1)
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

class _RigProblem:
    """Residuals and sparse Jacobian of the rig's reprojection errors.

    x = [cam_from_cam0 (rvec, tvec) of cameras 1..C-1, cam0_from_board of each used frame].
    Residuals are ordered camera by camera, observation by observation, (u, v).
    """

    def __init__(self, cameras, object_points, image_points, valid):
        self.cameras, self.obj = cameras, object_points
        self.C, self.F = len(cameras), valid.shape[1]
        self.n_rig = 6 * (self.C - 1)
        self.valid = valid  # (C, F, N)
        self.obs = [image_points[c][valid[c]] for c in range(self.C)]
        rows, cols, self.offsets = [], [], [0]
        for c in range(self.C):
            f = np.nonzero(valid[c])[0]
            k = len(f)
            blocks = [self.n_rig + 6 * f[:, None] + np.arange(6)]  # (K, 6) board columns
            if c > 0:
                blocks.insert(0, np.broadcast_to(6 * (c - 1) + np.arange(6), (k, 6)))
            cb = np.concatenate(blocks, axis=1)  # (K, ncol)
            r = self.offsets[-1] + 2 * np.arange(k)[:, None] + np.arange(2)  # (K, 2)
            rows.append(np.broadcast_to(r[:, :, None], (k, 2, cb.shape[1])).ravel())
            cols.append(np.broadcast_to(cb[:, None, :], (k, 2, cb.shape[1])).ravel())
            self.offsets.append(self.offsets[-1] + 2 * k)
        self.rows, self.cols = np.concatenate(rows), np.concatenate(cols)
        self.shape = (self.offsets[-1], self.n_rig + 6 * self.F)

    def unpack(self, x):
        rig = np.vstack([np.zeros(6), x[: self.n_rig].reshape(-1, 6)])
        return rig, x[self.n_rig:].reshape(-1, 6)

    def evaluate(self, x, jacobian: bool):
        rig, boards = self.unpack(x)
        Y = (np.einsum("fij,nj->fni", rodrigues_to_matrix(boards[:, :3]), self.obj)
             + boards[:, None, 3:])  # board points in camera 0's frame (F, N, 3)
        if jacobian:  # d Y / d (rvec, tvec) of cam0_from_board, (F, N, 3, 6)
            dY = np.concatenate([np.stack([rotate_jacobian(b[:3], self.obj) for b in boards]),
                                 np.broadcast_to(np.eye(3), Y.shape + (3,))], axis=-1)
        res, data = [], []
        for c, cam in enumerate(self.cameras):
            uv, J = project_with_jacobians(Y[self.valid[c]], cam.intrinsics, cam.dist,
                                           rig[c, :3], rig[c, 3:], jacobians=jacobian)
            res.append((uv - self.obs[c]).ravel())
            if jacobian:
                Jb = J["point"] @ dY[self.valid[c]]
                data.append((np.concatenate([J["pose"], Jb], -1) if c > 0 else Jb).ravel())
        r = np.concatenate(res)
        if not jacobian:
            return r
        return scipy.sparse.csr_matrix((np.concatenate(data), (self.rows, self.cols)),
                                       shape=self.shape)

    def rms(self, x) -> tuple[float, np.ndarray]:
        r = self.evaluate(x, False)
        per = [np.sqrt(np.mean(r[a:b] ** 2) * 2) for a, b in zip(self.offsets, self.offsets[1:])]
        return float(np.sqrt(np.mean(r**2) * 2)), np.array(per)


def calibrate_rig(
    cameras: Sequence[Camera],
    object_points,
    image_points,
    board_rvecs,
    board_tvecs,
    found=None,
    tolerance: float = 1e-12,
) -> RigCalibration:
    """Calibrate the relative poses of a rig; see the module notes.

    cameras: C >= 2 intrinsic estimates. object_points (N, 3) mm. image_points (C, F, N, 2) px,
    NaN where a point was not detected. board_rvecs, board_tvecs (C, F, 3): each camera's own
    cam_from_board, NaN where not found. found (C, F) bool, optional (default: finite pose).
    A camera sees a frame if found, its pose is finite and it detected at least
    MIN_POINTS_PER_VIEW points. ``tolerance`` is least_squares' ftol, xtol and gtol.
    """
    t0 = time.perf_counter()
    C = len(cameras)
    obj = np.asarray(object_points, dtype=np.float64)
    img = np.asarray(image_points, dtype=np.float64)
    rv, tv = np.asarray(board_rvecs, dtype=np.float64), np.asarray(board_tvecs, dtype=np.float64)
    if C < 2:
        raise ValueError(f"rig calibration: expected at least 2 cameras, got {C}")
    if obj.ndim != 2 or obj.shape[1] != 3:
        raise ValueError(f"object_points: expected shape (N, 3), got {obj.shape}")
    F, N = img.shape[1:3] if img.ndim == 4 else (None, None)
    if img.shape != (C, F, N, 2) or N != len(obj):
        raise ValueError(f"image_points: expected shape (C={C}, F, N={len(obj)}, 2), got "
                         f"{img.shape}")
    for name, a in (("board_rvecs", rv), ("board_tvecs", tv)):
        if a.shape != (C, F, 3):
            raise ValueError(f"{name}: expected shape {(C, F, 3)}, got {a.shape}")
    found = np.ones((C, F), bool) if found is None else np.asarray(found, dtype=bool)
    if found.shape != (C, F):
        raise ValueError(f"found: expected shape {(C, F)}, got {found.shape}")
    detected = np.all(np.isfinite(img), axis=-1)  # (C, F, N)
    seen = (found & np.all(np.isfinite(rv), -1) & np.all(np.isfinite(tv), -1)
            & (detected.sum(-1) >= MIN_POINTS_PER_VIEW))
    names = [cam.name for cam in cameras]

    board_R = rodrigues_to_matrix(np.where(seen[..., None], rv, 0.0))
    R, t, init_log = initial_rig(board_R, np.where(seen[..., None], tv, 0.0), seen, names)

    used = seen.sum(axis=0) >= 2
    frames = np.flatnonzero(used)
    # Initial cam0_from_board: through the lowest-numbered camera that sees the frame.
    first = np.argmax(seen[:, frames], axis=0)
    R0c, t0c = invert(R[first], t[first])
    R0b = R0c @ board_R[first, frames]
    t0b = np.einsum("fij,fj->fi", R0c, tv[first, frames]) + t0c
    x0 = np.concatenate([np.hstack([matrix_to_rodrigues(R[1:]), t[1:]]).ravel(),
                         np.hstack([matrix_to_rodrigues(R0b), t0b]).ravel()])

    valid = detected[:, frames] & seen[:, frames, None]
    problem = _RigProblem(cameras, obj, img[:, frames], valid)
    rms0, _ = problem.rms(x0)
    sol = least_squares(lambda x: problem.evaluate(x, False), x0,
                        jac=lambda x: problem.evaluate(x, True), method="trf", x_scale="jac",
                        ftol=tolerance, xtol=tolerance, gtol=tolerance,
                        # Tight inner LSMR solves: with its default 1e-6 a noisy 3-camera rig
                        # took 61 inexact steps instead of 5.
                        tr_options={"atol": 1e-10, "btol": 1e-10})
    rms, rms_per = problem.rms(sol.x)
    rig, boards = problem.unpack(sol.x)
    board_rvecs_out, board_tvecs_out = np.full((F, 3), np.nan), np.full((F, 3), np.nan)
    board_rvecs_out[frames], board_tvecs_out[frames] = boards[:, :3], boards[:, 3:]
    return RigCalibration(
        cameras=[cam.with_params(rvec=rig[c, :3], tvec=rig[c, 3:])
                 for c, cam in enumerate(cameras)],
        board_rvecs=board_rvecs_out, board_tvecs=board_tvecs_out, frames_used=used,
        rms_px=rms, rms_px_per_camera=rms_per, iterations=int(sol.njev),
        time_s=time.perf_counter() - t0,
        log={"initial_rms_px": rms0, "nfev": int(sol.nfev), "status": int(sol.status),
             "message": sol.message, "n_observations": int(valid.sum()),
             "initialization": init_log})


# ----------------------------------------------------------------------------------------------
# Comparison with a true rig
# ----------------------------------------------------------------------------------------------

def cam_from_cam0(cameras: Sequence[Camera]) -> tuple[np.ndarray, np.ndarray]:
    """Each camera's pose relative to the first, from their cam_from_world: (R (C,3,3), t (C,3))."""
    R = np.stack([cam.R for cam in cameras])
    t = np.stack([cam.tvec for cam in cameras])
    return compose(R, t, *invert(R[0], t[0]))


def rig_errors(estimated: Sequence[Camera], truth: Sequence[Camera]) -> dict[str, np.ndarray]:
    """Per camera (C,), the estimated cam_from_cam0 against the true one (both from cam_from_world).

    rotation_deg: angle of R_est R_true^T; translation_mm: |t_est - t_true|; baseline_mm: signed
    |t_est| - |t_true|, the error of the distance between the camera's centre and camera 0's.
    Camera 0 scores 0 by construction.
    """
    if len(estimated) != len(truth):
        raise ValueError(f"rig_errors: {len(estimated)} estimated and {len(truth)} true cameras")
    Re, te = cam_from_cam0(estimated)
    Rt, tt = cam_from_cam0(truth)
    return {"rotation_deg": np.degrees(geodesic_distance(Rt, Re)),
            "translation_mm": np.linalg.norm(te - tt, axis=-1),
            "baseline_mm": np.linalg.norm(te, axis=-1) - np.linalg.norm(tt, axis=-1)}
