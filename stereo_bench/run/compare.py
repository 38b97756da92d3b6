"""`stereo-bench compare-tools RIG.yaml`: the calibrators people run, graded against the truth.

For each seed the rig's session is rendered and detected once (the run directory's trial, as
``stereo-bench RIG.yaml`` would make it), and every tool of stereo_bench.tools calibrates the same
detections, each as its users run it, writing its own file; the file is read back and scored as
the suite scores its own methods (run/exchange.score_cameras): per camera the projection
difference over the image against the true lens and the parameter errors; for a rig, RMSE_cal
(the board triangulated through the tool's cameras), the cameras' rotation and centre errors (the
reference camera fixed, and after a similarity alignment). The tool's own time is recorded.

Detections. Every tool gets the suite's detections, with each frame's corners numbered as the
board is (a symmetric checkerboard found turned by 180 degrees is renumbered from the truth):
which corner comes first is the detector's trap (TRAPS.md; ``stereo-bench RIG.yaml`` handles it
without the truth), and here the calibrators are compared, not detectors. A tool that reads
only images (multical) gets the session's images (``Session.images``) and detects the board
itself.

Uncertainty. A tool that reports one (stereo_bench.tools' module notes) is checked against the
true error of the very quantity it describes, per seed:

* a parameter's 1-sigma: inside when |estimate - truth| <= sigma;
* a projection covariance Sigma at pixel q and distance d (mrcal's mean-frames uncertainty): the
  true error is e = q* - q, with q* the projection through the TRUE camera of the point at
  distance d along the estimate's ray of q, carried into every board frame the tool used with the
  tool's board poses and back with the true ones, and averaged over the frames (mrcal's
  definition, with the truth as the perturbed calibration); inside when e' Sigma^-1 e is within
  the 68.27 % quantile of chi-square with 2 degrees of freedom (2.30), the 2-D analogue of 1-sigma.

An honest uncertainty has 68 % of its values inside over many seeds; the share is reported with
its 95 % Wilson interval.

Pose. With ``pose=True`` and a rig that surrounds a body, pose-eval (a separate program that
reads run directories) is run on the output: each tool's rig is written where pose-eval finds a
method's rig (``TrialPaths.rig``), and its paired MPJPE cost joins the table.
"""

from __future__ import annotations

import math
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
from scipy import stats

from .. import tools
from ..config.schema import RigConfig
from ..core.files import UnreadableFileError, read_json, strict, write_json
from ..evaluate.metrics import parameter_errors
from ..evaluate.stage import load_or_detect
from ..io.rundir import Notes, RunPaths, TrialPaths, fingerprint
from ..multiview.orientation import numbered_like
from ..core.poses import rodrigues_to_matrix
from ..scene.dataset import Dataset
from .exchange import rebased, score_cameras
from .pipeline import dataset_of, rig_fingerprint
from ..report.markdown import COMPARE_FIGURES
from .sweep_stats import t_interval
from .workers import in_processes

#: e' Sigma^-1 e below this holds 68.27 % of a 2-D Gaussian: the 1-sigma region in 2-D.
CHI2_2D_68 = float(stats.chi2.ppf(0.6827, 2))


def session_of(ds: Dataset, dets) -> tools.Session:
    """The session every tool is given (module notes: numbered as the board is)."""
    points = np.stack([d.points for d in dets])
    if ds.pattern.kind != "charuco":  # ChArUco corners carry their ids
        truth = ds.ground_truth.points
        points = np.stack([numbered_like(p, truth[c], ds.object_points)
                           for c, p in enumerate(points)])
    return tools.Session([c.name for c in ds.cameras], [c.size for c in ds.cameras],
                         ds.object_points, points, np.stack([d.found for d in dets]),
                         ds.pattern, images=ds.root / "images")


def _true_cam_from_board(ds: Dataset, c: int, frames) -> tuple[np.ndarray, np.ndarray]:
    """(V, 3, 3), (V, 3): camera c's true cam_from_board in ``frames``."""
    cam = ds.cameras[c]
    Rcw, tcw = rodrigues_to_matrix(cam.rvec), cam.tvec
    Rwb = rodrigues_to_matrix(ds.trajectory.rvecs[frames])
    twb = ds.trajectory.tvecs[frames]
    return Rcw @ Rwb, twb @ Rcw.T + tcw


