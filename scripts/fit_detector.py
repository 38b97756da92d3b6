"""Fit BlazePose's keypoint error on Blender renders of a studio (pose_eval.detector_fit) and
write it as a detector model that pose-eval (--detector-model) and stereo-bench study
(the blazepose_fit detector) replay without Blender.

The body of each motion is rendered once through the studio's true cameras (reused from
BODIES when already there: pose_eval.study.render_bodies), BlazePose runs on every clean
frame, and the model is fitted to all motions together. The shipped
pose_eval/data/blazepose_fit.json was made by

    python scripts/fit_detector.py configs/studios/h36m_rectangle.yaml \\
        --motions walk_circle arm_raise squat --frames 60 --samples 8 --bodies out/bodies

It then prints the floors of BlazePose and of the fitted model through the true cameras on the
same scenes (MPJPE over the joints BlazePose reports), side by side: the model is meant to give
the detector's floor.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from stereo_bench.config.schema import load_rig
from stereo_bench.core.files import write_json
from stereo_bench.render.blender.environment import REQUIREMENTS
from pose_eval.body import load_body_model
from pose_eval.detector_fit import SHIPPED, fit_detector, observe_fitted
from pose_eval.metrics import pose_metrics
from pose_eval.motion import JOINT_NAMES
from pose_eval.photoreal import detect_keypoints
from pose_eval.reconstruct import triangulate_joints
from pose_eval.scene import make_scene
from pose_eval.study import body_folder, render_bodies


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("rig", help="a studio rig file")
    p.add_argument("--motions", nargs="+", default=["walk_circle", "arm_raise", "squat"])
    p.add_argument("--frames", type=int, default=60)
    p.add_argument("--samples", type=int, default=8, help="Cycles samples per pixel")
    p.add_argument("--bodies", default="out/bodies", help="folder of the rendered bodies")
    p.add_argument("--out", default=str(SHIPPED), help="the model's JSON file")
    args = p.parse_args()

    rig = Path(args.rig).stem
    cameras = load_rig(args.rig).cameras_true()
    render_bodies(rig, cameras, args.motions, args.frames, args.samples, Path(args.bodies),
                  print)
    model = load_body_model()
    scenes, keypoints = [], []
    for motion in args.motions:
        folder = body_folder(Path(args.bodies), rig, motion, args.frames, args.samples)
        scenes.append(make_scene(cameras, motion, args.frames, model=model))
        keypoints.append(detect_keypoints(cameras, folder / "images", args.frames))
    mediapipe = next(r for r in REQUIREMENTS if r.startswith("mediapipe"))
    source = {"detector": f"BlazePose GHUM full ({mediapipe}), landmarks mapped to SMPL's "
                          f"joints",
              "rig": rig, "motions": args.motions, "frames": args.frames,
              "render_samples": args.samples, "cameras": len(cameras),
              "script": "scripts/fit_detector.py"}
    fit = fit_detector("blazepose", cameras, scenes, keypoints, source)
    write_json(args.out, fit.to_dict())
    print(f"wrote {args.out}")
    print("joint: offset in the body frame (mm), noise sigma seen / hidden (mm), "
          "gross share, miss share")
    for j in np.flatnonzero(fit.reported):
        print(f"  {JOINT_NAMES[j]:>15}: {np.round(fit.offset_mm[j], 1)}, "
              f"{fit.sigma_mm[j, 0]:.1f} / {fit.sigma_mm[j, 1]:.1f}, "
              f"{fit.gross_rate[j, 0]:.3f}, {fit.miss_rate[j, 0]:.3f}")
    print("floor (MPJPE through the true cameras, mm): BlazePose | fitted model")
    for motion, scene, kp in zip(args.motions, scenes, keypoints):
        real = pose_metrics(triangulate_joints(cameras, kp)[0], scene.joints)["mpjpe_mm"]
        drawn = [pose_metrics(triangulate_joints(cameras, observe_fitted(
            cameras, scene, fit, np.random.default_rng(s)))[0], scene.joints)["mpjpe_mm"]
            for s in range(5)]
        print(f"  {motion:>12}: {real:.1f} | {np.mean(drawn):.1f} (5 draws, "
              f"{min(drawn):.1f}-{max(drawn):.1f})")



if __name__ == "__main__":
    main()
