"""Detect, calibrate every camera of a dataset with every method, and score against the truth.

This is the stage behind ``stereo-bench calibrate``. It writes, under the output directory::

    detections/<camera>.npz, timing.json    detections (reused when complete)
    calibrations/<method>/<camera>.json     the estimate (SynthCal JSON) ...
    calibrations/<method>/<camera>.yaml     ... and OpenCV FileStorage YAML
    calibrations/<method>/<camera>_views.npz  per-view cam_from_board (rvecs, tvecs, view_ids)
    metrics.json                            every number (see ``evaluate_dataset``)

A camera or method that fails is recorded with its error message; the others go on.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from .calibrate import CalibrationResult, Observations, get_calibrator
from .camera import Camera, matrix_to_rodrigues
from .dataset import Dataset
from .detect import CameraDetections, detect_dataset, detection_errors
from .metrics import parameter_errors, parameter_rmse, pose_errors, projection_difference, rpe_rms

MIN_POINTS = 8  # fewer detected corners than this hardly constrain a view
MIN_SPREAD = 0.2  # the board points' minor extent relative to their major one


def observations(det: CameraDetections, object_points: np.ndarray,
                 camera: Camera) -> tuple[Observations, dict[int, str]]:
    """The found views of one camera, each with its detected (finite) points, and the found
    views left out with the reason: too few points, or points nearly on a line (a partial
    ChArUco view of one row), which leave a view's homography, and so every closed-form
    initialization built on it, undetermined."""
    obj, img, ids, dropped = [], [], [], {}
    for f in np.flatnonzero(det.found):
        ok = np.isfinite(det.points[f]).all(axis=1)
        if ok.sum() < MIN_POINTS:
            dropped[int(f)] = f"{int(ok.sum())} points, need {MIN_POINTS}"
            continue
        sv = np.linalg.svd(object_points[ok, :2] - object_points[ok, :2].mean(0),
                           compute_uv=False)
        if sv[1] < MIN_SPREAD * sv[0]:
            dropped[int(f)] = f"points nearly collinear (spread {sv[1] / sv[0]:.2f})"
            continue
        obj.append(object_points[ok])
        img.append(det.points[f, ok])
        ids.append(int(f))
    if not ids:
        raise ValueError(f"camera {camera.name!r}: no usable view ({len(det.errors)} frames "
                         f"not found, e.g. {next(iter(det.errors.values()), '')!r}; "
                         f"{len(dropped)} found views left out)")
    return Observations(obj, img, camera.size, ids, camera.name), dropped


def load_or_detect(ds: Dataset, out: Path, progress=None) -> tuple[list[CameraDetections], float]:
    """Detections of every camera, read from ``out/detections`` when complete there, and the
    time the detection took when it ran (kept beside them, so reuse does not hide it)."""
    folder = out / "detections"
    paths = [folder / f"{cam.name}.npz" for cam in ds.cameras]
    timing = folder / "timing.json"
    if all(p.is_file() for p in paths) and timing.is_file():
        return ([CameraDetections.load(p) for p in paths],
                json.loads(timing.read_text())["detect_s"])
    start = time.perf_counter()
    dets = detect_dataset(ds, progress=progress)
    seconds = time.perf_counter() - start
    folder.mkdir(parents=True, exist_ok=True)
    for det, p in zip(dets, paths):
        det.save(p)
    timing.write_text(json.dumps({"detect_s": seconds}))  # written last: marks completion
    return dets, seconds


def score(result: CalibrationResult, obs: Observations, truth: Camera,
          true_cam_from_board: tuple[np.ndarray, np.ndarray]) -> dict:
    """Every accuracy number of one calibration against the true camera."""
    R, t = true_cam_from_board
    views = np.array(obs.view_ids)
    est = result.camera
    poses = pose_errors(result.rvecs, result.tvecs, matrix_to_rodrigues(R[views]), t[views])
    return {
        "rpe_rms_px": rpe_rms(est, result.rvecs, result.tvecs, obs.object_points,
                              obs.image_points),
        "paper_rmse": parameter_rmse(est, truth),
        "parameter_errors": parameter_errors(est, truth),
        "projection_difference": projection_difference(est, truth),
        "board_pose": {k: v for k, v in poses.items() if not isinstance(v, list)},
        "views": obs.n_views,
        "points": obs.n_points,
        "log": jsonable(result.log),
    }


def jsonable(x):
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return jsonable(x.tolist())
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return x.item()
    return x


def save_calibration(result: CalibrationResult, obs: Observations, folder: Path) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    name = result.camera.name
    result.camera.save_json(folder / f"{name}.json")
    result.camera.save_opencv_yaml(folder / f"{name}.yaml")
    np.savez(folder / f"{name}_views.npz", rvecs=result.rvecs, tvecs=result.tvecs,
             view_ids=np.array(obs.view_ids))


def evaluate_dataset(ds: Dataset, methods: list[str], out: Path, progress=None) -> dict:
    """Detect, calibrate with each method, score; write everything under ``out``.

    Returns the dict written to ``out/metrics.json``: ``detection[camera]`` (rate and error
    against the truth), ``calibration[method][camera]`` (see ``score``, or ``{"error": ...}``).
    """
    out = Path(out)
    for m in methods:  # fail early on a typo, before any work
        get_calibrator(m)
    dets, detect_s = load_or_detect(ds, out, progress)
    start = time.perf_counter()
    gt = ds.ground_truth
    rig = ds.rig()
    report = {"dataset": str(ds.root), "name": ds.config.name, "seed": ds.config.seed,
              "pattern": ds.config.pattern.kind, "environment": ds.config.environment.kind,
              "cameras": [c.name for c in ds.cameras], "methods": methods,
              "detection": {}, "calibration": {m: {} for m in methods},
              "timing": {"detect_s": detect_s}}
    for c, (cam, det) in enumerate(zip(ds.cameras, dets)):
        report["detection"][cam.name] = detection_errors(det, gt.points[c], gt.visible[c])
        truth = cam.with_params(rvec=np.zeros(3), tvec=np.zeros(3))
        try:
            obs, dropped = observations(det, ds.object_points, cam)
            report["detection"][cam.name]["views_left_out"] = dropped
        except ValueError as e:
            for m in methods:
                report["calibration"][m][cam.name] = {"error": str(e)}
            continue
        for m in methods:
            t0 = time.perf_counter()
            try:
                result = get_calibrator(m).calibrate(obs)
                result = CalibrationResult(result.camera.with_params(name=cam.name),
                                           result.rvecs, result.tvecs, result.log)
                save_calibration(result, obs, out / "calibrations" / m)
                entry = score(result, obs, truth, rig.cam_from_board(cam))
            except (ValueError, np.linalg.LinAlgError, RuntimeError) as e:
                entry = {"error": f"{type(e).__name__}: {e}"}
            entry["wall_time_s"] = time.perf_counter() - t0
            report["calibration"][m][cam.name] = entry
    report["timing"]["calibrate_s"] = time.perf_counter() - start
    (out / "metrics.json").write_text(json.dumps(jsonable(report), indent=2))
    return report