def projection_errors(ds: Dataset, c: int, estimate, projection: dict) -> np.ndarray:
    """(P, 2) px: the true error of the mean-frames projection of ``projection['pixels']``
    (module notes) for camera c's ``estimate``."""
    uv = np.asarray(projection["pixels"], np.float64)
    p = estimate.unproject_rays(uv) * float(projection["distance_mm"])  # (P, 3) estimate's frame
    frames = sorted(projection["board_poses"])
    Re = rodrigues_to_matrix(np.array([projection["board_poses"][f][0] for f in frames]))
    te = np.array([projection["board_poses"][f][1] for f in frames])
    Rt, tt = _true_cam_from_board(ds, c, np.array(frames))
    board = np.einsum("fji,fpj->fpi", Re, p[None] - te[:, None])  # board_from_cam, per frame
    carried = np.einsum("fij,fpj->fpi", Rt, board) + tt[:, None]
    return ds.cameras[c].project_cam(carried.mean(axis=0)) - uv


def check_uncertainty(ds: Dataset, result: tools.ToolResult) -> dict:
    """Per camera, each reported parameter's z = (estimate - truth) / sigma and each probed
    pixel's e' Sigma^-1 e (module notes)."""
    out = {}
    by_name = {c.name: c for c in result.cameras}
    for c, truth in enumerate(ds.cameras):
        reported = result.uncertainty.get(truth.name)
        if not reported or truth.name not in by_name:
            continue
        est = by_name[truth.name]
        entry = {"error": reported["error"]} if "error" in reported else {}
        if "parameters" in reported:
            err = parameter_errors(est, truth.with_params(rvec=np.zeros(3), tvec=np.zeros(3)))
            entry["parameter_z"] = {k: err[k] / s for k, s in reported["parameters"].items()
                                    if k in err and s and math.isfinite(s) and s > 0}
        if "projection" in reported:
            proj = reported["projection"]
            e = projection_errors(ds, c, est, proj)
            cov = np.asarray(proj["covariance"], np.float64)
            entry["projection"] = {
                "distance_mm": float(proj["distance_mm"]),
                "error_px": np.linalg.norm(e, axis=-1),
                "sigma_worst_px": np.sqrt(np.linalg.eigvalsh(cov)[:, -1]),
                "mahalanobis2": np.einsum("pi,pij,pj->p", e, np.linalg.inv(cov), e)}
        out[truth.name] = entry
    return out


def _run_tool(name: str, session: tools.Session, ds: Dataset, trial: TrialPaths) -> dict:
    """One tool on one seed: its calibration scored (or why it has none)."""
    mod = tools.module(name)
    if (why := mod.missing()) is not None:
        return {"tool": name, "skipped": why}
    t0 = time.perf_counter()
    try:
        result = mod.calibrate(session, trial.tool(name), name)
        if len(result.cameras) > 1:  # a tool's world (anipose's, caliscope's) as camera 0's
            result.cameras = rebased(result.cameras)
        entry = {"tool": name, "file": str(result.path), "format": result.fmt,
                 "time_s": result.time_s, "log": result.log,
                 "cameras_estimated": [c.to_dict() for c in result.cameras]}
        if result.proxy is not None:
            entry.update(_score_proxy(ds, result, session))
        else:
            entry.update(score_cameras(ds, result.cameras, session.image_points,
                                       str(result.path)))
        entry["uncertainty"] = check_uncertainty(ds, result)
    except (ValueError, RuntimeError, np.linalg.LinAlgError, cv2.error, OSError) as e:
        entry = {"tool": name, "error": f"{type(e).__name__}: {e}"}
    entry["wall_time_s"] = time.perf_counter() - t0
    return strict(entry)


def _score_proxy(ds: Dataset, result: tools.ToolResult, session: tools.Session) -> dict:
    """A lens the camera model cannot hold, scored through its stand-ins (ToolResult.proxy):
    the rig as the suite scores any rig, each camera's projection difference as the tool's own
    projection gives it; its parameters are not the camera model's and are not compared."""
    cams, points, projection = result.proxy(
        [c.with_params(rvec=np.zeros(3), tvec=np.zeros(3)) for c in ds.cameras],
        session.image_points)
    scored = score_cameras(ds, cams, points, str(result.path))
    for cam, proj in zip(scored["cameras"].values(), projection):
        cam.update(projection_difference=proj, parameter_errors=None, validity=None)
    scored["note"] = ("a lens the suite's camera model cannot hold: scored through the tool's "
                      "own projection, each camera frame turned onto the true one first")
    return scored


