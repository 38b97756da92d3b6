"""What a calibration's own data say about it, without ground truth.

A calibration of real images has no truth to score against; these checks use only the detections,
the estimate and its board poses (CalibrationResult), and return JSON-ready dicts.

* ``heldout``: k-fold cross-validation over views. The method calibrates on k-1 folds; each
  held-out view's pose is fitted with those intrinsics fixed (pose.planar_pose) and its RMS
  reprojection error measured. On pure noise the held-out RMS exceeds the in-sample RMS of the
  same points by what the intrinsics fitted of the noise (the held-out poses are refitted):
  roughly sqrt((1 + p/n) / (1 - p/n)) for p intrinsics and n residuals, 1.003 for 9 and 3520;
  much more means the model fits the noise or the views disagree.
* ``view_outliers``: per-view RMS reprojection error, flagged by the modified z-score
  0.6745 (x - median) / MAD > 3.5 of Iglewicz & Hoaglin ("How to detect and handle outliers",
  1993), one-sided (only views that fit worse than the others), with the scale never below the
  spread that Gaussian noise alone gives a view's RMS.
* ``point_outliers``: residuals beyond a robust threshold: sigma from the median absolute residual
  coordinate (1.4826 x median |r|), and |r| > sigma sqrt(2 ln(N / false_alarm)), the level that
  N independent Gaussian residuals (|r|^2 / sigma^2 ~ chi^2 with 2 degrees of freedom) exceed
  with probability at most ``false_alarm`` altogether (Bonferroni).
* ``residual_randomness``: are the residuals noise? The statistic is the correlation of residual
  vectors between neighbouring board points of a view, sum over neighbour pairs r_j . r_k per pair
  over sum |r_j|^2 per point: 0 for noise, towards 1 for a smooth systematic residual (a lens
  model too simple, a bent board, a detector bias). Fitted residuals are not independent (each
  view's pose and the shared intrinsics absorb part of the noise, which makes neighbours slightly
  anti-correlated), so the null distribution is simulated through the linearized fit: Gaussian
  noise e, residuals (I - J (J^T J)^+ J^T) e through refine.py's Schur factorization, with J the
  Jacobian of all the intrinsics the method estimated and all the poses.
  One-sided Monte Carlo p-values per view and for the camera (neighbour-pair-weighted mean of the
  views' statistics), flagged below ``alpha``; a per-view flag is a per-view test (about alpha of
  the views of a clean calibration are flagged).
* ``coverage``: where the detected features lie in the image: per-cell counts on a grid, the share
  of cells holding a feature, the convex hull of all features and the union of the views' hulls
  as shares of the image.
* ``view_geometry``: before any calibration, do the views determine the camera at all? A view of
  a plane is a homography (8 numbers), of which the board's pose takes 6: it constrains 2 of the
  pinhole parameters (Zhang 2000, section 2.3), so fx, fy, cx, cy need at least 2 views and
  Zhang's closed form with skew 3. Views of parallel boards give the same 2 constraints as one,
  and boards facing the camera none on the focal length (Zhang 2000, section 4, degenerate
  configurations; Sturm & Maybank, "On plane-based camera calibration", CVPR 1999, list the
  other singular sets, e.g. boards turned about one axis). What measures it is the calibration's
  Jacobian in the pinhole model (distortion removed, so that a distortion coefficient cannot
  stand in for the geometry): how far the focal length can move, every pose refitted, for a
  given change of the RMS reprojection error (``focal_ambiguity``). It is a property of the
  views' orientations, not of the noise or of how many views repeat them.
"""

from __future__ import annotations


import math
from typing import Sequence

import cv2
import numpy as np

from . import get_calibrator
from .base import Observations
from .homography import fit_homographies
from .refine import CameraModel, free_mask, intrinsic_information, linearize, refine
from .homography import extrinsics_from_homography
from ..core.camera import Camera, project_points
from ..core.poses import rodrigues_to_matrix
from ..core.files import strict
from .pose import planar_pose
from .uncertainty import check_poses

