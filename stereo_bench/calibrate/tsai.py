"""Tsai's camera calibration, coplanar case, extended to many views of a planar board.

R. Y. Tsai, "A versatile camera calibration technique for high-accuracy 3D machine vision
metrology using off-the-shelf TV cameras and lenses", IEEE J. Robotics and Automation RA-3(4),
1987, section III.D (coplanar set of points). Equation numbers below are the paper's.

Tsai's model, in pixel-sized sensor units (dx = dy = 1, so f is in pixels):

    (Xc, Yc, Zc) = R p_board + T                                    world -> camera    (1)
    Xu = f Xc / Zc,  Yu = f Yc / Zc                                 pinhole            (2)
    Xu = Xd (1 + kappa1 r_d^2),  Yu = Yd (1 + kappa1 r_d^2),  r_d^2 = Xd^2 + Yd^2      (3)
    u = sx Xd + Cx,  v = Yd + Cy                                    pixels             (4)

so fx = sx f and fy = f. The principal point (Cx, Cy) is held at the image centre, which in
OpenCV pixel centres (top-left pixel centre at (0, 0)) is ((w - 1) / 2, (h - 1) / 2).

Stages (the first per view, the others over all views):

1. Radial alignment constraint (RAC), eqs. (10)-(12) coplanar form: (Xd, Yd) is parallel to
   (Xc, Yc), which is independent of f, Tz and kappa1. One linear least-squares solve for
   [r1, r2, Tx, r4, r5] / Ty; |Ty| from the 2x2 block C (the paper's closed form); the sign of
   Ty from the point farthest from the centre; r3, r6 and the third row by orthonormality, the
   remaining sign by f > 0 (flip r3, r6, r7, r8 if f came out negative). sx is taken as given
   (1 unless the caller knows better): the RAC cannot determine sx for a plane, not even from
   many views, because every view adds one unknown (its Ty) for each constraint it adds.
2. f and Tz linearly from the y equations with kappa1 = 0 (eq. (15)); here f is shared and each
   view has its own Tz (eliminated in closed form, so one equation remains for f).
3. The paper's nonlinear stage over f, Tz and kappa1, in its multi-view form: f, sx and kappa1
   shared by all views, refined jointly with every 6-DOF pose by the shared bundle adjustment
   :func:`stereo_bench.calibrate.refine.refine` through :class:`TsaiModel`. Cx, Cy stay fixed
   unless asked (the coplanar method cannot estimate them).

Relation to OpenCV's distortion. Tsai maps distorted -> undistorted with one coefficient; OpenCV
maps undistorted normalized (x, y) -> distorted with a polynomial. Tsai's map is exactly radial
in OpenCV's normalized coordinates x = Xu / f, y = Yu / f (normalized by fx = sx f and fy = f
respectively), with radial factor rho = r_d / r_u, the root of r_u = r_d (1 + kappa1 r_d^2):
an algebraic function with no finite polynomial (or rational k1..k6) equivalent. Series inversion
in dimensionless K = kappa1 f^2 and normalized radius r gives

    rho = 1 - K r^2 + 3 K^2 r^4 - 12 K^3 r^6 + 55 K^4 r^8 - ...     (coefficients (3n)!/(n!(2n+1)!))

so k1 ~ -K, k2 ~ 3 K^2, k3 ~ -12 K^3. :func:`tsai_to_opencv` fits k1, k2, k3 instead by linear
least squares in pixels over a dense grid of the image (exact Tsai undistortion of each pixel)
and reports the conversion residual (max and RMS, px), which the calibration log carries.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..core.camera import Camera
from ..core.poses import matrix_to_rodrigues, nearest_rotation
from .base import CalibrationResult, Observations
from .refine import refine

PARAM_NAMES = ("f", "sx", "cx", "cy", "kappa1")


class TsaiUnreachableError(ValueError):
    """kappa1 < 0 and a point lies beyond the fold of r_u = r_d (1 + kappa1 r_d^2)."""


# ----------------------------------------------------------------------------------------------
# Tsai's distortion and the projection model
# ----------------------------------------------------------------------------------------------

def distortion_ratio(q: np.ndarray, kappa1: float, strict: bool = True, max_iter: int = 100):
    """rho = r_d / r_u for undistorted squared radii q = r_u^2 (sensor units, px^2).

    Solves rho + kappa1 q rho^3 = 1, i.e. eq. (3) with r_d = rho r_u, which stays regular at
    r_u = 0. Newton from rho = 1 converges monotonically on the increasing branch (the cubic is
    convex there for kappa1 > 0 and concave for kappa1 < 0, so iterates never cross the root).
    For kappa1 < 0, r_u(r_d) peaks at r_d^2 = -1 / (3 kappa1); points with kappa1 q <= -4/27
    have no root on that branch: :class:`TsaiUnreachableError` if ``strict``, else NaN.

    Returns (rho, d rho / d q, d rho / d kappa1), by implicit differentiation.
    """
    q = np.asarray(q, dtype=np.float64)
    kq = kappa1 * q
    bad = kq <= -4.0 / 27.0
    if strict and np.any(bad):
        raise TsaiUnreachableError(
            f"kappa1 = {kappa1:.6g} px^-2 folds Tsai's distortion at undistorted radius "
            f"{2.0 / 3.0 / np.sqrt(-3.0 * kappa1):.6g} px; {int(bad.sum())} points (up to "
            f"radius {np.sqrt(q[bad].max()):.6g} px) have no distorted image")
    kq = np.where(bad, np.nan, kq)
    rho = np.ones_like(q)
    for _ in range(max_iter):
        step = (rho + kq * rho**3 - 1.0) / (1.0 + 3.0 * kq * rho**2)
        rho = rho - step
        if not np.any(np.abs(step) > 1e-12):  # quadratic convergence: the next error is ~1e-24
            break
    dh = 1.0 + 3.0 * kq * rho**2  # > 0 on the monotone branch
    return rho, -kappa1 * rho**3 / dh, -q * rho**3 / dh


class TsaiModel:
    """Tsai's projection (eqs. (2)-(4)) of camera-frame points, for ``refine``.

    params = [f, sx, cx, cy, kappa1] (f in px, kappa1 in px^-2). With ``strict=False`` points
    beyond the fold of a negative kappa1 project to NaN instead of raising, so that a trial step
    of refine's Levenberg-Marquardt that crosses the fold is rejected rather than fatal.
    """

    param_names = PARAM_NAMES

    def __init__(self, strict: bool = True):
        self.strict = strict

    def project(self, params: np.ndarray, points_cam: np.ndarray, jacobians: bool = True):
        """points_cam (N, 3) -> uv (N, 2), d uv / d params (N, 2, 5), d uv / d points (N, 2, 3);
        both Jacobians None when ``jacobians`` is False."""
        f, sx, cx, cy, k = np.asarray(params, dtype=np.float64)
        P = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
        z = P[:, 2]
        pu = f * P[:, :2] / z[:, None]                     # (Xu, Yu)
        q = np.sum(pu * pu, axis=1)
        rho, rho_q, rho_k = distortion_ratio(q, k, self.strict)
        pd = rho[:, None] * pu                             # (Xd, Yd)
        S = np.array([sx, 1.0])
        uv = pd * S + np.array([cx, cy])
        if not jacobians:
            return uv, None, None

        # d(Xd, Yd) / d(Xu, Yu) = rho I + 2 rho_q pu pu^T
        Jd = (rho[:, None, None] * np.eye(2)
              + 2 * rho_q[:, None, None] * pu[:, :, None] * pu[:, None, :])
        Jp = np.zeros((len(P), 2, 5))
        Jp[:, :, 0] = np.einsum("nij,nj->ni", Jd, pu / f) * S   # d pu / d f = pu / f
        Jp[:, 0, 1] = pd[:, 0]
        Jp[:, 0, 2] = 1.0
        Jp[:, 1, 3] = 1.0
        Jp[:, :, 4] = rho_k[:, None] * pu * S
        Ju = np.zeros((len(P), 2, 3))                      # d pu / d points
        Ju[:, 0, 0] = Ju[:, 1, 1] = f / z
        Ju[:, :, 2] = -pu / z[:, None]
        Jx = S[None, :, None] * (Jd @ Ju)
        return uv, Jp, Jx


# ----------------------------------------------------------------------------------------------
# Closed-form stages
# ----------------------------------------------------------------------------------------------

def radial_alignment_pose(board_xy: np.ndarray, sensor_d: np.ndarray):
    """Stage 1 for one view: R (3, 3), Tx, Ty from the radial alignment constraint.

    board_xy (N, 2): board points (z = 0), mm. sensor_d (N, 2): distorted sensor coordinates
    (Xd, Yd) relative to the principal point, px. R's third column is fixed up to the f > 0
    choice, which :func:`initial_estimate` makes; the returned R is the r3 >= 0 branch.

    The RAC divides by Ty, so Tsai asks for a world origin far from the camera's x-z plane. The
    solve therefore uses the board point imaged farthest from the image's horizontal centre line
    as origin, and moves Tx, Ty back to the board's own origin at the end.
    """
    Xd, Yd = sensor_d[:, 0], sensor_d[:, 1]
    origin = board_xy[np.argmax(np.abs(Yd))]
    xw, yw = (board_xy - origin).T
    # Eq. (10) coplanar: Yd xw r1' + Yd yw r2' + Yd Tx' - Xd xw r4' - Xd yw r5' = Xd.
    A = np.stack([Yd * xw, Yd * yw, Yd, -Xd * xw, -Xd * yw], 1)
    sol, _, rank, _ = np.linalg.lstsq(A, Xd, rcond=None)
    if rank < 5:
        raise ValueError(f"radial alignment: rank {rank} < 5 (need >= 5 points in general "
                         f"position, not all on a line through the image centre)")
    r1p, r2p, txp, r4p, r5p = sol
    # |Ty| (eq. (12)): 1/Ty^2 is the larger squared singular value of C = [[r1', r2'], [r4', r5']].
    C = np.array([[r1p, r2p], [r4p, r5p]])
    Sr = float(np.sum(C * C))
    det = float(np.linalg.det(C))
    # The paper's Ty^2 = (Sr - sqrt(Sr^2 - 4 det^2)) / (2 det^2), rationalized to avoid the
    # cancellation as det -> 0; at det = 0 it is the paper's other case, 1 / (ri'^2 + rj'^2).
    ty = np.sqrt(2.0 / (Sr + np.sqrt(max(Sr * Sr - 4 * det * det, 0.0))))
    # Sign of Ty: with Ty > 0 the farthest point's (Xc, Yc) must point the way (Xd, Yd) does.
    i = np.argmax(Xd * Xd + Yd * Yd)
    xc = (r1p * xw[i] + r2p * yw[i] + txp) * ty
    yc = (r4p * xw[i] + r5p * yw[i] + 1.0) * ty
    if xc * Xd[i] + yc * Yd[i] < 0:
        ty = -ty
    r1, r2, tx, r4, r5 = r1p * ty, r2p * ty, txp * ty, r4p * ty, r5p * ty
    r3 = np.sqrt(max(1.0 - r1 * r1 - r2 * r2, 0.0))
    # r6 = -sgn(r1 r4 + r2 r5) sqrt(...); at a tie (r3 = 0) either sign, the f > 0 test decides.
    r6 = np.copysign(np.sqrt(max(1.0 - r4 * r4 - r5 * r5, 0.0)), -(r1 * r4 + r2 * r5))
    row1, row2 = np.array([r1, r2, r3]), np.array([r4, r5, r6])
    R = np.stack([row1, row2, np.cross(row1, row2)])
    tx, ty = np.array([tx, ty]) - R[:2, :2] @ origin
    return R, float(tx), float(ty)


def _focal_terms(xy: np.ndarray, yd: np.ndarray, R: np.ndarray, ty: float):
    """One view's share of eq. (15)'s least squares for f, its Tz eliminated in closed form.

    Per point: y_i f - Yd_i Tz = w_i Yd_i with y_i = r4 xw + r5 yw + Ty and w_i = r7 xw + r8 yw.
    For fixed f the best Tz fits Yd Tz to y f - w Yd; what is left is f P y = P (w Yd), P the
    projection that removes Yd. Returns (num, den, y, w Yd) with this view's f = num / den.
    """
    y = xy @ R[1, :2] + ty
    b = (xy @ R[2, :2]) * yd
    out = lambda a: a - yd * (yd @ a) / (yd @ yd)
    return out(y) @ out(b), out(y) @ out(y), y, b


def focal_and_tz(board_xy: list[np.ndarray], Yd: list[np.ndarray], Rs: list[np.ndarray],
                 tys: list[float]):
    """Stage 2: shared f and per-view Tz from eq. (15) with kappa1 = 0. Returns (f, tz (V,))."""
    terms = [_focal_terms(*args) for args in zip(board_xy, Yd, Rs, tys)]
    den = sum(t[1] for t in terms)
    if not den > 1e-12 * sum(t[2] @ t[2] for t in terms):
        raise ValueError("Tsai stage 2: f and Tz are not separable; the board must be tilted "
                         "against the image plane in some view")
    f = sum(t[0] for t in terms) / den
    return float(f), np.array([yd @ (y * f - b) / (yd @ yd)
                               for (_, _, y, b), yd in zip(terms, Yd)])


def flip_for_positive_f(R: np.ndarray) -> np.ndarray:
    """The other RAC branch: r3, r6, r7, r8 change sign (the paper's rule when f < 0)."""
    return R * np.array([[1, 1, -1], [1, 1, -1], [-1, -1, 1]])


def initial_estimate(obs: Observations, sx: float):
    """Stages 1 and 2 over all views: (params0 [f, sx, cx, cy, 0], rvecs0 (V,3), tvecs0 (V,3))."""
    w, h = obs.image_size
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    board = [o[:, :2] for o in obs.object_points]
    sensor = [np.stack([(p[:, 0] - cx) / sx, p[:, 1] - cy], 1) for p in obs.image_points]
    Rs, txs, tys = [], [], []
    for vid, xy, d in zip(obs.view_ids, board, sensor):
        try:
            R, tx, ty = radial_alignment_pose(xy, d)
        except ValueError as e:
            raise ValueError(f"Tsai calibration of {obs.camera_name!r}, view {vid}: {e}") from None
        # This view's f has the sign of its numerator; a board parallel to the image has f ~ 0
        # from either branch, and there the branches nearly coincide anyway.
        Rs.append(flip_for_positive_f(R) if _focal_terms(xy, d[:, 1], R, ty)[0] < 0 else R)
        txs.append(tx)
        tys.append(ty)
    f, tz = focal_and_tz(board, [d[:, 1] for d in sensor], Rs, tys)
    behind = [vid for vid, z in zip(obs.view_ids, tz) if z <= 0]
    if f <= 0 or behind:
        raise ValueError(f"Tsai calibration of {obs.camera_name!r}: stage 2 gave f = {f:.6g} px "
                         f"and the board behind the camera in views {behind}")
    rvecs = matrix_to_rodrigues(np.stack([nearest_rotation(R) for R in Rs]))
    return np.array([f, sx, cx, cy, 0.0]), rvecs, np.stack([txs, tys, tz], 1)


# ----------------------------------------------------------------------------------------------
# Conversion to OpenCV's model
# ----------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class ConversionReport:
    """How well OpenCV's k1, k2, k3 reproduce Tsai's exact map over the image (pixels)."""

    max_px: float
    rms_px: float
    series_k: tuple[float, float, float]  # -K, 3K^2, -12K^3 with K = kappa1 f^2


def tsai_to_opencv(params: np.ndarray, width: int, height: int, name: str = "camera",
                   grid: int = 161, tolerance_px: float = 0.01) -> tuple[Camera, ConversionReport]:
    """Camera with fx = sx f, fy = f and OpenCV radial coefficients fitted to Tsai's distortion.

    Every pixel of a grid x grid lattice over the image and a 20 % margin around it is
    undistorted exactly by eq. (3); the radial coefficients minimise, linearly, the pixel
    distance between OpenCV's forward projection of that undistorted point and the pixel
    itself. k1, k2, k3 first; when they leave more than ``tolerance_px`` (strong lenses: about
    2 px at the corners of the paper's wide-angle camera), the rational model k1..k6 is fitted
    instead (linearized as num - rho den = 0), so the conversion does not pollute the
    comparison. This is a dense deterministic fit of a known function, so the rational
    model's non-identifiability from planar views (TRAPS.md) does not apply.
    """
    f, sx, cx, cy, k = np.asarray(params, dtype=np.float64)

    def samples(lo: float, hi: float):
        """Tsai's exact undistorted normalized points and radial factor on a pixel lattice."""
        u, v = np.meshgrid(np.linspace(lo, hi, grid) * (width - 1),
                           np.linspace(lo, hi, grid) * (height - 1))
        pd = np.stack([(u.ravel() - cx) / sx, v.ravel() - cy], 1)
        rd2 = np.sum(pd * pd, axis=1)
        if k < 0:  # beyond the fold Tsai's map has no inverse
            pd, rd2 = pd[rd2 * -3.0 * k < 0.95], rd2[rd2 * -3.0 * k < 0.95]
        xy = pd * (1.0 + k * rd2)[:, None] / f
        return xy, np.sum(xy * xy, axis=1), 1.0 / (1.0 + k * rd2)

    corner2 = max(((x - cx) / sx) ** 2 + (y - cy) ** 2
                  for x in (0, width - 1) for y in (0, height - 1))
    if k < 0 and corner2 * -3.0 * k >= 1.0:
        raise TsaiUnreachableError(
            f"kappa1 = {k:.6g} folds Tsai's distortion inside the {width}x{height} image "
            f"(at distorted radius {1 / np.sqrt(-3 * k):.6g} px); no OpenCV equivalent")
    fxy = np.array([sx * f, f])
    image = samples(0.0, 1.0)
    # The fit also covers 20 % beyond each border: another camera's rays (the true one's, in the
    # projection-difference metric) land slightly outside this image, and a rational fit must
    # not extrapolate there (it can have a pole just outside the fitted range).
    xy, r2, rho = (np.concatenate(p) for p in zip(image, samples(-0.2, 1.2)))
    # Pixel residual of OpenCV's map: fxy * xy * (radial(r2) - rho).
    a = (fxy * xy).T.reshape(-1)                      # u rows, then v rows
    r2a, rhoa = np.concatenate([r2, r2]), np.concatenate([rho, rho])
    powers = np.stack([r2a, r2a**2, r2a**3], 1)

    def fit(A):
        scale = np.linalg.norm(A, axis=0)  # r2^3 is ~100x smaller than r2: equilibrate
        return np.linalg.lstsq(A / scale, a * (rhoa - 1.0), rcond=None)[0] / scale

    kk = fit(a[:, None] * powers)
    dist = np.array([kk[0], kk[1], 0, 0, kk[2], 0, 0, 0])
    if _conversion_error(dist, r2, rho, fxy, xy).max() > tolerance_px:
        kk = fit(a[:, None] * np.hstack([powers, -rhoa[:, None] * powers]))
        dist = np.array([kk[0], kk[1], 0, 0, kk[2], kk[3], kk[4], kk[5]])
    err = _conversion_error(dist, image[1], image[2], fxy, image[0])  # reported over the image
    K = k * f * f
    cam = Camera(name, width, height, sx * f, f, cx, cy, 0.0, dist)
    return cam, ConversionReport(float(err.max()), float(np.sqrt(np.mean(err**2))),
                                 (float(-K), float(3 * K * K), float(-12 * K**3)))


def _conversion_error(dist, r2, rho, fxy, xy) -> np.ndarray:
    """Pixel distance between OpenCV's radial map with ``dist`` and Tsai's exact one."""
    k1, k2, _, _, k3, k4, k5, k6 = dist
    radial = (1 + k1 * r2 + k2 * r2**2 + k3 * r2**3) / (1 + k4 * r2 + k5 * r2**2 + k6 * r2**3)
    return np.linalg.norm(fxy * xy * (radial - rho)[:, None], axis=1)


# ----------------------------------------------------------------------------------------------
# The calibrator
# ----------------------------------------------------------------------------------------------

class TsaiCalibrator:
    """Tsai's coplanar calibration over many views (stages in the module docstring).

    sx: a known horizontal scale factor to hold fixed; None (default) starts at 1, as Tsai
    assumes for coplanar targets, and estimates it in the joint refinement.
    free_principal_point: also refine Cx, Cy (Tsai's method keeps them at the image centre).
    """

    name = "tsai"
    # Tsai's model (radial kappa1 on distorted coordinates, scale factor sx) is not the OpenCV
    # model its estimate is converted to, so no OpenCV parameters stand for it in a rig's
    # bundle adjustment: there its intrinsics stay as estimated.
    model_parameters = None
    # For the same reason it fits none of the lens models of lens_models.py.
    lens_models = ()
    own_model = ("Tsai's own model (k1 radial on distorted coordinates as kappa1, scale factor "
                 "sx, principal point at the image centre)")

    def __init__(self, sx: float | None = None, free_principal_point: bool = False,
                 max_iter: int = 100):
        self.sx = sx
        self.free_principal_point = free_principal_point
        self.max_iter = max_iter

    def calibrate(self, obs: Observations) -> CalibrationResult:
        t0 = time.perf_counter()
        w, h = obs.image_size
        free = np.array([True, self.sx is None] + [self.free_principal_point] * 2 + [True])
        model = TsaiModel(strict=False)
        passes = []
        sx0 = 1.0 if self.sx is None else float(self.sx)
        # Pass 1 starts at sx = 1 (or the known sx). The RAC's rotations are only as good as that
        # sx, and with a wrong one (e.g. 4/3 for non-square pixels) refine can end in a local
        # minimum; pass 2 redoes the closed-form stages with pass 1's multi-view sx.
        for _ in range(2 if self.sx is None else 1):
            params0, rvecs0, tvecs0 = initial_estimate(obs, sx0)
            res = refine(model, params0, free, obs.object_points, obs.image_points, rvecs0,
                         tvecs0, max_iter=self.max_iter)
            passes.append((res, params0))
            if abs(res.params[1] - sx0) <= 1e-3 * sx0:  # the RAC already had sx to 0.1 %
                break
            sx0 = float(res.params[1])
        res = min((r for r, _ in passes), key=lambda r: r.cost)
        camera, conv = tsai_to_opencv(res.params, w, h, obs.camera_name)
        f, kappa1 = res.params[[0, 4]]
        log = {
            "method": self.name,
            **res.log(),
            "tsai": dict(zip(PARAM_NAMES, map(float, res.params))),
            "kappa1_f2": float(kappa1 * f * f),
            "passes": [{"f0": float(p0[0]), "sx0": float(p0[1]), "iterations": r.iterations,
                        "final_cost": r.cost} for r, p0 in passes],
            "principal_point": "free" if self.free_principal_point else
                               "fixed at the image centre ((w - 1) / 2, (h - 1) / 2)",
            "opencv_conversion": {"max_px": conv.max_px, "rms_px": conv.rms_px,
                                  "k1_k2_k3": camera.dist[[0, 1, 4]].tolist(),
                                  "series_k1_k2_k3": list(conv.series_k)},
            "time_s": time.perf_counter() - t0,
        }
        return CalibrationResult(camera, res.rvecs, res.tvecs, log)
