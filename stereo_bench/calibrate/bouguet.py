"""Bouguet's Camera Calibration Toolbox for Matlab (Caltech), as its calibration runs by default.

J.-Y. Bouguet, "Camera Calibration Toolbox for Matlab", 2004; its model and main optimization
follow J. Heikkila and O. Silven, "A four-step camera calibration procedure with implicit image
correction", CVPR 1997. The steps are the toolbox's scripts:

1. ``init_intrinsic_param``: principal point cc at the image centre, skew alpha_c = 0, kc = 0, and
   one focal length fc from the orthogonality of vanishing points: with the principal point
   subtracted, columns h1, h2 of each homography (the board's two axes) and (h1 +- h2) / 2 (its
   diagonals) are pairs of orthogonal directions, so a_i a_j / f^2 + b_i b_j / f^2 + c_i c_j = 0;
   1 / f^2 is the least-squares solution over all views (``two_focals_init = 0``: fx = fy).
2. ``compute_extrinsic_init``: per view, the homography from the board to normalized image
   coordinates, scaled by the mean norm of its first two columns, rotation by Gram-Schmidt.
3. ``compute_extrinsic_refine``: per view pose refinement with the intrinsics fixed.
4. The main optimization of fc, cc, alpha_c, kc = (k1, k2, p1, p2, k3) and all extrinsics, with the
   toolbox defaults est_dist = [1 1 1 1 0] (k3 fixed at 0) and est_alpha = 0 (no skew).

Steps 3-4 run through the shared ``refine.py`` (Levenberg-Marquardt) instead of the toolbox's
damped Gauss-Newton; both minimize the same reprojection error, so they share the minimum.
"""

from __future__ import annotations

import time

import numpy as np

from ..camera import matrix_to_rodrigues
from .base import CalibrationResult, Observations
from .homography import apply_homography, fit_homography
from .refine import OpenCVModel, free_mask, refine

KC_NAMES = ("k1", "k2", "p1", "p2", "k3")


def init_focal(Hs: list[np.ndarray], cc: np.ndarray, two_focals: bool = False) -> np.ndarray:
    """(fx, fy) from the vanishing points of each board's axes and diagonals (init_intrinsic_param)."""
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


def extrinsic_init(K: np.ndarray, board_xy: np.ndarray, image_xy: np.ndarray):
    """cam_from_board (rvec, tvec) from the normalized-coordinate homography (compute_extrinsic_init)."""
    normalized = apply_homography(np.linalg.inv(K), image_xy)
    H = fit_homography(board_xy, normalized)
    H = H / np.mean(np.linalg.norm(H[:, :2], axis=0))
    if H[2, 2] < 0:  # the board must lie in front of the camera
        H = -H
    u1 = H[:, 0] / np.linalg.norm(H[:, 0])
    u2 = H[:, 1] - (u1 @ H[:, 1]) * u1
    u2 /= np.linalg.norm(u2)
    R = np.column_stack([u1, u2, np.cross(u1, u2)])
    return matrix_to_rodrigues(R), H[:, 2]


class BouguetCalibrator:
    name = "bouguet"

    def __init__(self, est_dist=(True, True, True, True, False), est_alpha: bool = False,
                 two_focals_init: bool = False, max_iter: int = 100):
        if len(est_dist) != 5:
            raise ValueError(f"bouguet: est_dist needs 5 flags for {KC_NAMES}, got {est_dist}")
        self.est_dist = tuple(bool(e) for e in est_dist)
        self.est_alpha = est_alpha
        self.two_focals_init = two_focals_init
        self.max_iter = max_iter

    def calibrate(self, obs: Observations) -> CalibrationResult:
        t0 = time.perf_counter()
        w, h = obs.image_size
        cc = np.array([w / 2 - 0.5, h / 2 - 0.5])  # the toolbox's centre, in 0-based pixel centres
        Hs = [fit_homography(o[:, :2], p) for o, p in zip(obs.object_points, obs.image_points)]
        fc = init_focal(Hs, cc, self.two_focals_init)
        K = np.array([[fc[0], 0.0, cc[0]], [0.0, fc[1], cc[1]], [0.0, 0.0, 1.0]])
        poses = [extrinsic_init(K, o[:, :2], p)
                 for o, p in zip(obs.object_points, obs.image_points)]

        model = OpenCVModel()
        params0 = np.concatenate([[fc[0], fc[1], cc[0], cc[1], 0.0], np.zeros(8)])
        args = (obs.object_points, obs.image_points)
        poses = refine(model, params0, np.zeros(len(params0), bool), *args,
                       np.array([p[0] for p in poses]), np.array([p[1] for p in poses]),
                       max_iter=20)
        free = (["fx", "fy", "cx", "cy"] + (["skew"] if self.est_alpha else [])
                + [n for n, e in zip(KC_NAMES, self.est_dist) if e])
        res = refine(model, params0, free_mask(model.param_names, free), *args,
                     poses.rvecs, poses.tvecs, max_iter=self.max_iter)
        log = {"method": self.name, "est_dist": list(self.est_dist), "est_alpha": self.est_alpha,
               "init": {"fc": fc.tolist(), "cc": cc.tolist()},
               **res.log(), "time_s": time.perf_counter() - t0,
               "notes": "Bouguet toolbox defaults: init_intrinsic_param, compute_extrinsic_init/"
                        "refine, main optimization through refine.py"}
        return CalibrationResult(model.camera(res.params, obs.camera_name, obs.image_size),
                                 res.rvecs, res.tvecs, log)
