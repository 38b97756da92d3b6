"""`stereo-bench RIG.yaml`: render -> detect -> calibrate -> rig calibration -> triangulate ->
metrics, over trials, with every stage saved so a rerun reuses what is complete.

The run directory's layout is owned by ``rundir`` (RunPaths, TrialPaths). A stage is reused only
when its marker (dataset: manifest.json; detection: detections/done.json; calibration:
metrics.json; rig: rig/<method>.json) is readable and carries the fingerprint of exactly what the
stage depends on now; otherwise it is redone and the run's notes say which and why. So an edited
rig file rerun into the same folder gives the new configuration's results, and an interrupted or
torn stage is redone. ``run`` holds the run directory's lock: a second run into it is refused.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..calibrate import get_calibrator
from ..calibrate.base import MIN_POINTS_PER_VIEW, fitted_shape
from ..core.camera import Camera
from ..config.schema import CalibrationConfig, RigConfig
from ..scene.dataset import Dataset, dataset_fingerprint, write_dataset
from ..detect.dataset import CameraDetections, DatasetDetections
from ..evaluate.stage import (detections_fingerprint, evaluate_dataset, metrics_fingerprint,
                              unusable_view)
from ..multiview.orientation import agree, numbered_like
from ..scene.rig import volume_centre
from ..io.rundir import (Notes, RunPaths, TrialPaths, changed_output, fingerprint, locked, reusable,
                         with_outputs)
from ..core.files import UnreadableFileError, read_arrays, read_json, strict, write_json
from ..multiview.bundle import (RigCalibration, aligned_rig_errors, calibrate_rig, rig_errors,
                                similarity_transform)
from ..calibrate.pose import planar_pose
from ..multiview.triangulate import triangulate
from .workers import in_processes


#: Shells of distance from the volume's centre in which RMSE_cal is also reported, mm.
REGION_EDGES_MM = (0.0, 500.0, 1000.0, 1500.0, 2000.0, np.inf)


def _board_poses(ds: Dataset, trial: TrialPaths, method: str, cam: Camera,
                 det: CameraDetections) -> tuple[np.ndarray, np.ndarray]:
    """Per frame cam_from_board (F, 3) x 2 for one camera: the poses its own calibration found,
    and for the other frames it detected (not among the views its intrinsics came from, see
    calibration.intrinsics_views) a planar pose through its estimate; NaN elsewhere."""
    F = ds.frames
    r, t = np.full((F, 3), np.nan), np.full((F, 3), np.nan)
    z = read_arrays(trial.views(method, cam.name), "a calibration's views")
    r[z["view_ids"]], t[z["view_ids"]] = z["rvecs"], z["tvecs"]
    for f in np.flatnonzero(det.found & ~np.isfinite(r).all(axis=1)):
        ok = np.isfinite(det.points[f]).all(axis=1)
        if unusable_view(ds.object_points[ok]):
            continue
        try:
            r[f], t[f] = planar_pose(cam, ds.object_points[ok], det.points[f, ok])
        except (ValueError, np.linalg.LinAlgError):
            continue  # a view the estimate cannot undistort starts nothing
    return r, t


def _by_region(true_pts: np.ndarray, err: np.ndarray, centre: np.ndarray) -> list[dict]:
    """RMSE_cal per shell of distance from the volume's centre (REGION_EDGES_MM)."""
    d = np.linalg.norm(true_pts - centre, axis=-1)
    rows = []
    for lo, hi in zip(REGION_EDGES_MM, REGION_EDGES_MM[1:]):
        inside = (d >= lo) & (d < hi)
        if inside.any():
            rows.append({"from_mm": lo, "to_mm": hi, "points": int(inside.sum()),
                         "rmse_cal_mm": float(np.sqrt(np.mean(err[inside] ** 2)))})
    return rows


def fitted_board(object_points: np.ndarray, trial: TrialPaths, method: str, cameras):
    """The board's shape (core/board_shape.py) as the method's calibrations fitted it (the mean
    of their warps and aspect errors; calibration.fit_board_warp), or None."""
    logs = [{k: v.tolist() for k, v in read_arrays(trial.views(method, cam.name),
                                                     "a calibration's views").items()}
            for cam in cameras]
    return fitted_shape(object_points, logs)


