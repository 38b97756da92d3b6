"""`stereo-bench RIG.yaml`: render -> detect -> calibrate -> rig calibration -> triangulate ->
metrics, over trials, with every stage saved so a rerun reuses what is complete.

Run directory::

    RUN/trials/seed_<s>/dataset/              the rendered dataset (manifest written last)
    RUN/trials/seed_<s>/detections/, calibrations/, metrics.json   (see evaluate.py)
    RUN/trials/seed_<s>/rig/<method>.json     the estimated rig (cameras with cam_from_world =
                                              cam_from_cam0) and its RMSE_cal and rig errors
    RUN/results.json, RUN/report.md, RUN/plots/*.png

A stage is complete when its last file exists (dataset: manifest.json; calibration:
metrics.json; rig: rig/<method>.json), so an interrupted run loses at most the stage in flight.
"""

from __future__ import annotations

import json
import multiprocessing
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .camera import Camera
from .config import RigConfig
from .dataset import Dataset, write_dataset
from .detect import CameraDetections
from .evaluate import jsonable, evaluate_dataset
from .stereo import calibrate_rig, rig_errors
from .triangulate import triangulate


def trial_dir(out: Path, seed: int) -> Path:
    return Path(out) / "trials" / f"seed_{seed}"


def rig_calibration(ds: Dataset, tdir: Path, method: str) -> dict:
    """Calibrate the rig from one method's per-camera estimates and score it against the truth.

    RMSE_cal (paper Sec. 4.2): the board's feature points triangulated in every frame through the
    estimated rig (DLT then reprojection refinement) against their true positions, both in the
    reference camera's frame, in mm; ``centre_rmse_mm`` does the same for the board's centre
    (the mean of the triangulated points of a frame against the mean of the true ones).
    """
    cams, rv, tv = [], [], []
    F = ds.frames
    dets = [CameraDetections.load(tdir / "detections" / f"{c.name}.npz") for c in ds.cameras]
    for cam in ds.cameras:
        folder = tdir / "calibrations" / method
        cams.append(Camera.load_json(folder / f"{cam.name}.json"))
        with np.load(folder / f"{cam.name}_views.npz") as z:
            r, t = np.full((F, 3), np.nan), np.full((F, 3), np.nan)
            r[z["view_ids"]], t[z["view_ids"]] = z["rvecs"], z["tvecs"]
        rv.append(r)
        tv.append(t)
    image_points = np.stack([d.points for d in dets])
    found = np.stack([d.found for d in dets])
    rig = calibrate_rig(cams, ds.object_points, image_points, np.stack(rv), np.stack(tv), found)

    # Truth in the true reference camera's frame.
    truth = ds.cameras
    world_pts = ds.rig().board_points_world()  # (F, N, 3)
    true_pts = truth[0].world_to_cam(world_pts)
    est_pts = triangulate(rig.cameras, image_points)  # NaN where fewer than two views
    ok = np.all(np.isfinite(est_pts), axis=-1)
    err = np.linalg.norm(est_pts - true_pts, axis=-1)[ok]
    frames = ok.all(axis=1)
    centre_err = np.linalg.norm(est_pts[frames].mean(1) - true_pts[frames].mean(1), axis=-1)
    errors = rig_errors(rig.cameras, truth)
    return {
        "method": method,
        "reference": truth[0].name,
        "cameras": [c.to_dict() for c in rig.cameras],
        "rms_px": rig.rms_px,
        "rms_px_per_camera": rig.rms_px_per_camera,
        "frames_used": int(rig.frames_used.sum()),
        "iterations": rig.iterations,
        "time_s": rig.time_s,
        "rmse_cal_mm": float(np.sqrt(np.mean(err**2))) if len(err) else float("nan"),
        "mean_error_mm": float(err.mean()) if len(err) else float("nan"),
        "max_error_mm": float(err.max()) if len(err) else float("nan"),
        "centre_rmse_mm": float(np.sqrt(np.mean(centre_err**2))) if len(centre_err)
        else float("nan"),
        "points_triangulated": int(ok.sum()),
        "rig_errors": {k: v[1:] for k, v in errors.items()},  # camera 0 is 0 by construction
        "log": rig.log,
    }


