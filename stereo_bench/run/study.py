"""`stereo-bench study STUDY.yaml`: what calibration costs in 3D human pose, as a curve and a
threshold, from calibration sessions and the pose evaluation run together.

A study file is a sweep's grid file (docs/sweeps.md: rigs, environments, axes, methods,
trials) with a ``pose`` section::

    name: studio_pose
    rigs: [../studios/h36m_rectangle.yaml, ../studios/ring8.yaml]
    environments: [clean, office, handheld_low_light]
    methods: [zhang, tsai, bouguet, opencv]
    trials: 5
    pose:
      motions: [walk_circle, arm_raise, squat]
      frames: 60
      detectors: [gaussian, blazepose_fit, blazepose]   # Detector, below
      noise_px: 1.0          # the gaussian detector's noise
      render_samples: 16     # Cycles samples of the rendered bodies (blazepose)
      detector_model: null   # a fitted detector's JSON (blazepose_fit); null: the shipped fit
      rendered_studios: null # the rig files (stems) whose bodies blazepose renders; null: all
      floor_share: 0.1       # the threshold: where the cost reaches this share of the floor
      seed: 0                # of the keypoint noise and the rendered body's imaging

Stages: every configuration's calibration sessions run as the sweep runs them (a Dask task per
configuration) into OUT/calibration/ (a sweep folder with its own report); with the
``blazepose`` detector, the body of each motion is rendered once per studio with Blender into
OUT/bodies/; then every configuration's pose evaluation is a Dask task
(``pose_eval.study.pose_costs``) whose rows go to OUT/calibration/<config>/pose.json.

The answer, per studio and detector (:func:`cost_curve`): each calibration's pose cost (paired
against the true cameras on the same keypoints, averaged over the motions, with its 95 %
interval over seeds) against its RMSE_cal and against its rig's reprojection error; a bias
``b`` in a joint adds to the detector's error ``F`` (the floor) in quadrature, so the model
``cost = sqrt(F^2 + (k RMSE_cal)^2) - F`` is fitted (one ``k`` per studio and detector, each
calibration with its own trial's floor), and the threshold is the RMSE_cal where the cost
reaches ``floor_share`` of the median floor: ``F sqrt((1 + s)^2 - 1) / k``.
OUT/study.json, study.md, study.html and study_<rig>.png hold it.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from ..config.schema import ConfigError, describe
from ..config.yaml_reader import load_yaml
from ..core.files import write_json, write_text
from ..io.rundir import locked
from .grid import Sweep, parse_grid, rig_reader
from .sweep_stats import t_interval

#: How far past the largest RMSE_cal measured a threshold is still said (as an extrapolation).
MAX_EXTRAPOLATION = 3.0

Detector = Literal["gaussian", "blazepose_fit", "blazepose"]
DETECTOR_TITLES = {"gaussian": "synthetic, Gaussian", "blazepose_fit": "synthetic, BlazePose's "
                   "fitted error", "blazepose": "BlazePose on rendered bodies"}


class PoseSection(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    motions: list[str] = Field(["walk_circle"], min_length=1)
    frames: int = Field(60, ge=2, le=10_000)
    detectors: list[Detector] = Field(["gaussian", "blazepose_fit"], min_length=1)
    noise_px: float = Field(1.0, ge=0, le=100)
    render_samples: int = Field(16, ge=1, le=4096)
    detector_model: str | None = None
    rendered_studios: list[str] | None = None
    floor_share: float = Field(0.1, gt=0, le=10)
    seed: int = Field(0, ge=0, lt=2**63)

    @field_validator("motions")
    @classmethod
    def _motions(cls, v):
        from pose_eval.motion import MOTIONS

        unknown = [m for m in v if m not in MOTIONS]
        if unknown:
            raise ValueError(f"{unknown} not among {sorted(MOTIONS)}")
        if len(set(v)) != len(v):
            raise ValueError("a motion listed twice")
        return v

    @field_validator("detectors")
    @classmethod
    def _detectors(cls, v):
        if len(set(v)) != len(v):
            raise ValueError("a detector listed twice")
        return v


def detectors_of(pose: dict, studio: str) -> list[str]:
    """The detectors a studio's configurations are evaluated with: blazepose only where its
    bodies are rendered (``rendered_studios``)."""
    rendered = pose.get("rendered_studios")
    return [d for d in pose["detectors"]
            if d != "blazepose" or rendered is None or studio in rendered]


class _PoseOnly(BaseModel):
    model_config = ConfigDict(extra="forbid")
    pose: PoseSection


@dataclass(frozen=True)
class Study:
    sweep: Sweep
    pose: PoseSection
    source: str


def load_study(path) -> Study:
    """The study file's grid (validated as a sweep's) and pose section; every refusal names the
    file and the field."""
    path = Path(path)
    data = load_yaml(path, "study file")
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping with a grid's keys and a pose section")
    data = dict(data)
    try:
        pose = _PoseOnly.model_validate({"pose": data.pop("pose", None) or {}}).pose
    except ValidationError as e:
        raise ConfigError(describe(e, str(path), "study file")) from None
    if pose.detector_model is not None:
        model = (path.parent / pose.detector_model).resolve()
        if not model.is_file():
            raise ConfigError(f"{path}: pose.detector_model: {model} is not a file")
        from pose_eval.detector_fit import load_fit

        try:
            load_fit(model)  # refused now, not after hours of calibration
        except ValueError as e:
            raise ConfigError(f"{path}: pose.detector_model: {e}") from None
        pose = pose.model_copy(update={"detector_model": str(model)})
    sweep = parse_grid(data, path, rig_reader(path))  # rig files relative to the study file
    studios = {c.rig for c in sweep.configurations}
    if pose.rendered_studios is not None:
        unknown = sorted(set(pose.rendered_studios) - studios)
        if unknown:
            raise ConfigError(f"{path}: pose.rendered_studios: {unknown} are none of the "
                              f"study's rig files {sorted(studios)}")
        if "blazepose" not in pose.detectors:
            raise ConfigError(f"{path}: pose.rendered_studios names the studios whose bodies "
                              f"the blazepose detector renders; it is not in pose.detectors")
    return Study(sweep, pose, str(path))


def _pose_task(job: tuple) -> dict:
    from pose_eval.study import pose_costs
    from ..config.schema import RigConfig

    cfg_json, studio, run_dir, settings, bodies = job
    cfg = RigConfig.model_validate(cfg_json)
    t0 = time.perf_counter()
    try:
        result = pose_costs(run_dir, cfg.environment, studio, settings, Path(bodies))
    except Exception as e:  # noqa: BLE001 - one configuration must not end the study
        result = {"error": f"{type(e).__name__}: {e}", "rows": []}
    result["wall_time_s"] = time.perf_counter() - t0
    write_json(Path(run_dir) / "pose.json", result)
    return result


def _true_rigs(sweep: Sweep) -> dict[str, list]:
    """Per studio (rig file) its true cameras: bodies are rendered per studio, whatever the
    imaging."""
    rigs = {}
    for c in sweep.configurations:
        rigs.setdefault(c.rig, c.config.cameras_true())
    return rigs


def run_study(study: Study, out: Path, workers: int = 2, scheduler: str | None = None,
              progress=None) -> dict:
    """The calibrations (a sweep into OUT/calibration), the rendered bodies, every
    configuration's pose costs, then the report (module notes). ``progress(message)``."""
    from .sweep import _dask_client, _gathered, run_sweep

    say = progress or (lambda message: None)
    pose = study.pose.model_dump()
    t0 = time.perf_counter()
    with locked(out) as out:
        out = out.resolve()
        if "blazepose" in pose["detectors"]:
            from stereo_bench.render.blender.environment import require

            require()  # before hours of calibration: Blender must be there
        say(f"calibrating {len(study.sweep.configurations)} configuration(s) x "
            f"{study.sweep.trials} trial(s)")
        sweep = run_sweep(study.sweep, out / "calibration", workers,
                          lambda d, n: say(f"calibrated {d}/{n}"), scheduler)
        t_cal = time.perf_counter() - t0
        bodies = out / "bodies"
        if "blazepose" in pose["detectors"]:
            from pose_eval.study import render_bodies

            for rig, cameras in _true_rigs(study.sweep).items():
                if "blazepose" not in detectors_of(pose, rig):
                    continue
                render_bodies(rig, cameras, pose["motions"], pose["frames"],
                              pose["render_samples"], bodies, say)
        t_render = time.perf_counter() - t0 - t_cal
        rows = {r["name"]: r for r in sweep["configurations"]}
        # The seeds the sweep ran: a configuration's folder may hold others from an earlier
        # study with more trials, which its calibration figures do not include.
        jobs = {c.name: (c.config.model_dump(mode="json"), c.rig,
                         str(out / "calibration" / c.name),
                         {**pose, "detectors": detectors_of(pose, c.rig),
                          "seeds": [c.config.seed + i for i in range(study.sweep.trials)]},
                         str(bodies))
                for c in study.sweep.configurations if "error" not in rows[c.name]}
        with _dask_client(workers, scheduler) as (client, _):
            futures = {client.submit(_pose_task, job, key=f"pose-{name}-{time.time_ns()}"): name
                       for name, job in jobs.items()}
            costs = _gathered(futures, lambda d, n: say(f"pose evaluated {d}/{n}"))
        result = assemble(study, sweep, costs)
        result["wall_time_s"] = {"calibration": t_cal, "bodies": t_render,
                                 "pose": time.perf_counter() - t0 - t_cal - t_render,
                                 "total": time.perf_counter() - t0}
        result["workers"] = sweep["workers"]
        write_outputs(result, out, Path(study.source))
    return result