def rig_of(source, trial: TrialPaths, method: str, calibration: CalibrationConfig,
           names: list[str] | None = None) -> tuple[RigCalibration, np.ndarray]:
    """The rig calibration of one method's per-camera estimates (saved under ``trial`` by
    stage.calibrate_cameras) and the detections it used, (C, F, N, 2) px, with each frame's
    views numbered alike (orientation.agree; what it changed is in the rig's log under
    "orientation"). ``source`` is a rendered ``Dataset`` or a real capture: this stage does not
    know which. ``names``: the cameras to join (default: all)."""
    chosen = [c for c in source.cameras if names is None or c.name in names]
    dets = [CameraDetections.load(trial.detection(c.name)) for c in chosen]
    cams, rv, tv = [], [], []
    for cam, det in zip(chosen, dets):
        est = Camera.load_json(trial.calibration(method, cam.name))
        r, t = _board_poses(source, trial, method, est, det)
        cams.append(est)
        rv.append(r)
        tv.append(t)
    shape = fitted_board(source.object_points, trial, method, chosen)
    image_points, rvecs, tvecs, found, changes = agree(
        source.object_points if shape is None else shape.points(source.object_points),
        np.stack([d.points for d in dets]), np.stack(rv), np.stack(tv),
        np.stack([d.found for d in dets]), [c.name for c in chosen],
        identified=source.pattern.kind == "charuco")
    params = get_calibrator(method).model_parameters if calibration.refine_intrinsics else None
    # With the board's shape fitted by the cameras, the rig refines it from there, jointly.
    rig = calibrate_rig(cams, source.object_points, image_points, rvecs, tvecs,
                        found, refine_intrinsics=[params] * len(cams) if params else None,
                        loss=calibration.loss, loss_scale_px=calibration.loss_scale_px,
                        board=shape)
    rig.log["orientation"] = changes
    return rig, image_points


def triangulated_board(cameras: list[Camera], image_points: np.ndarray
                       ) -> tuple[np.ndarray, dict[str, int]]:
    """The board's points triangulated in every frame through a rig's cameras (cam_from_cam0),
    (F, N, 3) mm in the reference camera's frame (NaN where fewer than two cameras saw them), and
    per camera the number of detections it could not use: those where its estimated distortion
    has no unique ray (an overfitted model folds inside the image, TRAPS.md); they are masked,
    not fatal."""
    pts = image_points.copy()
    dropped = {}
    for c, cam in enumerate(cameras):
        seen = np.isfinite(pts[c]).all(-1)
        bad = seen.copy()
        bad[seen] = ~cam.invertible(pts[c][seen])
        pts[c][bad] = np.nan
        dropped[cam.name] = int(bad.sum())
    return triangulate(cameras, pts), dropped


def board_geometry(points: np.ndarray, object_points: np.ndarray) -> dict:
    """How well the triangulated board keeps its known shape, which needs no truth: per frame
    with at least MIN_POINTS_PER_VIEW triangulated points, the rigid motion that best maps the
    board's layout onto them; ``rmse_mm`` is the RMS distance left (wrong intrinsics or a wrong
    rig bend the board), and ``scale_error_pct`` the mean size error of the triangulated board
    from a similarity fit (a wrong baseline scales it)."""
    resid, scales = [], []
    for frame in points:
        ok = np.isfinite(frame).all(-1)
        if ok.sum() < MIN_POINTS_PER_VIEW:
            continue
        try:
            s, R, t = similarity_transform(object_points[ok], frame[ok])
            _, R1, t1 = similarity_transform(object_points[ok], frame[ok], scale=False)
        except ValueError:  # points on a line fix no pose
            continue
        resid.append(np.linalg.norm(object_points[ok] @ R1.T + t1 - frame[ok], axis=-1))
        scales.append(s)
    if not resid:
        return {"frames": 0, "rmse_mm": None, "scale_error_pct": None}
    r = np.concatenate(resid)
    return {"frames": len(resid), "rmse_mm": float(np.sqrt(np.mean(r**2))),
            "max_mm": float(r.max()), "scale_error_pct": float(100 * (np.mean(scales) - 1))}


