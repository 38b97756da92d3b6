"""Bouguet's Camera Calibration Toolbox for Matlab (Caltech), as its calibration runs by default.

J.-Y. Bouguet, "Camera Calibration Toolbox for Matlab", 2004; its model and main optimization
follow J. Heikkila and O. Silven, "A four-step camera calibration procedure with implicit image
correction", CVPR 1997. The steps are the toolbox's scripts:

1. ``init_intrinsic_param``: principal point cc at the image centre, skew alpha_c = 0, kc = 0, and
   one focal length fc from the orthogonality of vanishing points: with the principal point
   subtracted, columns h1, h2 of each homography (the board's two axes) and (h1 +- h2) / 2 (its
   diagonals) are pairs of orthogonal directions, so a_i a_j / f^2 + b_i b_j / f^2 + c_i c_j = 0;
   1 / f^2 is the least-squares solution over all views (``two_focals_init = 0``: fx = fy).
2. ``compute_extrinsic_init``: per view, the homography from the board to undistorted normalized
   image coordinates, scaled by the mean norm of its first two columns, rotation by Gram-Schmidt;
   then ``compute_extrinsic_refine``: that view's pose refined with the intrinsics fixed.
3. ``go_calib_optim_iter``, the main optimization of fc, cc, alpha_c, kc = (k1, k2, p1, p2, k3) and
   all extrinsics, with the toolbox defaults est_dist = [1 1 1 1 0] (k3 fixed at 0), est_alpha = 0
   (no skew) and recompute_extrinsic = 1.

Two departures, neither changing the minimum sought. The joint optimization is the shared
``refine.py`` (Levenberg-Marquardt to a tight tolerance) instead of the toolbox's 30 smoothed
Gauss-Newton steps. And recompute_extrinsic, which in the toolbox redoes step 2 for every view
after every joint step ("makes the region of convergence larger": a view whose initial pose fell
into the planar tilt ambiguity, as happens on the wide camera when the single-focal init is far
off, is pulled out of it by a fresh init from better intrinsics), is done here after each
converged joint optimization: a view takes its fresh pose if that reprojects better, and the joint
optimization reruns until no view improves. Redone after every step, it took 5-40 s on 30 views of
the wide camera (each single step gains little before the poses are reset) against ~1 s here.
"""

from __future__ import annotations

import time

import numpy as np

from ..core.board_shape import BoardShape
from ..core.poses import matrix_to_rodrigues
from ..core.distortion import undistort_normalized
from .base import CalibrationResult, Observations
from .homography import fit_homographies
from .lens_models import LENS_MODELS, core_lens, free_coefficients, method_name
from .refine import CameraModel, free_mask, refine
from .wide_angle import wide_angle_start

KC_NAMES = ("k1", "k2", "p1", "p2", "k3")
EST_DIST = (True, True, True, True, False)  # the toolbox's default: k3 fixed at 0


def init_focal(Hs: list[np.ndarray], cc: np.ndarray, two_focals: bool = False) -> np.ndarray:
    """(fx, fy) from vanishing points of the boards' axes and diagonals (init_intrinsic_param)."""
    sub_cc = np.array([[1.0, 0.0, -cc[0]], [0.0, 1.0, -cc[1]], [0.0, 0.0, 1.0]])
    A, b = [], []
    for H in Hs:
        H = sub_cc @ H
        pairs = [(H[:, 0], H[:, 1]), ((H[:, 0] + H[:, 1]) / 2, (H[:, 0] - H[:, 1]) / 2)]
        for p, q in pairs:
            p, q = p / np.linalg.norm(p), q / np.linalg.norm(q)
            A.append([p[0] * q[0], p[1] * q[1]])
            b.append(-p[2] * q[2])
    A, b = np.array(A), np.array(b)
    if two_focals:
        inv_f2 = np.linalg.lstsq(A, b, rcond=None)[0]
    else:
        s = A.sum(axis=1)
        inv_f2 = np.full(2, (s @ b) / (s @ s))
    return np.sqrt(np.abs(1.0 / inv_f2))


def extrinsic_init(camera, board_xy: list[np.ndarray], image_xy: list[np.ndarray]):
    """cam_from_board rvecs, tvecs (V, 3) of V views (board (N_i, 2) and pixels (N_i, 2) each)
    from their homographies to normalized coordinates (compute_extrinsic_init)."""
    if camera.model == "opencv":
        distorted = camera.pixels_to_distorted_normalized(np.concatenate(image_xy))
        normalized = undistort_normalized(distorted, camera.dist)[0]
    else:
        normalized = camera.undistorted(np.concatenate(image_xy))[0]
    H = fit_homographies(board_xy, np.split(normalized, np.cumsum([len(p) for p in image_xy])[:-1]))
    # H[2, 2] > 0 keeps the board in front
    H = H / np.mean(np.linalg.norm(H[:, :, :2], axis=1), axis=1)[:, None, None]
    u1 = H[:, :, 0] / np.linalg.norm(H[:, :, 0], axis=1, keepdims=True)
    u2 = H[:, :, 1] - np.sum(u1 * H[:, :, 1], axis=1, keepdims=True) * u1
    u2 /= np.linalg.norm(u2, axis=1, keepdims=True)
    R = np.stack([u1, u2, np.cross(u1, u2)], -1)
    return matrix_to_rodrigues(R), H[:, :, 2]


