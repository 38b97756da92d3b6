"""What a calibration's own data say about it, without ground truth.

A calibration of real images has no truth to score against; these checks use only the detections,
the estimate and its board poses (CalibrationResult), and return JSON-ready dicts.

* ``heldout``: k-fold cross-validation over views. The method calibrates on k-1 folds; each
  held-out view's pose is fitted with those intrinsics fixed (stereo.planar_pose) and its RMS
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
"""

from __future__ import annotations

import math
from typing import Sequence

import cv2
import numpy as np

from .calibrate import get_calibrator
from .calibrate.base import Observations
from .calibrate.refine import OpenCVModel, free_mask, linearize
from .camera import Camera, project_points
from .rundir import strict
from .stereo import planar_pose
from .uncertainty import check_poses

MIN_TRAINING_VIEWS = 3  # Zhang's minimum for the five pinhole intrinsics (section 3.1)
MODIFIED_Z = 3.5  # Iglewicz & Hoaglin's recommended cut on the modified z-score
_CALIBRATION_ERRORS = (ValueError, np.linalg.LinAlgError, RuntimeError, cv2.error)


def view_residuals(camera: Camera, obs: Observations, rvecs, tvecs) -> list[np.ndarray]:
    """Per view (N_i, 2) px: projected - detected, through the camera and the view's pose."""
    rv, tv = check_poses(obs, rvecs, tvecs)
    return [project_points(o, camera.intrinsics, camera.dist, r, t) - p
            for o, p, r, t in zip(obs.object_points, obs.image_points, rv, tv)]


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
    model = OpenCVModel()
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


def heldout(method: str, obs: Observations, k: int = 5, seed: int = 0) -> dict:
    """k-fold cross-validated reprojection error of calibration ``method`` (registry name).

    Views are shuffled with ``seed`` and split into k folds; each fold is held out in turn, the
    method calibrates on the others, and every held-out view gets its pose from the trained
    camera (intrinsics fixed, stereo.planar_pose). With fewer than k views each view is its own
    fold (``folds`` < ``k_requested`` and ``note`` says so); every training set keeps at least
    MIN_TRAINING_VIEWS views. The same method's calibration on all views gives the in-sample
    error of the same points.

    Returns ``heldout_rms_px`` and ``in_sample_rms_px`` (over the views that have both),
    ``ratio`` (held-out over in-sample), ``train_rms_px`` (the folds' own fits), ``views``: a list
    of {view_id, fold, heldout_rms_px, in_sample_rms_px, error}, ``fold_errors`` (fold -> why its
    calibration failed), ``folds``, ``k_requested``, ``note``, ``method``, ``seed``.
    """
    calibrator = get_calibrator(method)
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
    in_sample = view_residuals(full.camera, obs, full.rvecs, full.tvecs)
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
        train_res += view_residuals(fit.camera, _subset(obs, train), fit.rvecs, fit.tvecs)
        for i in test:
            o, p = obs.object_points[i], obs.image_points[i]
            try:
                rvec, tvec = planar_pose(fit.camera, o, p)
            except _CALIBRATION_ERRORS as e:  # e.g. a held-out corner beyond the trained fold
                errors[i] = f"{type(e).__name__}: {e}"
                continue
            heldout_res[i] = project_points(o, fit.camera.intrinsics, fit.camera.dist, rvec,
                                            tvec) - p
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
