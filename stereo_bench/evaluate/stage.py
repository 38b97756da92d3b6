"""Detect, calibrate every camera of a dataset with every method, and score against the truth.

Detection (``load_or_detect``) and calibration (``calibrate_cameras``) read only what a real
capture has too (cameras' names and image sizes, frames, images, the board), so a real capture
(``image_folders.ImageFolders``, ``stereo-bench calibrate-images``) runs the very same stages;
only ``evaluate_dataset``'s scoring against the truth (``score``, ``detection_errors``) is
synthetic. This is the stage behind ``stereo-bench calibrate``. It writes, in a trial's folder (paths built by
``rundir.TrialPaths``)::

    detections/<camera>.npz, done.json      detections; done.json marks them complete and holds
                                            their fingerprint and the detection's wall time
    calibrations/<method>/<camera>.json     the estimate (SynthCal JSON) ...
    calibrations/<method>/<camera>.yaml     ... and OpenCV FileStorage YAML
    calibrations/<method>/<camera>_views.npz  per-view cam_from_board (rvecs, tvecs, view_ids)
    metrics.json                            every number (see ``evaluate_dataset``); it marks
                                            the stage complete for its fingerprint

A camera or method that fails is recorded with its error message; the others go on.
"""

from __future__ import annotations

import shutil
import time
from dataclasses import dataclass

import numpy as np

from ..calibrate import fits_board_warp, CalibrationResult, Observations, get_calibrator
from ..core.camera import Camera
from ..core.poses import matrix_to_rodrigues
from ..config.schema import CalibrationConfig
from ..scene.dataset import Dataset
from ..detect.dataset import (CameraDetections, DatasetDetections, detect_dataset,
                              detection_errors)
from ..detect.boards import resolve_method
from ..io import opencv_yaml
from .metrics import (parameter_errors, parameter_rmse, pose_errors, projection_difference, rpe_rms,
                      validity)
from ..io.rundir import Notes, TrialPaths, fingerprint, reusable, with_outputs
from ..core.files import strict, write_json, write_npz

MIN_POINTS = 8  # fewer detected corners than this hardly constrain a view
MIN_SPREAD = 0.2  # the board points' minor extent relative to their major one


def unusable_view(object_points: np.ndarray) -> str | None:
    """Why the detected board points (K, 3) of one view cannot start a calibration or a pose,
    or None: too few points, or points nearly on a line (a partial ChArUco view of one row),
    which leave the view's homography, and every closed-form initialization built on it,
    undetermined."""
    if len(object_points) < MIN_POINTS:
        return f"{len(object_points)} points, need {MIN_POINTS}"
    sv = np.linalg.svd(object_points[:, :2] - object_points[:, :2].mean(0), compute_uv=False)
    if sv[1] < MIN_SPREAD * sv[0]:
        return f"points nearly collinear (spread {sv[1] / sv[0]:.2f})"
    return None


def observations(det: CameraDetections, object_points: np.ndarray,
                 camera: Camera, frames: np.ndarray | None = None,
                 ) -> tuple[Observations, dict[int, str]]:
    """The found views of one camera, each with its detected (finite) points, and the found
    views left out with the reason (``unusable_view``). ``frames`` (F,) bool: the frames the
    views may come from (default: all)."""
    obj, img, ids, dropped = [], [], [], {}
    allowed = det.found if frames is None else det.found & frames
    for f in np.flatnonzero(allowed):
        ok = np.isfinite(det.points[f]).all(axis=1)
        reason = unusable_view(object_points[ok])
        if reason:
            dropped[int(f)] = reason
            continue
        obj.append(object_points[ok])
        img.append(det.points[f, ok])
        ids.append(int(f))
    if not ids:
        outside = int((det.found & ~allowed).sum())
        raise ValueError(f"camera {camera.name!r}: no usable view ({len(det.errors)} frames "
                         f"not found, e.g. {next(iter(det.errors.values()), '')!r}; "
                         f"{len(dropped)} found views left out"
                         + (f"; {outside} found views outside calibration.intrinsics_views"
                            if outside else "") + ")")
    return Observations(obj, img, camera.size, ids, camera.name), dropped


