"""What every calibration of one study configuration costs in 3D pose, per 2D detector and
motion: the pose half of ``stereo-bench study`` (stereo_bench/run/study.py runs the
calibrations and writes the report).

For each motion the body is placed in the studio (:func:`pose_eval.scene.make_scene`) and
observed through the true cameras by each detector:

* ``gaussian``: the projected joints plus ``noise_px`` of Gaussian noise (pose-eval's default
  synthetic detector, occlusion modelled);
* ``blazepose_fit``: synthetic detections drawn from a detector model fitted to BlazePose on
  rendered bodies (:mod:`pose_eval.detector_fit`; the shipped fit unless the study names one);
* ``blazepose``: BlazePose itself, on Blender renders of the body photographed through the
  configuration's imaging (:func:`pose_eval.photoreal.photograph_body`): the same noise, lens
  blur, vignetting and JPEG as its calibration session.

Every calibrated rig of every trial then triangulates the same keypoints as the true cameras
(``evaluate_trial``): its cost is its MPJPE minus the true cameras' on the same keypoints.
Synthetic keypoints are drawn per trial (seeded by the trial's seed and the motion); the
rendered body is one recording per configuration (its noise drawn from the study's seed),
shared by the trials, whose calibrations differ.

Bodies are rendered once per studio and motion into ``BODIES/<rig>/<motion>_<frames>f_<samples>s``
and reused while their cameras and joints are those of the scene (a changed studio or motion
renders again).
"""

from __future__ import annotations

import fcntl
import json
from pathlib import Path

import numpy as np

from stereo_bench.core.files import read_json
from stereo_bench.run.pipeline import load_run

from .body import load_body_model
from .cli import run_rigs, evaluate_trial
from .detector_fit import load_fit, observe_fitted
from .observe import DetectorModel, observe, scene_occlusion
from .report import COST, FLOOR
from .scene import make_scene

RENDERED = "blazepose"


def body_folder(bodies: Path, rig: str, motion: str, frames: int, samples: int) -> Path:
    return Path(bodies) / rig / f"{motion}_{frames}f_{samples}s"


def _rendered_matches(folder: Path, cameras, scene) -> bool:
    """Whether ``folder`` holds every frame of this scene rendered through these cameras."""
    try:
        same_cameras = read_json(folder / "cameras.json") == json.loads(
            json.dumps([c.to_dict() for c in cameras]))
        joints = np.load(folder / "joints_mm.npy")
    except (OSError, ValueError):
        return False
    last = folder / "images" / cameras[-1].name / f"{len(scene.joints) - 1:06d}.png"
    return (same_cameras and joints.shape == scene.joints.shape
            and np.allclose(joints, scene.joints, atol=1e-6) and last.is_file())


def render_bodies(rig: str, cameras, motions: list[str], frames: int, samples: int,
                  bodies: Path, progress=None) -> None:
    """Blender renders of each motion's body in the studio, unless already there."""
    from .photoreal import render_body

    model = load_body_model()
    weights = model.lbs_weights.detach().cpu().numpy()
    for motion in motions:
        scene = make_scene(cameras, motion, frames, model=model)
        folder = body_folder(bodies, rig, motion, frames, samples)
        folder.mkdir(parents=True, exist_ok=True)
        # Another study (or scripts/fit_detector.py) rendering the same body: wait for it and
        # use its frames rather than render them twice.
        with open(folder / ".rendering", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            if _rendered_matches(folder, cameras, scene):
                continue
            if progress:
                progress(f"rendering {motion}: {frames} frames x {len(cameras)} cameras")
            render_body(cameras, scene, weights, folder, samples=samples)


def pose_costs(run_dir, environment, rig: str, settings: dict, bodies: Path) -> dict:
    """Every trial's paired pose cost of every method of the run in ``run_dir`` (a study
    configuration's folder): {"rows": [{seed, detector, motion, method, cost_mm, floor_mm}
    or {..., error}; method "gt" carries the floor], "detector_2d": per motion the rendered
    detector's error}; ``settings`` is the study's pose section (motions, frames, detectors,
    noise_px, render_samples, detector_model, seed) and the ``seeds`` of the trials to
    evaluate (None: every one there)."""
    run_dir = Path(run_dir)
    trials = [t for t in load_run(run_dir)
              if settings.get("seeds") is None or t.seed in settings["seeds"]]
    if not trials:
        raise ValueError(f"{run_dir}: no complete trial to evaluate")
    methods = sorted({m for t in trials for m in t.rigs})
    model = load_body_model()
    fit = load_fit(settings.get("detector_model")) if "blazepose_fit" in settings["detectors"] \
        else None
    seed = settings["seed"]
    rows, detector_2d = [], {}
    truth = trials[0].truth  # a study's trials share the studio; a run with others is refused
    for t in trials:
        if [c.to_dict() for c in t.truth] != [c.to_dict() for c in truth]:
            raise ValueError(f"{run_dir}: trial seed {t.seed} has other true cameras than "
                             f"seed {trials[0].seed}")
    for mi, motion in enumerate(settings["motions"]):
        scene = make_scene(truth, motion, settings["frames"], model=model)
        occluded = scene_occlusion(truth, scene)
        for detector in settings["detectors"]:
            shared = None
            if detector == RENDERED:
                from .photoreal import keypoint_errors, recorded_keypoints

                folder = body_folder(bodies, rig, motion, settings["frames"],
                                     settings["render_samples"])
                if not _rendered_matches(folder, truth, scene):
                    raise FileNotFoundError(f"{folder}: no rendered body of this studio")
                shared = recorded_keypoints(truth, scene, folder / "images", environment,
                                            run_dir / "body" / motion, seed)
                detector_2d[motion] = keypoint_errors(truth, shared, scene.joints)
            for t in trials:
                rng = np.random.default_rng([seed, t.seed, mi])
                if shared is not None:
                    keypoints = shared
                elif detector == "gaussian":
                    keypoints = observe(truth, scene, DetectorModel(settings["noise_px"]), rng,
                                        occluded)
                else:
                    keypoints = observe_fitted(truth, scene, fit, rng, occluded)
                entries, _ = evaluate_trial(truth, run_rigs(["gt"] + methods, t), keypoints,
                                            scene, label=f"trial seed {t.seed}")
                # The floor stands even where every calibration failed.
                rows.append({"seed": t.seed, "detector": detector, "motion": motion,
                             "method": "gt", "cost_mm": 0.0,
                             "floor_mm": entries["gt"]["triangulated"]["mpjpe_mm"]})
                for m in methods:
                    row = {"seed": t.seed, "detector": detector, "motion": motion, "method": m}
                    e = entries[m]
                    if "error" in e:
                        row["error"] = e["error"]
                    else:
                        row["cost_mm"] = e["triangulated"][COST]
                        row["floor_mm"] = e["triangulated"][FLOOR]
                    rows.append(row)
    return {"rows": rows, "detector_2d": detector_2d}