def _per_seed(rows: list[dict], key: str) -> dict:
    """{(detector, method, seed): mean over motions of ``key``} of rows without error; a seed
    with a failed motion has no value."""
    by = {}
    for r in rows:
        by.setdefault((r["detector"], r["method"], r["seed"]), []).append(r.get(key, math.nan))
    return {k: float(np.mean(v)) for k, v in by.items() if all(map(math.isfinite, v))}


def assemble(study: Study, sweep: dict, costs: dict) -> dict:
    """The study's figures from the sweep's rows and the pose rows: one entry per configuration
    (calibration and pose figures with intervals over seeds), then per studio and detector the
    curve's points, the fitted model and the threshold."""
    pose = study.pose
    configs = []
    for row in sweep["configurations"]:
        entry = {k: row[k] for k in ("name", "rig", "environment", "axes") if k in row}
        entry["studio"] = row["rig"]  # the rig file's stem: a configuration renames the rig
        if "error" in row:
            entry["error"] = row["error"]
            configs.append(entry)
            continue
        trials = {t["seed"]: t for t in row["per_trial"]}
        methods = sweep["methods"]
        entry["calibration"] = {
            m: {k: t_interval([trials[s]["methods"].get(m, {}).get(k) for s in trials])
                for k in ("rmse_cal_mm", "rig_rpe_px")} for m in methods}
        got = costs.get(row["name"], {"error": "no pose evaluation"})
        if got.get("error"):
            entry["pose_error"] = got["error"]
        cost, floor = _per_seed(got.get("rows", []), "cost_mm"), _per_seed(got.get("rows", []),
                                                                            "floor_mm")
        entry["pose"] = {}
        for d in detectors_of(pose.model_dump(), entry["studio"]):
            floors = {s: v for (dd, _, s), v in floor.items() if dd == d}
            entry["pose"][d] = {
                "floor_mm": t_interval(list(floors.values())),
                "methods": {m: t_interval([v for (dd, mm, _), v in cost.items()
                                           if dd == d and mm == m]) for m in methods},
                "points": [{"method": m, "seed": s, "cost_mm": v, "floor_mm": floor[(d, m, s)],
                            "rmse_cal_mm": trials[s]["methods"].get(m, {}).get("rmse_cal_mm"),
                            "rig_rpe_px": trials[s]["methods"].get(m, {}).get("rig_rpe_px")}
                           for (dd, m, s), v in sorted(cost.items()) if dd == d
                           and m != "gt" and s in trials]}
        entry["detector_2d"] = got.get("detector_2d", {})
        entry["failures"] = sorted({f"{r['method']} (seed {r['seed']}): {r['error']}"
                                    for r in got.get("rows", []) if "error" in r})
        configs.append(entry)
    curves = []
    for studio in dict.fromkeys(c["studio"] for c in configs):
        for d in detectors_of(pose.model_dump(), studio):
            points = [dict(p, configuration=c["name"]) for c in configs
                      if c["studio"] == studio and "pose" in c for p in c["pose"][d]["points"]]
            curves.append({"studio": studio, "detector": d, "points": points,
                           **cost_curve(points, pose.floor_share)})
    return {"name": study.sweep.grid.name, "study_file": study.source,
            "methods": sweep["methods"], "trials_per_configuration": sweep[
                "trials_per_configuration"], "pose": pose.model_dump(),
            "configurations": configs, "curves": curves, "failed": sweep["failed"]}