def detections_fingerprint(ds: Dataset) -> str:
    return fingerprint("detections", ds.fingerprint, resolve_method(ds.pattern, None))


def load_or_detect(ds: Dataset, trial: TrialPaths, progress=None, notes: Notes | None = None,
                   detected: DatasetDetections | None = None,
                   ) -> tuple[list[CameraDetections], float, str]:
    """Detections of every camera, reused when ``trial``'s marker was written for this dataset,
    the time the detection took when it ran (kept in the marker, so reuse does not hide it),
    and the detections' fingerprint. ``detected``: the dataset's detections already made (as
    it was rendered), saved as this stage's."""
    fp = detections_fingerprint(ds)
    if detected is not None:
        if detected.method != resolve_method(ds.pattern, None):
            raise ValueError(f"detections by {detected.method!r} given for a dataset of "
                             f"{ds.pattern.kind}")
        return _saved(trial, detected.result([c.name for c in ds.cameras], ds.frames),
                      detected.seconds, fp)
    marker = reusable(trial.detections_done, fp, notes, "detection")
    if marker is not None:
        try:
            return ([CameraDetections.load(trial.detection(c.name)) for c in ds.cameras],
                    float(marker["detect_s"]), fp)
        except (ValueError, KeyError, TypeError) as e:
            if notes:
                notes.add(f"{trial.detections}: {e}; redoing the detection stage")
    start = time.perf_counter()
    dets = detect_dataset(ds, progress=progress)
    return _saved(trial, dets, time.perf_counter() - start, fp)


def _saved(trial: TrialPaths, dets: list[CameraDetections], seconds: float, fp: str):
    trial.detections_done.unlink(missing_ok=True)
    for det in dets:
        det.save(trial.detection(det.camera))
    write_json(trial.detections_done,  # marks completion
               with_outputs({"fingerprint": fp, "detect_s": seconds}, trial.detections_done,
                            [trial.detection(d.camera) for d in dets]))
    return dets, seconds, fp


def summary(result: CalibrationResult, obs: Observations) -> dict:
    """What one calibration says of itself, without any truth: its fit to the detections, where
    its model can be used, how much data it saw, and its log."""
    return {
        "rpe_rms_px": rpe_rms(result.camera, result.rvecs, result.tvecs,
                              result.board_points(obs), obs.image_points),
        "validity": validity(result.camera),
        "views": obs.n_views,
        "points": obs.n_points,
        "log": strict(result.log),
    }


def score(result: CalibrationResult, obs: Observations, truth: Camera,
          true_cam_from_board: tuple[np.ndarray, np.ndarray]) -> dict:
    """Every accuracy number of one calibration against the true camera (the scoring step:
    the only one a real capture lacks)."""
    R, t = true_cam_from_board
    views = np.array(obs.view_ids)
    est = result.camera
    poses = pose_errors(result.rvecs, result.tvecs, matrix_to_rodrigues(R[views]), t[views])
    return {
        "paper_rmse": parameter_rmse(est, truth),
        "parameter_errors": parameter_errors(est, truth),
        "projection_difference": projection_difference(est, truth),
        "validity": validity(est, truth),  # over the pixels the true lens sees
        "board_pose": {k: v for k, v in poses.items() if not isinstance(v, list)},
    }


def save_calibration(result: CalibrationResult, obs: Observations, trial: TrialPaths,
                     method: str) -> None:
    name = result.camera.name
    result.camera.save_json(trial.calibration(method, name))
    opencv_yaml.write_camera(result.camera, trial.calibration_yaml(method, name))
    # The board's shape it fitted, which the rig stage gives its board (pipeline.fitted_board).
    shape = {k: np.asarray(result.log[k]) for k in ("board_warp_mm", "board_aspect_error_pct",
                                                    "board_grid_mm")
             if k in result.log}
    write_npz(trial.views(method, name), rvecs=result.rvecs, tvecs=result.tvecs,
              view_ids=np.array(obs.view_ids), **shape)