def rig_summary(rig: RigCalibration, image_points: np.ndarray, object_points: np.ndarray,
                method: str, calibration: CalibrationConfig) -> tuple[dict, np.ndarray]:
    """What a rig calibration says of itself, without any truth, and its triangulated board
    (``triangulated_board``), which the scoring step compares with the truth."""
    points, dropped = triangulated_board(rig.cameras, image_points)
    entry = {
        "method": method,
        "reference": rig.cameras[0].name,
        "cameras": [c.to_dict() for c in rig.cameras],
        "rms_px": rig.rms_px,
        "rms_px_per_camera": rig.rms_px_per_camera,
        "frames_used": int(rig.frames_used.sum()),
        "iterations": rig.iterations,
        "time_s": rig.time_s,
        # cam_from_cam0 of each camera, as a user reads a rig: baseline and relative rotation.
        "baseline_mm": {c.name: float(np.linalg.norm(c.center)) for c in rig.cameras},
        "rotation_deg": {c.name: float(np.degrees(np.linalg.norm(c.rvec)))
                         for c in rig.cameras},
        "board_geometry": board_geometry(points, object_points),
        "detections_outside_model": dropped,
        "log": rig.log,
    }
    if calibration.refine_intrinsics and not get_calibrator(method).model_parameters:
        entry["note"] = (f"{method}'s model is not a subset of OpenCV's: its intrinsics stay as "
                         f"estimated in the rig's bundle adjustment (calibration."
                         f"refine_intrinsics)")
    return entry, points


def score_rig(cameras: list[Camera], est_pts: np.ndarray, ds: Dataset) -> dict:
    """A rig's cameras (cam_from_cam0) against the truth (the scoring step).

    RMSE_cal (paper Sec. 4.2): the board's feature points triangulated in every frame through the
    estimated rig (DLT then reprojection refinement) against their true positions, both in the
    reference camera's frame, in mm, over the whole volume and per shell of distance from its
    centre (the point nearest every camera's axis for a studio, else the mean board point);
    ``centre_rmse_mm`` does the same for the board's centre (the mean of the points triangulated
    in a frame against the mean of the same points' truth). Per camera: rotation and centre errors
    with the reference camera fixed, and again after a similarity alignment (3+ cameras), beside
    the reprojection error (added by ``rig_calibration``), so that a low reprojection error
    cannot hide a wrong geometry.
    """
    truth = ds.cameras
    world_pts = ds.rig().board_points_world()  # (F, N, 3)
    true_pts = truth[0].world_to_cam(world_pts)
    if ds.pattern.kind != "charuco":  # which corner of a symmetric board is first: a convention
        est_pts = numbered_like(est_pts, true_pts, ds.object_points)
    ok = np.all(np.isfinite(est_pts), axis=-1)
    err = np.linalg.norm(est_pts - true_pts, axis=-1)[ok]
    # Per frame, the centroid of the points triangulated in it against the centroid of the same
    # points' truth: a studio's partial views rarely triangulate the whole board.
    frames = ok.sum(axis=1) >= MIN_POINTS_PER_VIEW
    w = ok[frames][..., None]
    diff = np.where(w, est_pts[frames] - true_pts[frames], 0.0)  # NaN where not triangulated
    centre_err = np.linalg.norm(diff.sum(1) / w.sum(1), axis=-1)
    try:
        centre = truth[0].world_to_cam(volume_centre(truth))
    except ValueError:  # cameras that look one way: the middle of the board's path
        centre = true_pts.reshape(-1, 3).mean(0)
    errors = rig_errors(cameras, truth)
    entry = {
        "rmse_cal_mm": float(np.sqrt(np.mean(err**2))) if len(err) else float("nan"),
        "mean_error_mm": float(err.mean()) if len(err) else float("nan"),
        "max_error_mm": float(err.max()) if len(err) else float("nan"),
        "centre_rmse_mm": float(np.sqrt(np.mean(centre_err**2))) if len(centre_err)
        else float("nan"),
        "rmse_cal_by_region": _by_region(true_pts[ok], err, centre),
        "points_triangulated": int(ok.sum()),
        "rig_errors": {k: v[1:] for k, v in errors.items()},  # camera 0 is 0 by construction
        "camera_errors": {c.name: {"rotation_deg": float(errors["rotation_deg"][i]),
                                   "centre_mm": float(errors["centre_mm"][i])}
                          for i, c in enumerate(truth)},
    }
    try:
        aligned = aligned_rig_errors(cameras, truth)
        entry["aligned"] = {"scale": aligned["scale"], "cameras": {
            c.name: {"rotation_deg": float(aligned["rotation_deg"][i]),
                     "centre_mm": float(aligned["centre_mm"][i])} for i, c in enumerate(truth)}}
    except ValueError as e:
        entry["aligned"] = None
        entry["aligned_reason"] = str(e)
    return entry


