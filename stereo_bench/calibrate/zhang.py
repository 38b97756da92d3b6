"""Zhang's calibration from views of a plane.

Z. Zhang, "A flexible new technique for camera calibration", IEEE PAMI 22(11), 2000:

1. a homography per view (Appendix A; ``homography.py``);
2. closed-form intrinsics: each H = [h1 h2 h3] gives two linear constraints on the symmetric
   B = K^-T K^-1, v12^T b = 0 and (v11 - v22)^T b = 0 (eq. 8-9); b is the null vector of the
   stacked V (Appendix B gives K from b);
3. extrinsics from K^-1 H (section 3.1), the rotation made orthogonal by SVD (Appendix C);
4. radial k1, k2 by linear least squares on the residual pixels (section 3.3, eq. 13);
5. maximum-likelihood refinement of all parameters and poses (eq. 14) through ``refine.py``,
   with Zhang's model: CameraModel with only fx, fy, cx, cy, skew, k1, k2 free (``zhang``), or
   with another lens model's coefficients free instead of k1, k2 (``zhang-brown`` etc.).
   A fisheye or omnidirectional model (``zhang-fisheye``, ``zhang-omnidir``,
   ``zhang-doublesphere``) replaces steps 1-4, which hold for a pinhole lens only, by the start
   of that model's paper (wide_angle.py); step 5 is the same.

Skew gamma is estimated by default, as in the paper; ``zero_skew=True`` imposes gamma = 0 with
Zhang's extra constraint B12 = 0 (section 3.1) and keeps it fixed in the refinement. Estimating
a skew that is truly zero costs a little precision (one more parameter) but no bias, so the
default measures the published algorithm.
"""

from __future__ import annotations

import time

import numpy as np

from ..core.board_shape import BoardShape
from ..core.camera import Camera, project_points
from ..core.poses import rodrigues_to_matrix
from .base import CalibrationResult, Observations
from .homography import extrinsics_from_homography, fit_homographies
from .lens_models import LENS_MODELS, core_lens, free_coefficients, method_name
from .refine import CameraModel, free_mask, refine
from .wide_angle import wide_angle_start


def _v(H: np.ndarray, i: int, j: int) -> np.ndarray:
    """Zhang's v_ij (eq. 8) from columns i, j of H (..., 3, 3) -> (..., 6)."""
    a, b = np.moveaxis(H[..., :, i], -1, 0), np.moveaxis(H[..., :, j], -1, 0)
    return np.stack([a[0] * b[0], a[0] * b[1] + a[1] * b[0], a[1] * b[1],
                     a[2] * b[0] + a[0] * b[2], a[2] * b[1] + a[1] * b[2], a[2] * b[2]], -1)


def intrinsics_from_homographies(Hs: np.ndarray, image_size, zero_skew: bool) -> np.ndarray:
    """Closed-form K (3, 3) from three or more plane homographies (two with zero skew).

    The homographies are first expressed in pixel units scaled by the image size and centred,
    a similarity N that keeps K upper triangular (K' = N K): in raw pixels the entries of b span
    ~12 orders of magnitude for a 4096 px camera and the SVD loses digits to that alone.
    """
    w, h = image_size
    s = 2.0 / (w + h)
    N = np.array([[s, 0.0, -s * w / 2], [0.0, s, -s * h / 2], [0.0, 0.0, 1.0]])
    NH = N @ np.asarray(Hs, dtype=np.float64).reshape(-1, 3, 3)
    V = np.stack([_v(NH, 0, 1), _v(NH, 0, 0) - _v(NH, 1, 1)], 1).reshape(-1, 6)
    cols = [0, 2, 3, 4, 5] if zero_skew else list(range(6))  # gamma = 0 <=> B12 = 0
    needed = len(cols) - 1
    if len(V) < needed:
        raise ValueError(f"Zhang: {len(Hs)} views give {len(V)} constraints on B; at least "
                         f"{needed} are needed ({(needed + 1) // 2} views)")
    b = np.zeros(6)
    b[cols] = np.linalg.svd(V[:, cols])[2][-1]
    if b[0] < 0:  # B = lambda K^-T K^-1 is positive definite for lambda > 0
        b = -b
    B11, B12, B22, B13, B23, B33 = b
    # Appendix B.
    den = B11 * B22 - B12 * B12
    v0 = (B12 * B13 - B11 * B23) / den
    lam = B33 - (B13 * B13 + v0 * (B12 * B13 - B11 * B23)) / B11
    if not (den > 0 and lam / B11 > 0):
        raise ValueError("Zhang: the views do not determine the intrinsics (degenerate "
                         "configuration, e.g. all boards parallel)")
    alpha = np.sqrt(lam / B11)
    beta = np.sqrt(lam * B11 / den)
    gamma = -B12 * alpha * alpha * beta / lam
    u0 = gamma * v0 / beta - B13 * alpha * alpha / lam
    K_scaled = np.array([[alpha, gamma, u0], [0.0, beta, v0], [0.0, 0.0, 1.0]])
    return np.linalg.solve(N, K_scaled)