def metrics_fingerprint(detections_fp: str, methods: list[str],
                        calibration: CalibrationConfig) -> str:
    """What the per-camera calibrations depend on: the detections, the methods, the views the
    intrinsics come from and whether the board's warp is fitted (the rig stage's settings are in
    ``pipeline.rig_fingerprint``)."""
    warp = ["board warp"] if calibration.fit_board_warp else []  # earlier runs keep theirs
    return fingerprint("metrics", detections_fp, list(methods), calibration.intrinsics_views,
                       *warp)


def warp_option(method: str, calibration: CalibrationConfig) -> dict:
    """The calibrator's options for ``calibration.fit_board_warp``: the methods that can fit
    the board's warp do (the others keep a flat board, and say so in their log)."""
    return {"board_warp": True} if calibration.fit_board_warp and fits_board_warp(method) \
        else {}


def intrinsics_frames(ds: Dataset, camera: int, calibration: CalibrationConfig) -> np.ndarray:
    """(F,) bool: the frames camera ``camera``'s intrinsics may come from
    (``calibration.intrinsics_views``: all, the camera's own close-ups, or the session walk)."""
    which = calibration.intrinsics_views
    if which == "closeups":
        return ds.closeup_of == camera
    if which == "session":
        return ds.closeup_of < 0
    return np.ones(ds.frames, bool)


@dataclass(frozen=True, eq=False)
class Estimate:
    """One camera's calibration by one method and the views it came from."""

    result: CalibrationResult
    obs: Observations


def with_given_intrinsics(camera: Camera, obs: Observations) -> CalibrationResult:
    """A camera whose intrinsics come from elsewhere (``camera``: a calibration file's), with the
    board pose of each view of ``obs`` fitted through them (pose.planar_pose: the homography,
    then the reprojection error's minimum with the intrinsics fixed)."""
    from ..calibrate.pose import planar_pose

    poses = [planar_pose(camera, o, i) for o, i in zip(obs.object_points, obs.image_points)]
    return CalibrationResult(camera.with_params(name=obs.camera_name, rvec=np.zeros(3),
                                                tvec=np.zeros(3)),
                             np.array([r for r, _ in poses]), np.array([t for _, t in poses]),
                             {"method": "given", "notes": ["intrinsics given, poses fitted"]})


def calibrate_cameras(source, dets: list[CameraDetections], methods: list[str],
                      trial: TrialPaths, calibration: CalibrationConfig,
                      given: dict[str, Camera] | None = None, workers=1
                      ) -> tuple[dict, dict[tuple[str, str], Estimate], dict]:
    """Calibrate every camera of ``source`` (a rendered ``Dataset`` or a real capture's
    ``ImageFolders``: they share this stage) with every method, saving each estimate under
    ``trial``. A camera in ``given`` (name -> Camera) keeps those intrinsics for every method,
    only its board poses fitted (``with_given_intrinsics``), and its entries say so.
    The cameras are independent: with ``workers`` (a count, or the command's
    ``run.workers.Workers``) they are calibrated that many at a time.

    Returns ``entries[method][camera]`` (``summary`` plus the wall time, or ``{"error": ...}``),
    the estimates by (method, camera), and per camera the found views left out with the reason
    (``observations``) or, when the camera has no usable view, the reason as a string.
    """
    from ..run.workers import in_processes

    jobs = [(source, c, det, methods, trial, calibration, (given or {}).get(cam.name))
            for c, (cam, det) in enumerate(zip(source.cameras, dets))]
    entries = {m: {} for m in methods}
    estimates, left_out = {}, {}
    for cam, (done, made, dropped) in zip(source.cameras,
                                          in_processes(_calibrate_camera, jobs, workers)):
        left_out[cam.name] = dropped
        for m in methods:
            entries[m][cam.name] = done[m]
            if m in made:
                estimates[m, cam.name] = made[m]
    return entries, estimates, left_out