def rig_calibration(ds: Dataset, trial: TrialPaths, method: str,
                    calibration: CalibrationConfig) -> dict:
    """Calibrate the rig from one method's per-camera estimates (``rig_of``, ``rig_summary``:
    shared with real captures) and score it against the truth (``score_rig``)."""
    rig, image_points = rig_of(ds, trial, method, calibration)
    entry, points = rig_summary(rig, image_points, ds.object_points, method, calibration)
    entry.update(score_rig(rig.cameras, points, ds))
    for c, rms in zip(ds.cameras, rig.rms_px_per_camera):
        entry["camera_errors"][c.name]["rms_px"] = float(rms)
    return entry


def rig_settings(calibration: CalibrationConfig) -> dict:
    """The settings the rig stage reads (the rest of ``calibration`` is the calibration
    stage's)."""
    return calibration.model_dump(mode="json", include={"refine_intrinsics", "loss",
                                                        "loss_scale_px"})


def rig_fingerprint(metrics_fp: str, method: str, settings: dict | None = None) -> str:
    """What a rig calibration depends on: the calibrations it starts from, its method and the
    rig stage's settings (``rig_settings``; None: the defaults)."""
    return fingerprint("rig", metrics_fp, method,
                       settings if settings is not None else rig_settings(CalibrationConfig()))


def dataset_of(cfg: RigConfig, trial: TrialPaths, dataset_dir: Path | None, progress,
               notes: Notes, workers=1) -> tuple[Dataset, DatasetDetections | None]:
    """The trial's dataset: an existing one (``dataset_dir``), or the trial's own, reused when
    it was rendered from this configuration and rendered again otherwise (its cameras
    ``workers`` at a time); with the detections of its images when it was rendered here (each
    image detected as it was made, not read back from its file), else None."""
    if dataset_dir is not None:
        return Dataset.load(dataset_dir), None
    paths = trial.dataset
    try:
        ds = Dataset.load(paths.root)
        if ds.fingerprint == dataset_fingerprint(cfg):
            return ds, None
        notes.stage_redone(f"{paths.manifest}: rendered from another configuration (the rig "
                           f"file changed); rendering again")
    except FileNotFoundError:
        pass
    except UnreadableFileError as e:
        notes.stage_redone(f"{e}; rendering again")
    found = DatasetDetections(cfg.pattern.build())
    return write_dataset(cfg, paths.root, progress, found, workers), found


def run_trial(cfg: RigConfig, out: Path, methods: list[str], progress=None,
              dataset_dir: Path | None = None, with_rig: bool = True, workers=1) -> dict:
    """One trial (one seed): every stage, each reused when its marker matches (module docstring).

    ``dataset_dir``: an existing dataset to use instead of rendering into the trial directory.
    ``workers`` (a count, or the command's ``workers.Workers``): processes that render and
    detect the cameras (``write_dataset``), calibrate them and make the methods' rigs.
    The returned report (the trial's metrics.json plus ``rig``, ``timing`` and ``notes``) says in
    ``notes`` which stages were redone and why, and carries the dataset's warnings.
    """
    trial = RunPaths(Path(out)).trial(cfg.seed)
    notes = Notes()
    ds, detected = dataset_of(cfg, trial, dataset_dir, progress, notes, workers)
    expected = metrics_fingerprint(detections_fingerprint(ds), methods, cfg.calibration)
    report = reusable(trial.metrics, expected, notes, "calibration")
    if report is None:
        report = evaluate_dataset(ds, methods, trial, cfg.calibration, progress, notes,
                                  detected, workers)
    report["rig"] = {}
    if with_rig and len(ds.cameras) >= 2:
        settings = rig_settings(cfg.calibration)
        todo = {}
        for m in methods:
            rig_fp = rig_fingerprint(report["fingerprint"], m, settings)
            entry = reusable(trial.rig(m), rig_fp, notes, f"rig calibration of {m}")
            if entry is not None:
                report["rig"][m] = entry
            else:
                failed = [e["error"] for e in report["calibration"][m].values() if "error" in e]
                todo[m] = (str(ds.root), str(out), cfg.seed, m,
                           cfg.calibration.model_dump(mode="json"), failed, rig_fp, settings)
        # The methods' rigs are independent: with workers they are made side by side.
        made = dict(zip(todo, in_processes(_rig_job, list(todo.values()), workers)))
        for m in methods:  # the report in the methods' order, reused or made
            if m in made:
                write_json(trial.rig(m), with_outputs(made[m], trial.rig(m)))
                report["rig"][m] = strict(made[m])
    # Stage times as measured when each stage ran (reused stages keep their original times).
    report["timing"] = {"render_s": ds.render_time_s, **report["timing"],
                        "rig_s": sum(e["wall_time_s"] for e in report["rig"].values())}
    report["notes"] = notes.items
    return strict(report)