def cost_curve(points: list[dict], share: float) -> dict:
    """The model ``cost = sqrt(F^2 + (k R)^2) - F`` fitted to points {rmse_cal_mm: R, floor_mm:
    F, cost_mm} by least squares in k >= 0, and the RMSE_cal where the cost reaches ``share``
    of the median floor. Without two usable points (or with a zero slope) there is no
    threshold, and the reason says why."""
    from scipy.optimize import least_squares

    use = [p for p in points if all(isinstance(p.get(k), (int, float)) and math.isfinite(p[k])
                                    for k in ("rmse_cal_mm", "floor_mm", "cost_mm"))]
    if len(use) < 2:
        return {"n": len(use), "reason": f"{len(use)} calibration(s) with a pose cost and an "
                                         f"RMSE_cal: no curve"}
    R = np.array([p["rmse_cal_mm"] for p in use])
    F = np.array([p["floor_mm"] for p in use])
    C = np.array([p["cost_mm"] for p in use])

    def residual(k):
        return np.sqrt(F ** 2 + (k[0] * R) ** 2) - F - C

    guess = np.sqrt(np.maximum((C + F) ** 2 - F ** 2, 0)) / np.maximum(R, 1e-12)
    fit = least_squares(residual, [float(np.median(guess))], bounds=([0.0], [np.inf]))
    k = float(fit.x[0])
    floor = float(np.median(F))
    out = {"n": len(use), "k": k, "floor_mm": floor,
           "residual_rms_mm": float(np.sqrt(np.mean(fit.fun ** 2))),
           "cost_range_mm": [float(C.min()), float(C.max())],
           "rmse_cal_range_mm": [float(R.min()), float(R.max())]}
    threshold = floor * math.sqrt((1 + share) ** 2 - 1) / k if k > 0 else math.inf
    if threshold > MAX_EXTRAPOLATION * R.max():
        out["reason"] = (f"the cost stays below {share:.0%} of the floor up to the largest "
                         f"RMSE_cal measured ({R.max():.3g} mm): no threshold within reach")
        return out
    out["threshold_rmse_cal_mm"] = threshold
    # Beyond the calibrations measured the model, not the data, says where the cost gets there.
    out["extrapolated"] = bool(threshold > R.max() or threshold < R.min())
    return out