def _calibrate_camera(args) -> tuple[dict, dict[str, Estimate], dict | str]:
    """One camera of ``calibrate_cameras``: its entries and estimates by method, and its views
    left out (or why it has none)."""
    source, c, det, methods, trial, calibration, given = args
    cam = source.cameras[c]
    try:
        obs, dropped = observations(det, source.object_points, cam,
                                    intrinsics_frames(source, c, calibration))
    except ValueError as e:
        return {m: {"error": str(e)} for m in methods}, {}, str(e)
    entries, estimates = {}, {}
    for m in methods:
        t0 = time.perf_counter()
        try:
            result = (with_given_intrinsics(given, obs) if given is not None else
                      get_calibrator(m, **warp_option(m, calibration)).calibrate(obs))
            result = CalibrationResult(result.camera.with_params(name=cam.name),
                                       result.rvecs, result.tvecs, result.log)
            save_calibration(result, obs, trial, m)
            entry = summary(result, obs)
            if given is not None:
                entry["intrinsics_given"] = True
            estimates[m] = Estimate(result, obs)
        except (ValueError, np.linalg.LinAlgError, RuntimeError) as e:
            entry = {"error": f"{type(e).__name__}: {e}"}
        entry["wall_time_s"] = time.perf_counter() - t0
        entries[m] = entry
    return entries, estimates, dropped


def clear_calibrations(trial: TrialPaths) -> None:
    """Estimates of an earlier calibration must not outlive it: a camera that fails now would
    otherwise leave its old estimate where the plots and the rig stage look for it."""
    trial.metrics.unlink(missing_ok=True)
    shutil.rmtree(trial.all_calibrations, ignore_errors=True)


def evaluate_dataset(ds: Dataset, methods: list[str], trial: TrialPaths,
                     calibration: CalibrationConfig, progress=None,
                     notes: Notes | None = None,
                     detected: DatasetDetections | None = None, workers=1) -> dict:
    """Detect (or take the detections ``detected`` as the dataset was rendered), calibrate with
    each method (the cameras ``workers`` at a time, ``calibrate_cameras``), score; write
    everything under ``trial``.

    ``calibration``: the settings of the calibration stage, from the rig file of the run (they
    may have changed since the images were rendered; the dataset does not hold them).

    Returns the dict written to ``trial.metrics``: ``detection[camera]`` (rate and error
    against the truth), ``calibration[method][camera]`` (``summary`` and ``score``, or
    ``{"error": ...}``), ``fingerprint`` (of the detections and the methods: what a rerun must
    match to reuse it).
    """
    for m in methods:  # fail early on a typo, before any work
        get_calibrator(m)
    dets, detect_s, det_fp = load_or_detect(ds, trial, progress, notes, detected)
    clear_calibrations(trial)
    start = time.perf_counter()
    gt = ds.ground_truth
    rig = ds.rig()
    inside = ds.root.resolve().is_relative_to(trial.root.resolve())
    entries, estimates, left_out = calibrate_cameras(ds, dets, methods, trial, calibration,
                                                     workers=workers)
    report = {"fingerprint": metrics_fingerprint(det_fp, methods, calibration),
              "intrinsics_views": calibration.intrinsics_views,
              # Relative inside the trial, so that two runs into different folders agree.
              "dataset": (ds.root.resolve().relative_to(trial.root.resolve()).as_posix()
                          if inside else str(ds.root)),
              "name": ds.config.name, "seed": ds.config.seed,
              "pattern": ds.config.pattern.kind, "environment": ds.config.environment.kind,
              "cameras": [c.name for c in ds.cameras], "methods": methods,
              "warnings": ds.warnings,
              "detection": {}, "calibration": entries,
              "timing": {"detect_s": detect_s}}
    for c, (cam, det) in enumerate(zip(ds.cameras, dets)):
        report["detection"][cam.name] = detection_errors(det, gt.points[c], gt.visible[c])
        if isinstance(left_out[cam.name], dict):
            report["detection"][cam.name]["views_left_out"] = left_out[cam.name]
        truth = cam.with_params(rvec=np.zeros(3), tvec=np.zeros(3))
        for m in methods:
            if (m, cam.name) in estimates:
                est = estimates[m, cam.name]
                entries[m][cam.name].update(score(est.result, est.obs, truth,
                                                  rig.cam_from_board(cam)))
    report["timing"]["calibrate_s"] = time.perf_counter() - start
    # The detections too: the later stages and the plots read them beside the calibrations.
    outputs = [p for p in trial.all_calibrations.rglob("*") if p.is_file()] + \
        [trial.detection(c.name) for c in ds.cameras]
    write_json(trial.metrics, with_outputs(report, trial.metrics, outputs))
    return strict(report)