def _rig_job(args) -> dict:
    """One method's rig calibration (``run_trial``): its entry, or the error that ended it."""
    root, out, seed, method, calibration, failed, rig_fp, settings = args
    t0 = time.perf_counter()
    try:
        if failed:
            raise ValueError(f"a camera's calibration failed: {failed[0]}")
        entry = strict(rig_calibration(Dataset.load(root), RunPaths(Path(out)).trial(seed),
                                       method, CalibrationConfig.model_validate(calibration)))
    except (ValueError, np.linalg.LinAlgError, RuntimeError, OSError) as e:
        entry = {"method": method, "error": f"{type(e).__name__}: {e}"}
    entry["fingerprint"] = rig_fp
    entry["settings"] = settings
    entry["wall_time_s"] = time.perf_counter() - t0
    return entry


def _run_trial_job(args):
    cfg_json, out, methods, dataset_dir, with_rig, workers = args
    return run_trial(RigConfig.model_validate(cfg_json), Path(out), methods,
                     dataset_dir=dataset_dir, with_rig=with_rig, workers=workers)


def run(cfg: RigConfig, out: Path, methods: list[str], trials: int = 1, workers=1,
        progress=None, first_dataset: Path | None = None, with_rig: bool = True) -> list[dict]:
    """All trials (seeds cfg.seed, cfg.seed + 1, ...); with ``workers`` (a count, or the
    command's ``workers.Workers``) > 1 in spawned processes that end with this one, or for one
    trial, its stages' jobs (cameras, rigs) that many at a time. Holds the run directory's
    lock throughout (RunLockedError if another run holds it).

    ``first_dataset``: an existing dataset of ``cfg`` used as the first trial.
    """
    per_trial = workers if trials == 1 else 1
    jobs = [(cfg.model_copy(update={"seed": cfg.seed + i}).model_dump(mode="json"), str(out),
             methods, first_dataset if i == 0 else None, with_rig, per_trial)
            for i in range(trials)]
    with locked(out):
        return in_processes(_run_trial_job, jobs, workers, progress)


@dataclass(frozen=True, eq=False)
class Trial:
    """One trial of a run, as pose-eval needs it: the true cameras (world frame) and each
    method's estimated rig (cam_from_world = cam_from_cam0), or its error message."""

    seed: int
    truth: list[Camera]
    rigs: dict[str, list[Camera] | str]


def load_run(run_dir) -> list[Trial]:
    """The trials of a run directory written by ``stereo-bench RIG.yaml --out RUN_DIR``; a
    trial whose dataset is incomplete is skipped, an unreadable rig file is an error naming it,
    and a rig file left from an earlier configuration or method list (its fingerprint is not
    the one of the trial's current calibrations) is not read: it would describe other cameras."""
    run = RunPaths(Path(run_dir))
    if not run.trials.is_dir():
        raise FileNotFoundError(f"{run.trials}: not found; is {run_dir} a run directory written "
                                f"by `stereo-bench RIG.yaml --out {run_dir}`?")
    trials = []
    for seed in run.trial_seeds():
        trial = run.trial(seed)
        cams_file = trial.dataset.cameras
        if not cams_file.is_file():
            continue  # an interrupted trial (the true cameras are all pose-eval needs of it)
        truth = [Camera.from_dict(d, str(cams_file)) for d in read_json(cams_file)]
        rigs = {}
        metrics = read_json(trial.metrics) if trial.metrics.is_file() else {}
        for path in sorted(trial.rigs.glob("*.json")):
            entry = read_json(path)
            if not isinstance(entry, dict) or "method" not in entry:
                raise UnreadableFileError(f"{path}: not a rig calibration written by stereo-bench")
            if changed := changed_output(path, entry):
                raise UnreadableFileError(f"{changed}; run the rig stage again")
            # Made from the trial's current calibrations, with the settings it records.
            if entry.get("fingerprint") != rig_fingerprint(metrics.get("fingerprint"),
                                                           entry["method"],
                                                           entry.get("settings")):
                continue
            rigs[entry["method"]] = entry["error"] if "error" in entry else [
                Camera.from_dict(d, str(path)) for d in entry["cameras"]]
        trials.append(Trial(seed, truth, rigs))
    if not trials:
        raise FileNotFoundError(f"{run.trials}: no complete trial")
    return trials