def _ci(s: dict, digits: int = 2) -> str:
    if not s or not s.get("n"):
        return "no value (Failures)"
    if s["n"] < 2 or not math.isfinite(s["ci_low"]):
        return f"{s['mean']:.{digits}f}"
    return f"{s['mean']:.{digits}f} [{s['ci_low']:.{digits}f}, {s['ci_high']:.{digits}f}]"


def study_markdown(result: dict) -> str:
    pose = result["pose"]
    methods = result["methods"]
    lines = [f"# Study {result['name']}: what calibration costs in 3D pose", "",
             f"{len(result['configurations'])} configuration(s) x "
             f"{result['trials_per_configuration']} seed(s); motions "
             f"{', '.join(pose['motions'])}, {pose['frames']} frames each. Means with 95 % "
             f"Student-t intervals over seeds. A cost is the MPJPE through a method's "
             f"calibration minus the MPJPE through the true cameras on the same keypoints "
             f"(the floor), averaged over the motions.", ""]
    lines += ["## The answer", ""]
    share = pose["floor_share"]
    for c in result["curves"]:
        title = DETECTOR_TITLES[c["detector"]]
        if "threshold_rmse_cal_mm" in c:
            lines.append(
                f"- **{c['studio']}, {title}**: a calibration costs {share:.0%} of the "
                f"floor ({c['floor_mm']:.1f} mm, so {share * c['floor_mm']:.2f} mm of "
                f"MPJPE) at RMSE_cal = **{c['threshold_rmse_cal_mm']:.2f} mm**"
                + (" (extrapolated: outside the calibrations measured)" if c["extrapolated"]
                   else "") + "; below it, calibration error hardly matters beside the "
                f"detector's. "
                f"(cost = sqrt(F^2 + ({c['k']:.3f} RMSE_cal)^2) - F fitted to {c['n']} "
                f"calibrations, RMSE_cal {c['rmse_cal_range_mm'][0]:.2f}-"
                f"{c['rmse_cal_range_mm'][1]:.1f} mm; residual {c['residual_rms_mm']:.2f} mm "
                f"RMS.)")
        else:
            lines.append(f"- **{c['studio']}, {title}**: {c.get('reason')}")
    lines += ["", "## Calibration: RMSE_cal (mm) and the rig's reprojection error (px)", "",
              "| configuration | " + " | ".join(f"{m} RMSE_cal | {m} RPE" for m in methods)
              + " |", "|---|" + "---|---|" * len(methods)]
    for c in result["configurations"]:
        if "calibration" not in c:
            lines.append(f"| {c['name']} | failed: {c.get('error', '')[:120]} |")
            continue
        cal = c["calibration"]
        lines.append(f"| {c['name']} | " + " | ".join(
            f"{_ci(cal[m]['rmse_cal_mm'])} | {_ci(cal[m]['rig_rpe_px'], 3)}" for m in methods)
            + " |")
    for d in pose["detectors"]:
        lines += ["", f"## Pose cost (mm), {DETECTOR_TITLES[d]}", "",
                  "| configuration | floor (true cameras) | " + " | ".join(methods) + " |",
                  "|---|---|" + "---|" * len(methods)]
        for c in result["configurations"]:
            if d not in c.get("pose", {}):
                continue
            p = c["pose"][d]
            lines.append(f"| {c['name']} | {_ci(p['floor_mm'], 1)} | " + " | ".join(
                _ci(p["methods"][m]) for m in methods) + " |")
    errors = [(c["name"], c["detector_2d"]) for c in result["configurations"]
              if c.get("detector_2d")]
    if errors:
        lines += ["", "## BlazePose's error against the projected true joints (median px)", ""]
        joints = list(next(iter(errors[0][1].values())))
        lines += ["| configuration | motion | " + " | ".join(joints) + " |",
                  "|---|---|" + "---|" * len(joints)]
        for name, by_motion in errors:
            for motion, rows in by_motion.items():
                lines.append(f"| {name} | {motion} | " + " | ".join(
                    "–" if rows[j]["median_px"] is None else f"{rows[j]['median_px']:.1f}"
                    for j in joints) + " |")
    failures = [(c["name"], f) for c in result["configurations"] for f in c.get("failures", [])]
    failures += [(c["name"], c["pose_error"]) for c in result["configurations"]
                 if c.get("pose_error")]
    if failures or result["failed"]:
        lines += ["", "## Failures", ""]
        lines += [f"- {name}: calibration failed" for name in result["failed"]]
        lines += [f"- {name}: {f}" for name, f in failures]
    w = result.get("wall_time_s")
    if w:
        lines += ["", f"Wall time {w['total']:.0f} s with {result['workers']} worker(s): "
                      f"calibration {w['calibration']:.0f} s, bodies {w['bodies']:.0f} s, "
                      f"pose {w['pose']:.0f} s.", ""]
    return "\n".join(lines) + "\n"


def write_outputs(result: dict, out: Path, source: Path) -> None:
    from ..report.html import provenance, write_html
    from ..report.plots import plot_study

    figures = []
    for studio in dict.fromkeys(c["studio"] for c in result["curves"]):
        path = out / f"study_{studio}.png"
        plot_study([c for c in result["curves"] if c["studio"] == studio],
                   result["pose"]["floor_share"], path)
        figures.append(path)
    write_json(out / "study.json", result)
    text = study_markdown(result)
    write_text(out / "study.md", text)
    write_html(out / "study.html", f"study: {result['name']}", text, figures, provenance(),
               source.read_text() if source.is_file() else None, methods=result["methods"])