class BouguetCalibrator:
    """The toolbox's calibration (module docstring). The distortion it frees is either the
    toolbox's ``est_dist`` (5 flags over KC_NAMES; default k1, k2, p1, p2) or a ``lens_model``
    of lens_models.py (``bouguet-brown`` is the toolbox with est_dist = [1 1 1 1 1];
    ``bouguet-rational`` also frees k4..k6, which the toolbox's kc does not have). Every
    coefficient starts at 0, as in the toolbox, so the init does not depend on the model."""

    fits_board_warp = True
    lens_models = tuple(LENS_MODELS)
    own_model = "the toolbox's default model (k1, k2, p1, p2; k3 fixed at 0)"

    def __init__(self, est_dist=None, est_alpha: bool = False,
                 two_focals_init: bool = False, recompute_extrinsic: bool = True,
                 max_recompute: int = 10, max_iter: int = 100, lens_model: str | None = None,
                 board_warp: bool = False):
        if lens_model is not None:
            if est_dist is not None:
                raise ValueError(f"bouguet: est_dist {est_dist} and lens_model {lens_model!r} "
                                 f"both choose the distortion; give one of them")
            dist = free_coefficients(lens_model)
        else:
            est_dist = EST_DIST if est_dist is None else est_dist
            if len(est_dist) != 5:
                raise ValueError(f"bouguet: est_dist needs 5 flags for {KC_NAMES}, "
                                 f"got {est_dist}")
            dist = tuple(n for n, e in zip(KC_NAMES, est_dist) if e)
        self.name = method_name("bouguet", lens_model)
        self.board_warp = board_warp  # also fit the board's warp (refine.py)
        self.est_dist = tuple(n in dist for n in KC_NAMES)
        self.est_alpha = est_alpha
        self.two_focals_init = two_focals_init
        self.recompute_extrinsic = recompute_extrinsic
        self.max_recompute = max_recompute
        self.max_iter = max_iter
        self.model = CameraModel(core_lens(lens_model))
        free = ["fx", "fy", "cx", "cy"] + (["skew"] if est_alpha else []) + list(dist)
        self.free = free_mask(self.model.param_names, free)
        self.model_parameters = tuple(free)

    def _extrinsics(self, params, obs: Observations, board=None):
        """Every view's pose afresh: compute_extrinsic_init, then compute_extrinsic_refine (on
        the board as fitted so far: ``board``'s warp held)."""
        camera = self.model.camera(params, obs.camera_name, obs.image_size)
        rvecs, tvecs = extrinsic_init(camera, [o[:, :2] for o in obs.object_points],
                                      obs.image_points)
        # The toolbox's compute_extrinsic_refine: 20 iterations at most, relative change 1e-10.
        return refine(self.model, params, np.zeros(len(params), bool), obs.object_points,
                      obs.image_points, rvecs, tvecs, max_iter=20, xtol=1e-10, ftol=1e-10,
                      board=board, fit_warp=False)

    def calibrate(self, obs: Observations) -> CalibrationResult:
        t0 = time.perf_counter()
        w, h = obs.image_size
        cc = np.array([w / 2 - 0.5, h / 2 - 0.5])  # the toolbox's ((nx-1)/2, (ny-1)/2), 0-based
        if self.model.lens != "opencv":
            # init_intrinsic_param's vanishing points need a pinhole: the wide lens's own start.
            params = self.model.params_of(wide_angle_start(obs, self.model.lens)[0])
            fc = params[:2]
        else:
            Hs = fit_homographies([o[:, :2] for o in obs.object_points], obs.image_points)
            fc = init_focal(Hs, cc, self.two_focals_init)
            params = np.concatenate([fc, cc, np.zeros(9)])
        poses = self._extrinsics(params, obs)
        rvecs, tvecs = poses.rvecs, poses.tvecs
        counts = np.array([len(p) for p in obs.image_points])
        starts = np.cumsum(counts) - counts
        view_cost = lambda r: np.add.reduceat(np.sum(r * r, axis=1), starts)
        reinitialized = []
        board = (BoardShape.of_points(np.concatenate(obs.object_points)) if self.board_warp
                 else None)
        for _ in range(self.max_recompute + 1):
            res = refine(self.model, params, self.free, obs.object_points, obs.image_points,
                         rvecs, tvecs, max_iter=self.max_iter, board=board)
            if board is not None:
                board = board.with_fit(res.board)
            if not self.recompute_extrinsic:
                break
            fresh = self._extrinsics(res.params, obs, board)
            # Improvements below 1e-8 px^2 per point are floating-point noise, not a new basin.
            better = view_cost(fresh.residuals) + 1e-8 * counts < view_cost(res.residuals)
            if not np.any(better):
                break
            reinitialized.append([obs.view_ids[i] for i in np.flatnonzero(better)])
            params = res.params
            rvecs = np.where(better[:, None], fresh.rvecs, res.rvecs)
            tvecs = np.where(better[:, None], fresh.tvecs, res.tvecs)
        log = {"method": self.name, "est_dist": list(self.est_dist), "est_alpha": self.est_alpha,
               "free": list(self.model_parameters),
               "init": {"fc": fc.tolist(), "cc": cc.tolist()},
               "views_reinitialized": reinitialized,
               **res.log(), "time_s": time.perf_counter() - t0,
               "notes": "Bouguet toolbox defaults: init_intrinsic_param, compute_extrinsic_init/"
                        "refine, main optimization with recompute_extrinsic, via refine.py"}
        return CalibrationResult(self.model.camera(res.params, obs.camera_name, obs.image_size),
                                 res.rvecs, res.tvecs, log)