def radial_from_linear(K, rvecs, tvecs, obs: Observations) -> np.ndarray:
    """k1, k2 from eq. 13: (u_obs - u) = (u - u0) [r^2 r^4] k on ideal (undistorted) projections."""
    counts = [len(o) for o in obs.object_points]
    R = rodrigues_to_matrix(np.repeat(rvecs, counts, axis=0))
    p = (R @ np.concatenate(obs.object_points)[:, :, None])[:, :, 0] + np.repeat(tvecs, counts, 0)
    r2 = np.sum((p[:, :2] / p[:, 2:]) ** 2, axis=1)
    uv = project_points(p, [K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1]], np.zeros(8),
                        np.zeros(3), np.zeros(3))
    centred = uv - K[:2, 2]
    D = np.stack([centred * r2[:, None], centred * (r2 * r2)[:, None]], -1).reshape(-1, 2)
    return np.linalg.lstsq(D, (np.concatenate(obs.image_points) - uv).ravel(), rcond=None)[0]


class ZhangCalibrator:
    """Zhang's algorithm (module docstring). ``lens_model`` (lens_models.py; None: Zhang's k1, k2)
    chooses the coefficients free in step 5: the closed form and eq. 13 stay as published, and
    the coefficients they do not estimate (p1, p2, k3..k6) start the refinement at 0."""

    lens_models = tuple(LENS_MODELS)
    own_model = "Zhang's model (fx, fy, cx, cy, skew, k1, k2)"

    fits_board_warp = True

    def __init__(self, zero_skew: bool = False, max_iter: int = 100,
                 lens_model: str | None = None, board_warp: bool = False):
        """``board_warp``: also fit the board's warp in the refinement (refine.py)."""
        self.name = method_name("zhang", lens_model)
        self.board_warp = board_warp
        self.zero_skew = zero_skew
        self.max_iter = max_iter
        dist = free_coefficients("radial2" if lens_model is None else lens_model)
        self.model_parameters = ("fx", "fy", "cx", "cy", *dist) + (() if zero_skew else ("skew",))
        self.lens = core_lens(lens_model)

    def calibrate(self, obs: Observations) -> CalibrationResult:
        t0 = time.perf_counter()
        if self.lens != "opencv":
            # A wide lens maps no plane by a homography: its model's own start (wide_angle.py).
            initial, rvecs, tvecs, _ = wide_angle_start(obs, self.lens)
        else:
            Hs = fit_homographies([o[:, :2] for o in obs.object_points], obs.image_points)
            K = intrinsics_from_homographies(Hs, obs.image_size, self.zero_skew)
            rvecs, tvecs = extrinsics_from_homography(K, Hs)
            initial = Camera.from_K(obs.camera_name, *obs.image_size, K,
                                    radial_from_linear(K, rvecs, tvecs, obs))
        model = CameraModel(self.lens)
        res = refine(model, model.params_of(initial),
                     free_mask(model.param_names, self.model_parameters),
                     obs.object_points, obs.image_points, rvecs, tvecs, max_iter=self.max_iter,
                     board=(BoardShape.of_points(np.concatenate(obs.object_points))
                            if self.board_warp else None))
        log = {"method": self.name, "zero_skew": self.zero_skew,
               "free": list(self.model_parameters), "closed_form": initial.to_dict(),
               **res.log(), "time_s": time.perf_counter() - t0,
               "notes": "Zhang 2000: closed form (App. B), eq. 13 radial, ML refinement (eq. 14)"}
        return CalibrationResult(model.camera(res.params, obs.camera_name, obs.image_size),
                                 res.rvecs, res.tvecs, log)