def _pose_ready(trial: TrialPaths, fp: str, entries: dict) -> None:
    """Each tool's rig where pose-eval reads a method's (pipeline.load_run): the trial's marker
    with the session's fingerprint and one rig file per tool that gave cameras."""
    write_json(trial.metrics, {"fingerprint": fp, "kind": "compare-tools"})
    for name, e in entries.items():
        if "skipped" in e:
            continue
        # A tool that failed, or whose lens pose-eval cannot triangulate through, says why.
        rig = ({"cameras": e["cameras_estimated"]} if e.get("cameras_estimated") else
               {"error": e.get("error", "its lens has no form in the suite's camera model, "
                                        "which pose-eval triangulates through")})
        write_json(trial.rig(name), {"method": name, **rig,
                                     "fingerprint": rig_fingerprint(fp, name)})


def run_seed(cfg: RigConfig, out: Path, names: list[str]) -> dict:
    """Every tool on the session of seed ``cfg.seed`` (rendered and detected once, reused)."""
    trial = RunPaths(out).trial(cfg.seed)
    notes = Notes()
    ds, detected = dataset_of(cfg, trial, None, None, notes)
    dets, detect_s, det_fp = load_or_detect(ds, trial, notes=notes, detected=detected)
    session = session_of(ds, dets)
    entries = {}
    for name in names:
        entries[name] = _run_tool(name, session, ds, trial)
        write_json(trial.tool_score(name), entries[name])
    _pose_ready(trial, fingerprint("compare-tools", det_fp, names), entries)
    return strict({"seed": cfg.seed, "tools": entries, "detect_s": detect_s,
                   "render_s": ds.render_time_s, "notes": notes.items})


# ----------------------------------------------------------------------------------------------
# Summaries over seeds
# ----------------------------------------------------------------------------------------------

