"""`pose-eval`: what a calibration method costs in 3D human pose (MPJPE), against exact truth.

A body moves in front of the rig, or at the centre of a studio that surrounds it
(pose_eval.scene); its joints are detected through the TRUE cameras (pose_eval.observe),
triangulated through each method's ESTIMATED cameras (pose_eval.reconstruct), optionally fitted
by SMPL (pose_eval.fit), and compared with the exact joints (pose_eval.metrics). The ``gt``
column triangulates the same detections through the true cameras: the error the keypoints alone
leave, and each method's cost is its MPJPE minus gt's on those keypoints (:func:`evaluate_trial`).
Every trial draws new keypoint noise; with a run of several trial seeds, trial i also uses the
calibrations of run trial i mod (number of run trials).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import warnings
from pathlib import Path

import numpy as np
from rich.console import Console

from stereo_bench.calibrate import available_methods, parse_method
from stereo_bench.config.bounds import ConfigError
from stereo_bench.config.schema import load_rig
from stereo_bench.cli import say
from stereo_bench.run.pipeline import Trial, load_run
from stereo_bench.render.blender.client import WorkerError
from stereo_bench.render.blender.environment import WorkerUnavailable
from stereo_bench.report.html import provenance, write_html
from stereo_bench.io.rundir import RunPaths, locked
from stereo_bench.core.files import is_safe_name, write_json, write_text

from .body import NUM_JOINTS, load_body_model
from .body_session import SCALES, Session, calibrate_session
from .fit import fit_smpl
from .metrics import excess_mpjpe, pose_metrics
from .motion import JOINT_NAMES, MOTIONS
from .detector_fit import load_fit, observe_fitted
from .observe import (DetectorModel, keypoints_at_clocks, observe, read_openpose,
                      scene_occlusion, write_openpose)
from .reconstruct import triangulate_joints
from .report import (BODY, COST, FLOOR, STAGES, aggregate, body_summary, headline_stage,
                     markdown, plot_mpjpe, plot_skeleton)
from .scene import (Person, in_true_world, make_scene, rig_axes, run_config, run_description,
                    seen_by_clocks)

console = Console(stderr=True)
NOISE_PX = 1.0
MAX_NOISE_PX = 100.0
MAX_DISTANCE_MM = 100_000.0  # 100 m: a person is then about 20 px tall through a 1000 px lens
MIN_DETECTED = 0.5
BODY_STREAM = 1  # the last entry of a calibration session's seeds ([seed, trial, 1])


DEFAULT_RUN = "out/quickstart"


def calib_choice(text: str) -> str:
    """--calib: gt, all or any calibration method name (BASE-MODEL variants too)."""
    if text not in ("gt", "all"):
        try:
            parse_method(text)
        except ValueError as e:
            raise argparse.ArgumentTypeError(f"{e}; or gt, all") from None
    return text


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="pose-eval",
        description="Measure how much a calibration method changes a reconstructed 3D human pose "
                    "(MPJPE), with the exact pose known: keypoints seen through the true cameras "
                    "are triangulated through the method's estimated cameras. The gt column "
                    "(true cameras) is always reported beside the chosen method.")
    p.add_argument("--calib", type=calib_choice, metavar="METHOD",
                   help="calibration method whose estimated rig triangulates ("
                        f"{', '.join(available_methods())} or BASE-MODEL, e.g. zhang-brown); "
                        "'gt' the true cameras only; 'all' every method in the run plus gt "
                        "(default with --calibration: gt)")
    p.add_argument("--calibration", metavar="FILE",
                   help="your own calibration of the rig's cameras, from another tool (a file "
                        "or folder in a format of docs/formats.md: OpenCV YAML, COLMAP, Kalibr, "
                        "EasyMocap, anipose, mrcal); reported beside gt as file:<name>")
    p.add_argument("--calibration-format", metavar="FORMAT",
                   help="its format (default: guessed from the file names)")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--run", metavar="RUN_DIR",
                     help="a `stereo-bench RIG.yaml --out RUN_DIR` run: true cameras and every "
                          "method's estimated rig per trial seed (default, without --rig: "
                          f"{DEFAULT_RUN}, written by `make demo`)")
    src.add_argument("--rig", metavar="RIG.yaml",
                     help="a rig file: the true cameras only (then only --calib gt)")
    src.add_argument("--capture", metavar="DIR",
                     help="your own rig, calibrated by `stereo-bench calibrate-images --out DIR`: "
                          "its opencv rig (else its first method's) stands for the true cameras, "
                          "and --calib METHOD or all measures what choosing another method's rig "
                          "instead would change in the pose. With --calibration FILE alone, the "
                          "file's cameras stand for the true ones")
    p.add_argument("--motion", default="walk_circle", choices=sorted(MOTIONS),
                   help="procedural body motion (default: %(default)s)")
    p.add_argument("--frames", type=int, default=60, help="frames at 30 fps (default: %(default)s)")
    p.add_argument("--noise-px", type=float,
                   help=f"Gaussian keypoint noise per coordinate, px (default: {NOISE_PX})")
    p.add_argument("--outlier-rate", type=float,
                   help="fraction of detections moved to a random point within 50 px (default: 0)")
    p.add_argument("--miss-rate", type=float, help="fraction of detections missed (default: 0)")
    p.add_argument("--no-occlusion", action="store_true",
                   help="do not mark joints hidden by the body (confidence 0.3, 3x noise)")
    p.add_argument("--keypoints", metavar="DIR",
                   help="use a detector's OpenPose-style JSON files instead of synthetic "
                        "keypoints: DIR/<camera>/<frame:06d>_keypoints.json, SMPL's 24 joints")
    p.add_argument("--detector-model", metavar="FILE",
                   help="draw synthetic keypoints from a fitted detector's error (its joints, "
                        "their offsets, noise in mm on the body, misses): 'blazepose' for the "
                        "shipped fit of BlazePose on rendered bodies, or a JSON file written by "
                        "scripts/fit_detector.py (docs/pose_eval.md)")
    p.add_argument("--rendered", action="store_true",
                   help="render the body with Blender from every true camera (OUT/body/) and "
                        "take the keypoints MediaPipe's BlazePose finds in those images, instead "
                        "of synthetic ones (needs `stereo-bench blender-setup`; docs/photoreal.md)")
    p.add_argument("--render-samples", type=int, default=16,
                   help="Cycles samples per pixel of --rendered (default: %(default)s)")
    p.add_argument("--body-calibration", action="store_true",
                   help="also calibrate the studio from people walking in it, with no board "
                        "(docs/body_calibration.md): their keypoints drawn like the evaluation's "
                        "(Gaussian or --detector-model), each camera at its clock (the rig's "
                        "time_offset_ms); reported as method 'body' beside the board methods, "
                        "with its errors against the truth")
    p.add_argument("--body-people", type=int, default=1,
                   help="people walking in the calibration session (default: %(default)s)")
    p.add_argument("--body-frames", type=int, default=300,
                   help="frames of the calibration session at 30 fps (default: %(default)s)")
    p.add_argument("--body-scale", choices=SCALES, default="baseline",
                   help="the known quantity that makes it metric: the baseline of cameras 0 "
                        "and 1 or the person's height (default: %(default)s; a detector whose "
                        "joints are not SMPL's biases the height: -7 %% for BlazePose)")
    p.add_argument("--max-offset-frames", type=int, default=10,
                   help="how far the cameras' clocks may disagree, whole frames; 0 takes them "
                        "as synchronised (default: %(default)s)")
    p.add_argument("--robust", action="store_true",
                   help="reject outlier views while triangulating (needs 3+ cameras)")
    p.add_argument("--fit-smpl", action="store_true",
                   help="fit SMPL to the triangulated joints (as EasyMocap does) and report both")
    p.add_argument("--trials", type=int,
                   help="noise trials (default: the run's trial count, or 1)")
    p.add_argument("--seed", type=int, default=0, help="base seed of the keypoint noise")
    p.add_argument("--distance-mm", type=float,
                   help="body distance from a rig whose cameras look the same way (default: the "
                        "least that keeps it in view); a studio that surrounds the body places "
                        "it at the point the cameras look at")
    p.add_argument("--model-path", help="an SMPL model file or folder (default: the shipped "
                                        "open stand-in body)")
    p.add_argument("--out", help="output directory (default: out/<rig name>/pose_eval)")
    return p


def _capture_trial(folder) -> tuple[str, str, list[Trial]]:
    """A calibrate-images output as one trial: the reference rig (opencv's, else the first
    method's that gave one) as the true cameras, the other methods' rigs as estimates."""
    from stereo_bench.run.exchange import _rig_file_cameras
    from stereo_bench.io.rundir import CapturePaths
    from stereo_bench.core.files import read_json

    paths = CapturePaths(folder)
    results = read_json(paths.results) if paths.results.is_file() else None
    if not isinstance(results, dict) or results.get("kind") != "capture":
        raise FileNotFoundError(f"{folder}: not a folder written by `stereo-bench "
                                f"calibrate-images`")
    rigs = {}
    for m in results.get("methods", []):
        path = paths.trial.rig(m)
        if path.is_file():
            rigs[m] = _rig_file_cameras(path)
    usable = [m for m, r in rigs.items() if not isinstance(r, str)]
    if not usable:
        raise ValueError(f"{folder}: no method gave a rig of two or more cameras ("
                         + "; ".join(f"{m}: {r}" for m, r in rigs.items()) + ")")
    reference = "opencv" if "opencv" in usable else usable[0]
    truth = rigs.pop(reference)
    return (Path(folder).name, f"capture (reference: {reference}'s rig)",
            [Trial(0, truth, rigs)])


def _source(args) -> str:
    return args.run or args.rig or args.capture or args.calibration


def _inputs(args) -> tuple[str, str, list[Trial]]:
    """(rig name, environment, run trials) from --run, --rig, --capture or --calibration
    alone (its cameras as the true ones)."""
    if args.capture:
        return _capture_trial(args.capture)
    if not args.run and not args.rig:
        from stereo_bench import io

        cams = io.load(args.calibration, args.calibration_format)
        return Path(args.calibration).stem, "calibration file", [Trial(0, cams, {})]
    if args.run:
        name, env = run_description(args.run)
        return name, env, load_run(args.run)
    cfg = load_rig(args.rig)
    return cfg.name, cfg.environment.kind, [Trial(cfg.seed, cfg.cameras_true(), {})]


def _methods(args, trials: list[Trial]) -> list[str]:
    if args.calib is None and not args.calibration and not args.body_calibration:
        raise ValueError("--calib: expected a method, gt or all (or --calibration FILE)")
    if args.calib in ("gt", None):
        return ["gt"]
    if not args.run and not args.capture:
        raise ValueError(f"--calib {args.calib} needs the method's calibrated rig: run "
                         f"`stereo-bench {args.rig} --out RUN` first and pass --run RUN "
                         f"(--rig alone gives the true cameras, i.e. --calib gt)")
    if args.calib == "all":
        found = {m for t in trials for m in t.rigs}
        rank = {m: i for i, m in enumerate(available_methods())}
        return ["gt"] + sorted(found, key=lambda m: (rank.get(m, len(rank)), m))
    for t in trials:
        if args.calib not in t.rigs:
            where = (Path(args.capture) / "rig" / f"{args.calib}.json" if args.capture else
                     RunPaths(Path(args.run)).trial(t.seed).rig(args.calib))
            raise FileNotFoundError(
                f"{where}: "
                f"no rig of method {args.calib!r} in this run (methods found: "
                f"{sorted(t.rigs) or 'none'})")
    return ["gt", args.calib]


def check_options(args) -> None:
    """Refuse options that would give a number without meaning (NaN noise, a body 1000 km away,
    every detection missed), naming the option and the range expected."""
    def need(ok, option, expected, value):
        if not ok:
            raise ValueError(f"{option}: expected {expected}, got {value!r}")

    need(1 <= args.frames <= 10_000, "--frames", "1..10000", args.frames)
    if args.trials is not None:
        need(1 <= args.trials <= 1000, "--trials", "1..1000", args.trials)
    need(0 <= args.seed < 2**63, "--seed", "a non-negative integer", args.seed)
    if args.noise_px is not None:
        need(math.isfinite(args.noise_px) and 0 <= args.noise_px <= MAX_NOISE_PX, "--noise-px",
             f"a number in 0..{MAX_NOISE_PX} px", args.noise_px)
    for option, value in (("--outlier-rate", args.outlier_rate), ("--miss-rate", args.miss_rate)):
        if value is not None:
            need(math.isfinite(value) and 0 <= value < 1, option, "a rate in [0, 1)", value)
    need(1 <= args.render_samples <= 4096, "--render-samples", "1..4096", args.render_samples)
    sources = [o for o, v in (("--rendered", args.rendered), ("--keypoints", args.keypoints),
                              ("--detector-model", args.detector_model)) if v]
    if len(sources) > 1:
        raise ValueError(f"{' and '.join(sources)} each say where the keypoints come from: "
                         f"give one")
    if args.distance_mm is not None:
        need(math.isfinite(args.distance_mm) and 0 < args.distance_mm <= MAX_DISTANCE_MM,
             "--distance-mm", f"a distance in (0, {MAX_DISTANCE_MM:g}] mm", args.distance_mm)
    if args.body_calibration:
        need(not (args.keypoints or args.rendered), "--body-calibration",
             "keypoints drawn by a detector model (Gaussian or --detector-model); calibrate a "
             "detector's own files with `calibrate-keypoints`",
             "--keypoints" if args.keypoints else "--rendered")
        need(args.run or args.rig, "--body-calibration", "the true cameras of --run or --rig",
             "--capture" if args.capture else "--calibration")


def body_session(args) -> Session | None:
    """--body-* as a body_session.Session (None without --body-calibration)."""
    if not args.body_calibration:
        return None
    try:
        return Session(args.body_people, args.body_frames, args.body_scale,
                       args.max_offset_frames)
    except ValueError as e:
        field, _, rest = str(e).partition(":")
        option = {"people": "--body-people", "frames": "--body-frames",
                  "max_offset_frames": "--max-offset-frames"}.get(field, field)
        raise ValueError(f"{option}:{rest}") from None


def _warnings(results: dict) -> list[str]:
    """What the user must know to read the numbers: too few detections, joints too few cameras
    saw, no method to compare."""
    out = []
    counts = results["detections"]
    if counts.get("views") and counts["detected"] < MIN_DETECTED * counts["views"]:
        out.append(f"only {counts['detected']} of {counts['views']} joint views were detected "
                   f"({counts['detected'] / counts['views']:.0%}); MPJPE rests on few "
                   f"triangulated joints")
    under = results["under_two_views"]
    if under:
        worst = sorted(under.items(), key=lambda kv: -kv[1])[:5]
        out.append(f"{sum(under.values())} joints (frames x joints, all trials) were detected by "
                   f"fewer than two cameras and are not triangulated (counted as missing), most "
                   f"often " + ", ".join(f"{j} ({n})" for j, n in worst))
    if results["settings"]["calib"] == "all" and list(results["methods"]) == ["gt"]:
        out.append(f"{results['settings']['source']}: no calibrated rig in this run (a mono rig, "
                   f"or written by `stereo-bench calibrate`); only the true cameras (gt) are "
                   f"reported")
    return out


def _evaluate_method(cameras, keypoints, scene, robust, fit, model) -> tuple[dict, dict]:
    """One method in one trial -> (its entry of pose metrics per stage, {stage: joints
    (T, 24, 3)})."""
    joints, dropped = triangulate_joints(cameras, keypoints, robust)
    entry = {"triangulated": pose_metrics(joints, scene.joints), "dropped_detections": dropped}
    stages = {"triangulated": joints}
    if fit:
        # A joint counts as much as its keypoints were trusted (occluded views: 0.3).
        fitted = fit_smpl(joints, weights=keypoints.confidence.mean(axis=0), model=model)
        entry["fitted"] = pose_metrics(fitted.joints, scene.joints)
        entry["fit"] = {"rms_mm": fitted.rms_mm, "iterations": fitted.iterations}
        stages["fitted"] = fitted.joints
    return entry, stages


def evaluate_trial(truth, rigs: dict, keypoints, scene, robust: bool = False,
                   fit: bool = False, model=None, label: str = "") -> tuple[dict, dict]:
    """gt and every method of one trial, on the same keypoints.

    rigs: {method: its cameras in the true world (pose_eval.scene.in_true_world), or the message
    saying why it has none}; gt (``truth``) comes first. A method whose cameras cannot be used
    (ValueError) is recorded as failed, its message prefixed by ``label``, and the others go on.
    Returns ({method: entry}, {method: {stage: joints (T, 24, 3)}}); each stage of an entry
    carries its paired cost against gt's (report.COST, pose_eval.metrics.excess_mpjpe) and gt's
    MPJPE of this trial (report.FLOOR), so that summaries over trials stay paired.
    """
    entries, joints = {}, {}
    for m, cameras in {"gt": truth, **rigs}.items():
        if isinstance(cameras, str):
            entries[m] = {"error": cameras}
            continue
        try:
            entries[m], joints[m] = _evaluate_method(cameras, keypoints, scene, robust, fit,
                                                     model)
        except ValueError as e:  # one method's degenerate estimate must not stop the others
            entries[m] = {"error": f"{label}: {e}" if label else str(e)}
    for stage, _ in STAGES:
        if stage in joints.get("gt", {}):
            for m, by_stage in joints.items():
                entries[m][stage][COST] = excess_mpjpe(by_stage[stage], joints["gt"][stage],
                                                       scene.joints)
                entries[m][stage][FLOOR] = entries["gt"][stage]["mpjpe_mm"]
    return entries, joints


def run_rigs(methods: list[str], run_trial: Trial) -> dict:
    """{method: cameras in the true world, or why there are none} of one run trial, gt aside."""
    rigs = {}
    for m in methods:
        if m == "gt":
            continue
        estimate = run_trial.rigs.get(m, f"no rig of {m} in this trial")
        if isinstance(estimate, str):
            rigs[m] = f"calibration failed in run trial seed {run_trial.seed}: {estimate}"
            continue
        try:
            rigs[m] = in_true_world(estimate, run_trial.truth)
        except ValueError as e:
            rigs[m] = f"run trial seed {run_trial.seed}: {e}"
    return rigs


def _imported(args, truth) -> dict:
    """{file:<name>: (the --calibration's cameras as a rig of the true cameras, how they were
    matched)}, or {} without --calibration."""
    if not args.calibration:
        return {}
    from stereo_bench import io
    from stereo_bench.run.exchange import as_rig_of

    cams, how = as_rig_of(io.load(args.calibration, args.calibration_format),
                          [c.name for c in truth], args.calibration)
    return {f"file:{Path(args.calibration).name}": (cams, how)}


def _placed(cameras, truth):
    """An imported rig in the true world, or why it cannot be (recorded as that method's
    failure, as a run's failed calibration is)."""
    try:
        return in_true_world(cameras, truth)
    except ValueError as e:
        return str(e)


def _display(truth, *joints):
    """Joints (24, 3) in the rig's (right, depth, up) axes, for the skeleton plot."""
    centre, axis, up, _ = rig_axes(truth)
    basis = np.stack([np.cross(axis, up), axis, up])
    return tuple((j - centre) @ basis.T for j in joints)


def evaluate(args) -> tuple[dict, dict]:
    """Run every trial -> (results, {method: (truth, estimate) of trial 0's middle frame (24, 3)
    in the rig's (right, depth, up) axes, for the skeleton plot})."""
    check_options(args)
    noise = (args.noise_px, args.outlier_rate, args.miss_rate)
    if (args.keypoints or args.rendered or args.detector_model) and any(
            v is not None for v in noise):
        raise ValueError("--noise-px, --outlier-rate and --miss-rate shape the Gaussian "
                         "synthetic keypoints; they do not apply with --keypoints, --rendered "
                         "or --detector-model")
    fitted = (load_fit(None if args.detector_model == "blazepose" else args.detector_model)
              if args.detector_model else None)
    if args.rendered:
        from stereo_bench.render.blender.environment import require

        require()  # before anything is placed or rendered
    rig, env, run_trials = _inputs(args)
    if len(run_trials[0].truth) < 2:
        raise ValueError(f"{_source(args)}: {len(run_trials[0].truth)} camera; "
                         f"triangulating a pose needs at least two")
    methods = _methods(args, run_trials)
    # --calibration alone is the true cameras, not an estimate of them.
    as_truth = not (args.run or args.rig or args.capture)
    imported = {} if as_truth else _imported(args, run_trials[0].truth)
    run_methods, methods = methods, methods + list(imported)
    session = body_session(args)
    methods += [BODY] if session is not None else []
    offsets = _clock_offsets(args)
    clocked = bool(np.any(offsets != 0)) if offsets is not None else False
    if clocked and args.rendered:
        raise ValueError(f"--rendered: {_source(args)} gives its cameras time_offset_ms; the "
                         f"Blender body renders take every camera at the same instant")
    detector = DetectorModel(*(d if v is None else v for v, d in zip(noise, (NOISE_PX, 0.0, 0.0))),
                             occlusion=not args.no_occlusion)

    def draw(cameras, scene, rng, occluded=None):
        """Synthetic keypoints of ``scene`` in ``cameras``: the fitted detector's or Gaussian."""
        if fitted is not None:
            return observe_fitted(cameras, scene, fitted, rng, occluded)
        return observe(cameras, scene, detector, rng, occluded)

    body_errors = []
    n_trials = args.trials or len(run_trials)
    model = load_body_model(args.model_path)
    shown = "fitted" if args.fit_smpl else "triangulated"  # the stage shown and plotted
    scenes = {}  # the true cameras of every run trial are normally the same: one scene
    per_method = {m: [] for m in methods}
    raw, examples = [], {}
    detections: dict[str, int] = {}
    under_two_views = np.zeros(NUM_JOINTS, dtype=np.int64)  # frames per joint, all trials
    placement: list[str] = []  # warnings of placing the body
    for i in range(n_trials):
        run_trial = run_trials[i % len(run_trials)]
        truth = run_trial.truth
        key = json.dumps([c.to_dict() for c in truth])
        if key not in scenes:
            # A body out of some camera's view is said in the results, not only on stderr.
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                try:
                    views = (seen_by_clocks(truth, [Person(args.motion)], args.frames,
                                            model=model, offsets_ms=offsets)
                             if clocked else None)
                    scene = (views[0][0] if clocked else
                             make_scene(truth, args.motion, args.frames, model=model,
                                        distance_mm=args.distance_mm))
                except ValueError as e:  # a rig with no place for a body: name its file
                    raise ValueError(f"{_source(args)}: {e}") from None
            placement += [str(w.message) for w in caught if str(w.message) not in placement]
            # The fitted detector's figures differ for hidden joints: it always needs them.
            occluded = (scene_occlusion(truth, scene) if (detector.occlusion or fitted is not None)
                        and not clocked else None)
            rendered = (_rendered_keypoints(truth, scene, model, output_dir(args, rig), args)
                        if args.rendered else None)
            scenes[key] = scene, occluded, rendered, views
        scene, occluded, rendered, views = scenes[key]
        if rendered is not None:
            keypoints, detector_2d = rendered
        elif args.keypoints:
            keypoints = read_openpose(args.keypoints, truth, args.frames)
        elif clocked:  # each camera sees the body at its own clock, truth at camera 0's
            keypoints = keypoints_at_clocks(truth, views, draw, [args.seed, i])
        else:
            keypoints = draw(truth, scene, np.random.default_rng([args.seed, i]), occluded)
        for k, v in keypoints.counts().items():
            detections[k] = detections.get(k, 0) + v
        under_two_views += keypoints.under_two_views().sum(axis=0)
        rigs = {**run_rigs(run_methods, run_trial),
                **{m: _placed(cams, truth) for m, (cams, _) in imported.items()}}
        if session is not None:
            # Its own streams: the session's keypoint noise owes nothing to the evaluation's.
            rigs[BODY], errors, said = _body_rig(truth, offsets, session, model, draw,
                                                 [args.seed, i, BODY_STREAM])
            body_errors.append(errors)
            placement += [w for w in said if w not in placement]
        entries, joints = evaluate_trial(truth, rigs, keypoints, scene,
                                         args.robust, args.fit_smpl, model,
                                         label=f"run trial seed {run_trial.seed}")
        for m in methods:
            per_method[m].append(entries[m])
            if m in joints and m not in examples:
                examples[m] = _display(truth, scene.joints[args.frames // 2],
                                       joints[m][shown][args.frames // 2])
        raw.append({"trial": i, "run_seed": run_trial.seed, "noise_seed": [args.seed, i],
                    "methods": entries})
        console.print(f"trial {i + 1}/{n_trials}, MPJPE ({dict(STAGES)[shown]}): " + ", ".join(
            f"{m} {e[shown]['mpjpe_mm']:.3f} mm" if "error" not in e else f"{m} failed"
            for m, e in entries.items()))
    first_scene, _, first_rendered, _ = next(iter(scenes.values()))
    settings = {
        "calib": args.calib,
        "calibration": {m: {"file": args.calibration, "cameras": how}
                        for m, (_, how) in imported.items()},
        "motion": args.motion, "frames": args.frames, "trials": n_trials,
        "distance_mm": first_scene.distance_mm, "surrounded": first_scene.surrounded,
        "robust": args.robust, "fit_smpl": args.fit_smpl,
        "model_path": args.model_path, "source": _source(args), "seed": args.seed,
        "keypoints": ("BlazePose (MediaPipe 0.10.21, full) on Blender renders, "
                      f"{args.render_samples} samples" if args.rendered else
                      f"OpenPose files from {args.keypoints}" if args.keypoints else
                      f"synthetic, drawn from the fitted detector {fitted.name!r} "
                      f"({args.detector_model})" if fitted is not None else
                      f"synthetic, noise {detector.noise_px} px, outliers "
                      f"{detector.outlier_rate:.0%}, misses {detector.miss_rate:.0%}, occlusion "
                      f"{'on' if detector.occlusion else 'off'}"),
    }
    results = {"rig": rig, "environment": env, "settings": settings, "detections": detections,
               "under_two_views": {j: int(n) for j, n in zip(JOINT_NAMES, under_two_views) if n},
               "methods": {m: aggregate(per_method[m]) for m in methods}, "trials": raw}
    if session is not None:
        results["body_calibration"] = body_summary(session, offsets, body_errors)
    if first_rendered is not None:
        results["detector_2d"] = first_rendered[1]
    results["warnings"] = placement + _warnings(results)
    return results, examples


def _clock_offsets(args) -> np.ndarray | None:
    """(C,) the cameras' time_offset_ms from the run's or the rig file's cameras (None for a
    capture or a calibration file: no clocks are known)."""
    if args.run:
        cfg = run_config(args.run)
        return cfg.time_offsets_ms() if cfg is not None else None
    return load_rig(args.rig).time_offsets_ms() if args.rig else None


def _body_rig(truth, offsets, session, model, draw, seed) -> tuple:
    """(the studio calibrated from the body in the true world, or why it failed; its errors
    against the truth, or {"error": why}; the warnings of placing its walkers)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            _, errors, cameras = calibrate_session(
                truth, np.zeros(len(truth)) if offsets is None else offsets, session, model,
                draw, seed)
        except ValueError as e:
            cameras, errors = f"calibration from the body (seed {seed}): {e}", {"error": str(e)}
    return cameras, errors, [f"calibration from the body: {w.message}" for w in caught]


def output_dir(args, rig: str) -> Path:
    if args.out:
        return Path(args.out)
    if args.capture:  # beside the capture's own results
        return Path(args.capture) / "pose_eval"
    return Path("out") / (rig if is_safe_name(rig) else "run") / "pose_eval"


def _environment(args):
    """The imaging the rendered body is photographed through: the run's or the rig file's
    ``environment`` section (None for a capture or a calibration file: the render as it is)."""
    if args.run:
        cfg = run_config(args.run)
        return cfg.environment if cfg is not None else None
    return load_rig(args.rig).environment if args.rig else None


def _rendered_keypoints(cameras, scene, model, out: Path, args):
    """(keypoints, the detector's error per joint) of BlazePose on Blender renders of ``scene``
    through ``cameras``, photographed through the run's imaging (its noise, lens blur,
    vignetting and JPEG: photoreal.photograph_body), written to OUT/body/ (images, the
    photographed images, OpenPose files, true joints)."""
    from .photoreal import keypoint_errors, recorded_keypoints, render_body

    body = out / "body"
    console.print(f"rendering {len(scene.joints)} frames x {len(cameras)} cameras with Blender "
                  f"into {body}/images ...")
    render_body(cameras, scene, model.lbs_weights.detach().cpu().numpy(), body,
                samples=args.render_samples,
                progress=lambda d, n: console.print(f"  frame {d}/{n}") if d % 10 == 0 or d == n
                else None)
    environment = _environment(args)
    if environment is not None and environment.kind != "clean":
        console.print(f"photographing them as the {environment.kind} cameras record them ...")
    keypoints = recorded_keypoints(cameras, scene, body / "images", environment, body, args.seed)
    write_openpose(body / "keypoints", cameras, keypoints)
    return keypoints, keypoint_errors(cameras, keypoints, scene.joints)


def write_outputs(results: dict, examples: dict, out: Path) -> None:
    """results.json, report.md, mpjpe.png, skeleton.png (the chosen method, trial 0) and
    report.html (all of it in one page)."""
    write_json(out / "results.json", results)
    text = markdown(results)
    write_text(out / "report.md", text)
    plot_mpjpe(results, out / "mpjpe.png")
    figures = [out / "mpjpe.png"]
    shown = next((m for m in examples if m != "gt"), "gt")
    if shown in examples:
        stage = dict(STAGES)[headline_stage(results)]
        plot_skeleton(*examples[shown], out / "skeleton.png",
                      f"{shown} ({stage}), frame {results['settings']['frames'] // 2}")
        figures.append(out / "skeleton.png")
    write_html(out / "report.html", f"pose-eval: {results['rig']}", text, figures,
               provenance(seeds=[results["settings"]["seed"]]),
               json.dumps(results["settings"], indent=2), methods=list(results["methods"]))


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if not (args.run or args.rig or args.capture or args.calibration):
        args.run = DEFAULT_RUN
    try:
        results, examples = evaluate(args)
        out = output_dir(args, results["rig"])
        with locked(out):
            write_outputs(results, examples, out)
    except (ConfigError, FileNotFoundError, ValueError, WorkerUnavailable, WorkerError) as e:
        say("error", "red", str(e))
        return 2
    except OSError as e:
        say("error", "red", f"{e.filename + ': ' if e.filename else ''}{e.strerror or e}")
        return 2
    console.print(markdown(results), markup=False, soft_wrap=True, highlight=False)
    for w in results["warnings"]:
        say("warning", "yellow", w)
    console.print(f"wrote {out}/results.json, report.md, report.html, mpjpe.png, skeleton.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