MIN_TRAINING_VIEWS = 3  # Zhang's minimum for the five pinhole intrinsics (section 3.1)
MODIFIED_Z = 3.5  # Iglewicz & Hoaglin's recommended cut on the modified z-score
_CALIBRATION_ERRORS = (ValueError, np.linalg.LinAlgError, RuntimeError, cv2.error)


def view_residuals(camera: Camera, obs: Observations, rvecs, tvecs, board_points=None
                   ) -> list[np.ndarray]:
    """Per view (N_i, 2) px: projected - detected, through the camera and the view's pose, of
    the board's points (``board_points`` per view, as a fit shaped the board; default the
    nominal ones)."""
    rv, tv = check_poses(obs, rvecs, tvecs)
    points = obs.object_points if board_points is None else board_points
    return [project_points(o, camera.intrinsics, camera.dist, r, t, camera.model) - p
            for o, p, r, t in zip(points, obs.image_points, rv, tv)]


def _rms(r: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(r * r, axis=-1))))


def view_outliers(camera: Camera, obs: Observations, rvecs, tvecs,
                  threshold: float = MODIFIED_Z) -> dict:
    """Per-view RMS reprojection error and the views that fit markedly worse than the others.

    The modified z-score (rms - median) / s with s = MAD / 0.6745 (the mean absolute deviation
    / 0.7979 when more than half the views share the median), floored per view at the spread
    Gaussian noise alone gives an RMS over N_i points, median / sqrt(4 N_i): twenty views'
    MAD is itself uncertain by a quarter and came out below that spread in clean data, where the
    bare rule flagged 3 of 480 views; the floor keeps ordinary noise from being called an outlier.

    Returns ``view_ids``, ``rms_px`` and ``modified_z`` (V,), ``threshold_px`` (V,) (the RMS above
    which each view is flagged), ``median_px``, ``mad_px``, ``flagged`` (view ids) and
    ``rms_px_all`` (over all points).
    """
    res = view_residuals(camera, obs, rvecs, tvecs)
    rms = np.array([_rms(r) for r in res])
    med = float(np.median(rms))
    mad = float(np.median(np.abs(rms - med)))
    spread = mad / 0.6745 if mad > 0 else float(np.mean(np.abs(rms - med))) / 0.7979
    noise = med / np.sqrt(4.0 * np.array([len(r) for r in res]))
    scale = np.maximum(spread, noise)
    z = np.where(scale > 0, (rms - med) / np.where(scale > 0, scale, 1.0), 0.0)
    return strict({
        "view_ids": obs.view_ids,
        "rms_px": rms,
        "modified_z": z,
        "threshold_px": med + threshold * scale,
        "median_px": med,
        "mad_px": mad,
        "flagged": [v for v, f in zip(obs.view_ids, z > threshold) if f],
        "rms_px_all": _rms(np.concatenate(res)),
    })


def point_outliers(camera: Camera, obs: Observations, rvecs, tvecs,
                   false_alarm: float = 0.01) -> dict:
    """Detections whose residual exceeds a robust threshold (see the module docstring).

    Returns ``sigma_px`` (1.4826 x the median absolute residual coordinate), ``threshold_px``,
    ``false_alarm``, ``n_points`` and ``flagged``: a list of {view_id, index (into the view's
    points), residual_px, image_point [u, v]}, largest first.
    """
    if not 0 < false_alarm < 1:
        raise ValueError(f"false_alarm: expected a probability in (0, 1), got {false_alarm}")
    res = view_residuals(camera, obs, rvecs, tvecs)
    sigma = 1.4826 * float(np.median(np.abs(np.concatenate(res))))
    n = obs.n_points
    threshold = sigma * math.sqrt(2.0 * math.log(n / false_alarm))
    flagged = []
    for v, r, p in zip(obs.view_ids, res, obs.image_points):
        norm = np.linalg.norm(r, axis=1)
        flagged += [{"view_id": v, "index": int(i), "residual_px": float(norm[i]),
                     "image_point": p[i]} for i in np.flatnonzero(norm > threshold)]
    flagged.sort(key=lambda f: -f["residual_px"])
    return strict({"sigma_px": sigma, "threshold_px": threshold, "false_alarm": false_alarm,
                   "n_points": n, "flagged": flagged})