def run_trial(cfg: RigConfig, out: Path, methods: list[str], progress=None,
              dataset_dir: Path | None = None, with_rig: bool = True) -> dict:
    """One trial (one seed): every stage, each reused when complete on disk.

    ``dataset_dir``: an existing dataset to use instead of rendering into the trial directory.
    """
    tdir = trial_dir(out, cfg.seed)
    dataset_dir = Path(dataset_dir or tdir / "dataset")
    try:
        ds = Dataset.load(dataset_dir)
    except FileNotFoundError:
        ds = write_dataset(cfg, dataset_dir, progress)
    cached = tdir / "metrics.json"
    report = json.loads(cached.read_text()) if cached.is_file() else None
    if report is None or report.get("methods") != methods:
        report = evaluate_dataset(ds, methods, tdir, progress)
    report["rig"] = {}
    if with_rig and len(ds.cameras) >= 2:
        (tdir / "rig").mkdir(exist_ok=True)
        for m in methods:
            path = tdir / "rig" / f"{m}.json"
            if path.is_file():
                report["rig"][m] = json.loads(path.read_text())
                continue
            failed = [e["error"] for e in report["calibration"][m].values() if "error" in e]
            t0 = time.perf_counter()
            try:
                if failed:
                    raise ValueError(f"a camera's calibration failed: {failed[0]}")
                entry = jsonable(rig_calibration(ds, tdir, m))
            except (ValueError, np.linalg.LinAlgError, RuntimeError, OSError) as e:
                entry = {"method": m, "error": f"{type(e).__name__}: {e}"}
            entry["wall_time_s"] = time.perf_counter() - t0
            path.write_text(json.dumps(entry, indent=2))
            report["rig"][m] = entry
    # Stage times as measured when each stage ran (reused stages keep their original times).
    report["timing"] = {"render_s": ds.render_time_s, **report["timing"],
                        "rig_s": sum(e["wall_time_s"] for e in report["rig"].values())}
    return report


def _run_trial_job(args):
    cfg_json, out, methods, dataset_dir, with_rig = args
    return run_trial(RigConfig.model_validate(cfg_json), Path(out), methods,
                     dataset_dir=dataset_dir, with_rig=with_rig)


def run(cfg: RigConfig, out: Path, methods: list[str], trials: int = 1, workers: int = 1,
        progress=None, first_dataset: Path | None = None, with_rig: bool = True) -> list[dict]:
    """All trials (seeds cfg.seed, cfg.seed + 1, ...); with workers > 1 in spawned processes
    (forking after OpenCV started its thread pool can deadlock: TRAPS.md).

    ``first_dataset``: an existing dataset of ``cfg`` used as the first trial.
    """
    jobs = [(cfg.model_copy(update={"seed": cfg.seed + i}).model_dump(mode="json"), str(out),
             methods, first_dataset if i == 0 else None, with_rig) for i in range(trials)]
    if workers <= 1 or trials == 1:
        results = []
        for i, job in enumerate(jobs):
            results.append(_run_trial_job(job))
            if progress:
                progress(i + 1, trials)
        return results
    results = [None] * trials
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        futures = {pool.submit(_run_trial_job, j): i for i, j in enumerate(jobs)}
        for n, fut in enumerate(as_completed(futures), 1):
            results[futures[fut]] = fut.result()
            if progress:
                progress(n, trials)
    return results


@dataclass(frozen=True, eq=False)
class Trial:
    """One trial of a run, as pose-eval needs it: the true cameras (world frame) and each
    method's estimated rig (cam_from_world = cam_from_cam0), or its error message."""

    seed: int
    truth: list[Camera]
    rigs: dict[str, list[Camera] | str]


def load_run(run_dir) -> list[Trial]:
    """The trials of a run directory written by ``stereo-bench RIG.yaml --out RUN_DIR``."""
    root = Path(run_dir) / "trials"
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: not found; is {run_dir} a run directory written by "
                                f"`stereo-bench RIG.yaml --out {run_dir}`?")
    trials = []
    for tdir in sorted(root.glob("seed_*"), key=lambda p: int(p.name.split("_")[1])):
        cams_file = tdir / "dataset" / "ground_truth" / "cameras.json"
        if not cams_file.is_file():
            continue  # an interrupted trial
        truth = [Camera.from_dict(d, str(cams_file)) for d in json.loads(cams_file.read_text())]
        rigs = {}
        for path in sorted((tdir / "rig").glob("*.json")):
            entry = json.loads(path.read_text())
            rigs[entry["method"]] = entry["error"] if "error" in entry else [
                Camera.from_dict(d, str(path)) for d in entry["cameras"]]
        trials.append(Trial(int(tdir.name.split("_")[1]), truth, rigs))
    if not trials:
        raise FileNotFoundError(f"{root}: no complete trial")
    return trials