def wilson(inside: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson's score interval of a proportion inside/n."""
    if n == 0:
        return math.nan, math.nan
    z = stats.norm.ppf(0.5 + confidence / 2)
    p = inside / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return centre - half, centre + half


def _share(flags: list[bool]) -> dict:
    n, k = len(flags), int(sum(flags))
    lo, hi = wilson(k, n)
    return {"n": n, "inside": k, "share": k / n if n else math.nan, "ci_low": lo, "ci_high": hi}


def seed_figures(entry: dict) -> dict:
    """The figures of one tool on one seed that the table summarizes (NaN where not defined)."""
    if "cameras" not in entry:
        return {}
    cams = entry["cameras"].values()
    rig = entry.get("rig") or {}
    aligned = (rig.get("aligned") or {}).get("cameras", {})
    fixed = rig.get("camera_errors", {})
    others = list(fixed)[1:]  # the reference camera's errors are 0 by construction
    errors = [c["parameter_errors"] for c in cams if c["parameter_errors"]]
    return {
        "focal_error_px": float(np.mean([(abs(e["fx"]) + abs(e["fy"])) / 2 for e in errors]))
        if errors else math.nan,
        "principal_point_error_px": float(np.mean([math.hypot(e["cx"], e["cy"])
                                                   for e in errors])) if errors else math.nan,
        "projection_difference_mean_px": float(np.mean(
            [c["projection_difference"]["mean_px"] for c in cams])),
        "projection_difference_max_px": float(np.max(
            [c["projection_difference"]["max_px"] for c in cams])),
        "rmse_cal_mm": rig.get("rmse_cal_mm", math.nan),
        "centre_error_mm": float(np.mean([fixed[n]["centre_mm"] for n in others]))
        if others else math.nan,
        "rotation_error_deg": float(np.mean([fixed[n]["rotation_deg"] for n in others]))
        if others else math.nan,
        "aligned_centre_error_mm": float(np.mean([c["centre_mm"] for c in aligned.values()]))
        if aligned else math.nan,
        "time_s": entry["time_s"],
    }


def coverage(seeds: list[dict], name: str) -> dict:
    """The share of seeds whose true error lies inside the tool's reported 1-sigma, per
    parameter (over cameras and seeds) and for the projection (over cameras, probed pixels and
    seeds); {} for a tool that reports none."""
    params: dict[str, list[bool]] = {}
    proj: list[bool] = []
    ratio: list[float] = []
    failed: list[str] = []
    for s in seeds:
        for cam_name, cam in s["tools"].get(name, {}).get("uncertainty", {}).items():
            if "error" in cam:
                failed.append(f"seed {s['seed']}, {cam_name}: {cam['error']}")
            for k, z in cam.get("parameter_z", {}).items():
                params.setdefault(k, []).append(abs(z) <= 1.0)
            if "projection" in cam:
                d2 = np.asarray(cam["projection"]["mahalanobis2"], float)
                proj += (d2 <= CHI2_2D_68).tolist()
                ratio += (np.asarray(cam["projection"]["error_px"], float)
                          / np.asarray(cam["projection"]["sigma_worst_px"], float)).tolist()
    out = {}
    if params:
        out["parameters"] = {k: _share(v) for k, v in params.items()}
        out["parameters_all"] = _share([f for v in params.values() for f in v])
    if proj:
        out["projection"] = _share(proj)
        out["projection_error_over_sigma_median"] = float(np.median(ratio))
    if failed:
        out["not_computed"] = failed
    return out


def summarize(seeds: list[dict], names: list[str]) -> dict:
    """Per tool: each figure's mean with its 95 % Student-t interval over the seeds where the
    tool gave a calibration, the seeds where it failed (with the first reason) or was skipped,
    and its uncertainty's coverage."""
    table = {}
    for name in names:
        runs = [s["tools"].get(name, {}) for s in seeds]
        figs = [seed_figures(r) for r in runs if "cameras" in r]
        row = {"seeds": len(figs),
               "failed": [f"seed {s['seed']}: {r['error']}" for s, r in zip(seeds, runs)
                          if "error" in r],
               "skipped": next((r["skipped"] for r in runs if "skipped" in r), None),
               "figures": {k: t_interval([f[k] for f in figs]) for k, _, _ in COMPARE_FIGURES},
               "coverage": coverage(seeds, name)}
        table[name] = row
    return table


def _pose_cost(out: Path, seeds: int, motion: str, progress=None) -> dict:
    """pose-eval on the output (module notes): per tool the paired MPJPE cost over the trials
    (``costs``: t_interval), the floor of the true cameras, or ``error`` saying why not."""
    if progress:
        progress("pose-eval on every tool's rig")
    pose_out = out / "pose_eval"
    cmd = [sys.executable, "-m", "pose_eval.cli", "--run", str(out), "--calib", "all",
           "--trials", str(seeds), "--motion", motion, "--out", str(pose_out)]
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        return {"error": (done.stderr.strip().splitlines() or ["pose-eval failed"])[-1]}
    try:
        results = read_json(pose_out / "results.json")
        trials = results["trials"]
        costs = {m: t_interval([t["methods"].get(m, {}).get("triangulated", {})
                                .get("excess_mpjpe_mm", math.nan) for t in trials])
                 for m in results["methods"] if m != "gt"}
        floor = t_interval([t["methods"]["gt"]["triangulated"]["mpjpe_mm"] for t in trials])
    except (FileNotFoundError, UnreadableFileError, KeyError, TypeError) as e:
        return {"error": f"{pose_out / 'results.json'}: {e}"}
    settings = results.get("settings", {})
    return {"costs": costs, "floor": floor, "report": str(pose_out / "report.md"),
            "about": f"motion {motion}, {settings.get('frames')} frames, {len(trials)} "
                     f"trial(s), keypoints {settings.get('keypoints')}"}


def _run_seed_job(args) -> dict:
    cfg_json, out, names = args
    return run_seed(RigConfig.model_validate(cfg_json), Path(out), names)


def _seeds(cfg: RigConfig, out: Path, names: list[str], seeds: int, workers: int,
           progress) -> list[dict]:
    """run_seed over the seeds, in ``workers`` spawned processes when more than one."""
    jobs = [(cfg.model_copy(update={"seed": cfg.seed + i}).model_dump(mode="json"), str(out),
             names) for i in range(seeds)]
    return in_processes(_run_seed_job, jobs, workers,
                        progress and (lambda done, total: progress(f"{done} of {total} seeds "
                                                                   f"done")))


def compare_tools(cfg: RigConfig, out: Path, names: list[str], seeds: int = 1,
                  pose: bool = True, motion: str = "walk_circle", progress=None,
                  workers: int = 1) -> dict:
    """Every tool on ``seeds`` sessions (seeds cfg.seed, cfg.seed + 1, ...): the results
    (``seeds``: per seed each tool's scored entry; ``table``: ``summarize``; ``pose``: pose-eval's
    results on the tools' rigs, for 2+ cameras)."""
    out = Path(out)
    results = _seeds(cfg, out, names, seeds, workers, progress)
    report = {"kind": "compare-tools", "rig": cfg.name, "environment": cfg.environment.kind,
              "pattern": cfg.pattern.kind, "cameras": len(cfg.cameras), "tools": names,
              "about": {n: _about(n) for n in names}, "seeds": results,
              "table": summarize(results, names),
              "chi2_2d_68": CHI2_2D_68}
    if pose and len(cfg.cameras) > 1:
        report["pose"] = _pose_cost(out, seeds, motion, progress)
    return strict(report)


def _about(name: str) -> str:
    about = tools.module(name).ABOUT
    return about[name] if isinstance(about, dict) else about