# ----------------------------------------------------------------------------------------------
# Are the residuals random?
# ----------------------------------------------------------------------------------------------

def neighbour_pairs(board_points: np.ndarray, reach: float = 1.5) -> np.ndarray:
    """(P, 2) index pairs j < k of board points (N, 3) closer than ``reach`` times the median
    nearest-neighbour distance on the board (on a square grid: the 8-neighbourhood)."""
    xy = np.asarray(board_points, dtype=np.float64)[:, :2]
    d = np.linalg.norm(xy[:, None] - xy[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    j, k = np.nonzero(np.triu(d <= reach * np.median(d.min(axis=1)), 1))
    return np.stack([j, k], -1)


def _neighbour_correlation(r: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """Statistic of residuals r (N, 2, ...) over pairs (P, 2): mean r_j . r_k over mean |r|^2."""
    num = np.mean(np.sum(r[pairs[:, 0]] * r[pairs[:, 1]], axis=1), axis=0)
    return num / np.mean(np.sum(r * r, axis=1), axis=0)


def _null_residuals(lin: dict, e: np.ndarray) -> np.ndarray:
    """Residuals (N, 2, S) the linearized fit leaves of noise e (N, 2, S): e - J delta with
    delta the least-squares step, solved blockwise (poses eliminated as in refine.py)."""
    Ja, Jb, V_inv = lin["J_params"], lin["J_pose"], np.linalg.inv(lin["V"])
    ga, gb = [], []
    for a, b in lin["bounds"]:
        ga.append(np.einsum("nif,nis->fs", Ja[a:b], e[a:b]))
        gb.append(np.einsum("nij,nis->js", Jb[a:b], e[a:b]))
    gb = np.array(gb)  # (V, 6, S)
    WVg = np.einsum("vfj,vjk,vks->fs", lin["W"], V_inv, gb)
    da = lin["S_inv"] @ (np.sum(ga, axis=0) - WVg)  # (F, S)
    out = e.copy()
    for v, (a, b) in enumerate(lin["bounds"]):
        db = V_inv[v] @ (gb[v] - lin["W"][v].T @ da)  # (6, S)
        out[a:b] -= np.einsum("nif,fs->nis", Ja[a:b], da) + np.einsum("nij,js->nis", Jb[a:b], db)
    return out


def residual_randomness(camera: Camera, obs: Observations, rvecs, tvecs,
                        parameters: Sequence[str] | None, alpha: float = 0.01,
                        n_sim: int = 999, seed: int = 0) -> dict:
    """Neighbour correlation of the residuals with Monte Carlo p-values (module docstring).

    ``parameters``: the intrinsics the method estimated (its ``model_parameters``); None or ()
    when none are known in the OpenCV model (then only the poses' absorption enters the null).
    Returns ``statistic`` and ``p_value`` for the camera, ``flagged`` (p_value < alpha),
    ``views``: a list of {view_id, statistic, p_value, flagged, n_pairs}, ``flagged_views``,
    ``alpha``, ``n_sim``, ``null_mean`` (the camera statistic's mean under the null).
    """
    if not 0 < alpha < 1:
        raise ValueError(f"alpha: expected a level in (0, 1), got {alpha}")
    if int(n_sim) < 1:
        raise ValueError(f"n_sim: expected at least 1 simulation, got {n_sim}")
    rv, tv = check_poses(obs, rvecs, tvecs)
    model = CameraModel(camera.model)
    free = free_mask(model.param_names, tuple(parameters or ()))
    lin = linearize(model, model.params_of(camera), free, obs.object_points, obs.image_points,
                    rv, tv)
    pairs = [neighbour_pairs(o) for o in obs.object_points]
    weights = np.array([len(p) for p in pairs], dtype=np.float64)
    if weights.sum() == 0:
        raise ValueError(f"observations of {obs.camera_name!r}: no view has neighbouring board "
                         f"points to correlate")
    views = [v for v, p in enumerate(pairs) if len(p)]

    def statistics(res):  # (views with pairs,) or (views with pairs, S)
        return np.array([_neighbour_correlation(res[slice(*lin["bounds"][v])], pairs[v])
                         for v in views])

    r = lin["residuals"]
    observed = statistics(r)
    rng = np.random.default_rng(seed)
    simulated = []
    for start in range(0, int(n_sim), 100):  # chunks: e for all points is N x 2 x S floats
        e = rng.standard_normal(r.shape + (min(100, int(n_sim) - start),))
        simulated.append(statistics(_null_residuals(lin, e)))
    simulated = np.concatenate(simulated, axis=1)  # (views with pairs, n_sim)
    w = weights[views] / weights[views].sum()
    cam_observed, cam_null = float(w @ observed), w @ simulated
    p_views = (1 + np.sum(simulated >= observed[:, None], axis=1)) / (1 + simulated.shape[1])
    p_cam = float((1 + np.sum(cam_null >= cam_observed)) / (1 + len(cam_null)))
    rows = [{"view_id": obs.view_ids[v], "statistic": float(s), "p_value": float(p),
             "flagged": bool(p < alpha), "n_pairs": int(weights[v])}
            for v, s, p in zip(views, observed, p_views)]
    return strict({
        "statistic": cam_observed, "p_value": p_cam, "flagged": p_cam < alpha,
        "null_mean": float(np.mean(cam_null)), "alpha": alpha, "n_sim": int(n_sim),
        "views": rows, "flagged_views": [row["view_id"] for row in rows if row["flagged"]],
    })


# ----------------------------------------------------------------------------------------------
# Coverage
# ----------------------------------------------------------------------------------------------

def coverage(obs: Observations, grid: tuple[int, int] = (10, 8), raster: int = 1024) -> dict:
    """How much of the image the detected features cover.

    ``grid`` (columns, rows) cells tile the image ([-0.5, W - 0.5] x [-0.5, H - 0.5] in OpenCV
    pixel centres). Returns ``counts`` (rows x columns lists of feature counts over all views,
    for a heat map), ``cell_fraction`` (share of cells with at least one feature),
    ``hull_fraction`` (convex hull of all features over the image area), ``board_fraction``
    (union of the views' convex hulls over the image area, rasterized with ``raster`` cells
    along the longer side), ``outside`` (features outside the image, not counted) and ``grid``.
    """
    nu, nv = (int(g) for g in grid)
    if nu < 1 or nv < 1:
        raise ValueError(f"grid: expected (columns, rows) of at least 1 each, got {grid}")
    w, h = obs.image_size

    def in_image(p):
        return np.all((p >= -0.5) & (p < np.array([w, h]) - 0.5), axis=1)

    pts = np.concatenate(obs.image_points)
    inside = in_image(pts)
    col = np.minimum(((pts[inside, 0] + 0.5) * nu / w).astype(int), nu - 1)
    row = np.minimum(((pts[inside, 1] + 0.5) * nv / h).astype(int), nv - 1)
    counts = np.zeros((nv, nu), dtype=int)
    np.add.at(counts, (row, col), 1)
    hull = cv2.convexHull(pts[inside].astype(np.float32)) if inside.sum() >= 3 else None
    hull_area = float(cv2.contourArea(hull)) if hull is not None else 0.0
    # Union of the views' hulls on a raster of the image (cv2 fills with 1/16-px precision).
    s = min(1.0, raster / max(w, h))
    mask = np.zeros((max(1, round(h * s)), max(1, round(w * s))), dtype=np.uint8)
    for p in obs.image_points:
        q = p[in_image(p)]
        if len(q) >= 3:
            poly = cv2.convexHull(np.round(((q + 0.5) * s - 0.5) * 16).astype(np.int32))
            cv2.fillConvexPoly(mask, poly, 1, lineType=cv2.LINE_8, shift=4)
    return strict({
        "grid": [nu, nv],
        "counts": counts,
        "cell_fraction": float(np.mean(counts > 0)),
        "hull_fraction": hull_area / (w * h),
        "board_fraction": float(mask.mean()),
        "outside": int((~inside).sum()),
    })


# ----------------------------------------------------------------------------------------------
# Held-out views
# ----------------------------------------------------------------------------------------------

def _subset(obs: Observations, index) -> Observations:
    return Observations([obs.object_points[i] for i in index],
                        [obs.image_points[i] for i in index], obs.image_size,
                        [obs.view_ids[i] for i in index], obs.camera_name)


def heldout(method: str, obs: Observations, k: int = 5, seed: int = 0, **options) -> dict:
    """k-fold cross-validated reprojection error of calibration ``method`` (registry name).

    Views are shuffled with ``seed`` and split into k folds; each fold is held out in turn, the
    method calibrates on the others, and every held-out view gets its pose from the trained
    camera (intrinsics fixed, pose.planar_pose). With fewer than k views each view is its own
    fold (``folds`` < ``k_requested`` and ``note`` says so); every training set keeps at least
    MIN_TRAINING_VIEWS views. The same method's calibration on all views gives the in-sample
    error of the same points.

    Returns ``heldout_rms_px`` and ``in_sample_rms_px`` (over the views that have both),
    ``ratio`` (held-out over in-sample), ``train_rms_px`` (the folds' own fits), ``views``: a list
    of {view_id, fold, heldout_rms_px, in_sample_rms_px, error}, ``fold_errors`` (fold -> why its
    calibration failed), ``folds``, ``k_requested``, ``note``, ``method``, ``seed``.
    ``options`` go to the calibrator (e.g. ``board_warp``); a fit that shaped the board sees
    every view, the held-out ones too, on the board as it fitted it.
    """
    calibrator = get_calibrator(method, **options)
    n = obs.n_views
    if int(k) != k or k < 2:
        raise ValueError(f"k: expected an integer number of folds >= 2, got {k}")
    if n < MIN_TRAINING_VIEWS + 1:
        raise ValueError(f"observations of {obs.camera_name!r}: {n} views; held-out errors need "
                         f"at least {MIN_TRAINING_VIEWS + 1} (training on {MIN_TRAINING_VIEWS})")
    folds = min(int(k), n)
    if n - math.ceil(n / folds) < MIN_TRAINING_VIEWS:
        raise ValueError(f"k: {folds} folds of {n} views leave fewer than {MIN_TRAINING_VIEWS} "
                         f"training views; use k >= {math.ceil(n / (n - MIN_TRAINING_VIEWS))}")
    note = (f"{n} views: {folds} folds (leave one view out) instead of {k}" if folds < k else "")
    order = np.random.default_rng(seed).permutation(n)
    fold_of = np.empty(n, dtype=int)
    for f, index in enumerate(np.array_split(order, folds)):
        fold_of[index] = f

    full = calibrator.calibrate(obs)
    in_sample = view_residuals(full.camera, obs, full.rvecs, full.tvecs, full.board_points(obs))
    heldout_res: list = [None] * n
    errors: list = [None] * n
    fold_errors, train_res = {}, []
    for f in range(folds):
        test, train = np.flatnonzero(fold_of == f), np.flatnonzero(fold_of != f)
        try:
            fit = calibrator.calibrate(_subset(obs, train))
        except _CALIBRATION_ERRORS as e:
            fold_errors[str(f)] = f"{type(e).__name__}: {e}"
            for i in test:
                errors[i] = f"calibration of fold {f} failed"
            continue
        trained = _subset(obs, train)
        train_res += view_residuals(fit.camera, trained, fit.rvecs, fit.tvecs,
                                    fit.board_points(trained))
        shaped = fit.board_points(obs)
        for i in test:
            o, p = shaped[i], obs.image_points[i]
            try:
                rvec, tvec = planar_pose(fit.camera, o, p)
            except _CALIBRATION_ERRORS as e:  # e.g. a held-out corner beyond the trained fold
                errors[i] = f"{type(e).__name__}: {e}"
                continue
            heldout_res[i] = project_points(o, fit.camera.intrinsics, fit.camera.dist, rvec,
                                            tvec, fit.camera.model) - p
    done = [i for i in range(n) if heldout_res[i] is not None]
    out_rms = _rms(np.concatenate([heldout_res[i] for i in done])) if done else None
    in_rms = _rms(np.concatenate([in_sample[i] for i in done])) if done else None
    return strict({
        "method": calibrator.name, "k_requested": int(k), "folds": folds, "note": note,
        "seed": int(seed),
        "heldout_rms_px": out_rms,
        "in_sample_rms_px": in_rms,
        "ratio": out_rms / in_rms if done and in_rms > 0 else None,
        "train_rms_px": _rms(np.concatenate(train_res)) if train_res else None,
        "views": [{"view_id": obs.view_ids[i], "fold": int(fold_of[i]),
                   "heldout_rms_px": None if heldout_res[i] is None else _rms(heldout_res[i]),
                   "in_sample_rms_px": _rms(in_sample[i]), "error": errors[i]}
                  for i in range(n)],
        "fold_errors": fold_errors,
    })


def diagnose(camera: Camera, obs: Observations, rvecs, tvecs,
             parameters: Sequence[str] | None, seed: int = 0) -> dict:
    """The checks that need no recalibration, with their defaults: ``views``
    (:func:`view_outliers`), ``points`` (:func:`point_outliers`), ``randomness``
    (:func:`residual_randomness`) and ``coverage`` (:func:`coverage`)."""
    return {
        "views": view_outliers(camera, obs, rvecs, tvecs),
        "points": point_outliers(camera, obs, rvecs, tvecs),
        "randomness": residual_randomness(camera, obs, rvecs, tvecs, parameters, seed=seed),
        "coverage": coverage(obs),
    }


# ----------------------------------------------------------------------------------------------
# Do the views determine the camera?
# ----------------------------------------------------------------------------------------------

PINHOLE_PARAMETERS = ("fx", "fy", "cx", "cy")
#: Each view of a plane constrains 2 pinhole parameters (module docstring): fx, fy, cx, cy
#: need 2 views, Zhang's closed form with skew 3 (zhang.intrinsics_from_homographies).
MIN_VIEWS = 2
MIN_VIEWS_WITH_SKEW = 3
#: The focal-length test: the views must not let fx or fy move by more than
#: MAX_FOCAL_AMBIGUITY (relative) while the RMS reprojection error, every pose refitted,
#: changes by only AMBIGUITY_RMS_PX. 0.1 px is the systematic misfit a real calibration keeps
#: and no number of views averages away (a lens model a little too simple, a board flat to a
#: fraction of a millimetre, a detector's bias; OpenCV's sample pair fits to 0.17 px and its
#: residuals fail the randomness test); if a focal length 10 % off fits the views that well,
#: they cannot tell it from the true one, and every projection off the centre may be 10 % off.
#: For scale (640 x 480 unless said): the 13 views of OpenCV's sample pair allow 1.3 %, the
#: quickstart's spring trajectory 3-4 %, the paper's 4096 x 3072 camera 0.9 % (the 0.1 px is
#: a smaller share of a larger image), two views tilted 30 deg in directions 60 deg apart 2 %;
#: one view, parallel boards, boards facing the camera or tilted only left and right:
#: unbounded (the Jacobian is singular); boards tilted 3 deg: 100-500 %. The test is strict
#: where the geometry is weak: a lens of f = 2000 px (18 deg across 640 px) with the board
#: tilted 30 deg and filling 40 % of the height allows 13 % (refused); filling 70 %, 4 %.
AMBIGUITY_RMS_PX = 0.1
MAX_FOCAL_AMBIGUITY = 0.10
#: Below this eigenvalue of the unit-diagonal information matrix (relative to its largest) the
#: pinhole parameters are exactly undetermined: float64 rounding of a singular 4 x 4 matrix.
_SINGULAR = 1e-12


def _provisional_focal(Hs: np.ndarray, image_size) -> float | None:
    """f (px) of square pixels with the principal point at the image centre from homographies
    (V, 3, 3): Zhang's two constraints per view (h1' w h2 = 0, h1' w h1 = h2' w h2, w = K^-T
    K^-1) are then linear in f^2, solved by least squares; None when the views do not give it
    (boards facing the camera: the constraints vanish)."""
    w, h = image_size
    T = np.array([[1.0, 0.0, -(w - 1) / 2], [0.0, 1.0, -(h - 1) / 2], [0.0, 0.0, 1.0]])
    H = T @ Hs
    H = H / np.linalg.norm(H[:, :2, :2], axis=(1, 2))[:, None, None]
    h1, h2 = H[:, :, 0], H[:, :, 1]
    a = np.concatenate([h1[:, 0] * h2[:, 0] + h1[:, 1] * h2[:, 1],
                        h1[:, 0] ** 2 + h1[:, 1] ** 2 - h2[:, 0] ** 2 - h2[:, 1] ** 2])
    b = np.concatenate([h1[:, 2] * h2[:, 2], h1[:, 2] ** 2 - h2[:, 2] ** 2])
    f2 = -(a @ b) / (b @ b) if b @ b > 0 else -1.0
    return float(np.sqrt(f2)) if np.isfinite(f2) and f2 > 0 else None


def _provisional_poses(obs: Observations) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pinhole parameters (13,) of the OpenCV model with the distortion zeroed, and board poses
    (V, 3) x 2, fitted with the fewest assumptions that still give every view a pose: principal
    point at the image centre, fx, fy, k1, k2 free (the lens' distortion bends the homographies
    of a wide-angle camera enough to misplace the boards' normals by tens of degrees)."""
    w, h = obs.image_size
    Hs = fit_homographies([o[:, :2] for o in obs.object_points], obs.image_points)
    # Where f is undetermined any value shows the same degeneracy: a 53-degree field of view.
    f = _provisional_focal(Hs, obs.image_size) or float(max(w, h))
    cx, cy = (w - 1) / 2, (h - 1) / 2
    model = CameraModel()
    params = np.zeros(len(model.param_names))
    params[:4] = f, f, cx, cy
    rvecs, tvecs = extrinsics_from_homography(np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]]),
                                              Hs)
    try:
        fit = refine(model, params, free_mask(model.param_names, ("fx", "fy", "k1", "k2")),
                     obs.object_points, obs.image_points, rvecs, tvecs, max_iter=50)
        if np.all(np.isfinite(fit.params)) and np.all(fit.params[:2] > 0):
            params, rvecs, tvecs = fit.params.copy(), fit.rvecs, fit.tvecs
    except (ValueError, np.linalg.LinAlgError):
        pass  # the homographies' poses serve
    params[5:] = 0.0
    return params, np.asarray(rvecs), np.asarray(tvecs)


def view_geometry(obs: Observations) -> dict:
    """Whether one camera's views can determine its pinhole parameters (module docstring).

    Returns ``views``; ``focal_ambiguity`` {fx, fy}: the relative change of each that changes the
    RMS reprojection error by only AMBIGUITY_RMS_PX (inf where the Jacobian is singular);
    ``principal_point_ambiguity_px`` {cx, cy}: the same in pixels; ``normal_spread_deg``, the
    largest angle between two views' board normals, and ``tilt_deg`` [min, max], the boards'
    angles to the image plane (from provisional poses: principal point at the centre, fx, fy,
    k1, k2 fitted); ``board_span``, the median share of the image diagonal the detected points
    of a view span; ``provisional`` {fx, fy}; ``refused``: why the views cannot determine the
    camera, in words, or None, and ``refused_brief``, the same in a few words. ValueError when
    the provisional poses fail numerically (then nothing is known either way).
    """
    n = obs.n_views
    out = {"views": n, "min_views": MIN_VIEWS, "ambiguity_rms_px": AMBIGUITY_RMS_PX,
           "max_focal_ambiguity": MAX_FOCAL_AMBIGUITY}
    params, rvecs, tvecs = _provisional_poses(obs)
    normals = rodrigues_to_matrix(rvecs)[:, :, 2]
    cosines = np.clip(normals @ normals.T, -1.0, 1.0)
    out["normal_spread_deg"] = float(np.degrees(np.arccos(cosines.min())))
    tilt = np.degrees(np.arccos(np.clip(np.abs(normals[:, 2]), 0.0, 1.0)))
    out["tilt_deg"] = [float(tilt.min()), float(tilt.max())]
    out["provisional"] = {"fx": float(params[0]), "fy": float(params[1])}
    diagonal = float(np.hypot(*obs.image_size))
    out["board_span"] = float(np.median([np.linalg.norm(np.ptp(p, axis=0)) / diagonal
                                         for p in obs.image_points]))
    model = CameraModel()
    S = intrinsic_information(model, params, free_mask(model.param_names, PINHOLE_PARAMETERS),
                              obs.object_points, rvecs, tvecs)
    d = np.sqrt(np.maximum(np.diag(S), 0.0))
    if not np.all(np.isfinite(S)):
        raise ValueError(f"observations of {obs.camera_name!r}: the provisional poses gave a "
                         f"non-finite Jacobian")
    C = np.full(4, np.inf)
    if np.all(d > 0):
        ev = np.linalg.eigvalsh(S / np.outer(d, d))
        if ev[0] > _SINGULAR * ev[-1]:
            C = np.diag(np.linalg.inv(S))
    # Fixing one parameter and refitting the rest costs delta^2 / C of squared residuals
    # (C: its diagonal entry of the inverse information), so the RMS over N points grows by
    # AMBIGUITY_RMS_PX when delta = AMBIGUITY_RMS_PX sqrt(N C).
    delta = AMBIGUITY_RMS_PX * np.sqrt(obs.n_points * C)
    out["focal_ambiguity"] = {"fx": float(delta[0] / params[0]), "fy": float(delta[1] / params[1])}
    out["principal_point_ambiguity_px"] = {"cx": float(delta[2]), "cy": float(delta[3])}
    out["refused_brief"], out["refused"] = _refusal(out)
    return strict(out)


def _percent(x: float) -> str:
    return "an unbounded amount" if not np.isfinite(x) else f"{100 * x:,.0f} %"


def _refusal(g: dict) -> tuple[str, str] | tuple[None, None]:
    """Why views of the geometry ``g`` (view_geometry) cannot determine the camera, as a few
    words and in full, or (None, None)."""
    n = g["views"]
    if n < MIN_VIEWS:
        brief = f"{n} usable view, at least {MIN_VIEWS} needed"
        return brief, (f"{n} usable view; a view of a plane constrains only 2 of the 4 pinhole "
                       f"parameters fx, fy, cx, cy (its homography has 8 numbers, the board's "
                       f"pose takes 6): at least {MIN_VIEWS} views at different board "
                       f"orientations are needed, {MIN_VIEWS_WITH_SKEW} for Zhang's closed form "
                       f"with skew")
    worst = max(g["focal_ambiguity"].values())
    if worst <= MAX_FOCAL_AMBIGUITY:
        return None, None
    lo, hi = (round(t) for t in g["tilt_deg"])
    brief = f"its {n} views do not determine the focal length"
    return brief, (
        f"{brief}: with every board pose refitted, fx or fy can change by {_percent(worst)} "
        f"(at most {100 * MAX_FOCAL_AMBIGUITY:.0f} % accepted) while the RMS reprojection error "
        f"changes by only {AMBIGUITY_RMS_PX} px. The boards' normals lie within "
        f"{g['normal_spread_deg']:.1f} deg of each other, tilted "
        f"{lo if lo == hi else f'{lo}-{hi}'} deg from the image plane, and span "
        f"{100 * g['board_span']:.0f} % of the image diagonal (median): boards at one "
        f"orientation constrain the focal length no more than one, boards facing the camera "
        f"not at all, boards turned about one axis only (tilted left, then right) too little, "
        f"boards small in the image (far, or only part of them detected) little. Needed: at "
        f"least {MIN_VIEWS} views of the board filling much of the image, tilted 20-45 deg in "
        f"different directions (not only opposite ones)")
