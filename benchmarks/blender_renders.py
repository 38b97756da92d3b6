"""Blender's Cycles beside the analytic renderer: the same rigs, poses and ground truth, detected.

For each of the paper's two cameras (wide-angle 640 x 480 and rectilinear 4096 x 3072, from
configs/paper/*_mono.yaml), each of the four boards and the clean and noisy environments, the
same frames are rendered by both backends (renderer.kind analytic / blender) and detected with
the board's default detector. Prints, per row: frames found, mean / max distance to the exact
ground truth (px, over the points detected in found frames that are not flipped), the signed
mean error (dx, dy: a bias), and the render time per frame (wall clock; Cycles on every core,
the analytic renderer on one), with the versions. Needs the worker environment
(`make blender`); without it, says so and stops.

    python benchmarks/blender_renders.py [--frames-wide 8] [--frames-rect 2] [--samples 64]
        [--cameras wide rectilinear] [--environments clean noisy] [--patterns ...]
        [--montage docs/images/blender_vs_analytic.png]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

from detection_accuracy import CAMERAS, rig_with_board, row
from stereo_bench.config.schema import parse_rig
from stereo_bench.scene.dataset import write_dataset
from stereo_bench.detect.boards import METHODS
from stereo_bench.detect.dataset import detect_dataset, detection_errors
from stereo_bench.render.blender import environment

COLUMNS = ("camera", "pattern", "environment", "renderer", "frames found", "mean", "max",
           "mean dx", "mean dy", "render s/frame")


def variant(camera: str, kind: str, env: str, renderer: str, frames: int, samples: int):
    cfg = rig_with_board(CAMERAS[camera], kind, frames)
    data = cfg.model_dump(mode="json")
    data["environment"] = {"kind": env}
    data["renderer"] = {"kind": renderer, "samples": samples}
    return parse_rig(data, f"{camera} {kind} {env} {renderer}")


def montage(datasets: dict, path: Path, frame: int = 0) -> None:
    """The same frame from both backends side by side: one row per (camera, environment)."""
    rows = []
    for (camera, env), pair in datasets.items():
        tiles = []
        for renderer in ("analytic", "blender"):
            image = cv2.cvtColor(pair[renderer].image(0, frame), cv2.COLOR_GRAY2BGR)
            image = cv2.resize(image, (640, 480), interpolation=cv2.INTER_AREA)
            cv2.putText(image, f"{camera}, {env}: {renderer}", (12, 32),
                        cv2.FONT_HERSHEY_SIMPLEX, 0.8, (0, 0, 255), 2, cv2.LINE_AA)
            tiles.append(image)
        rows.append(np.hstack(tiles))
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.vstack(rows))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames-wide", type=int, default=8)
    parser.add_argument("--frames-rect", type=int, default=2)
    parser.add_argument("--samples", type=int, default=64, help="Cycles samples per pixel")
    parser.add_argument("--patterns", nargs="+", default=list(METHODS))
    parser.add_argument("--cameras", nargs="+", default=["wide", "rectilinear"],
                        choices=["wide", "rectilinear"])
    parser.add_argument("--environments", nargs="+", default=["clean", "noisy"],
                        choices=["clean", "noisy"])
    parser.add_argument("--montage", type=Path, help="write the side-by-side figure here")
    args = parser.parse_args(argv)
    reason = environment.status()
    if reason:
        print(reason, file=sys.stderr)
        return 1
    bpy_version = subprocess.run([str(environment.python()), "-c",
                                  "import bpy; print(bpy.app.version_string)"],
                                 capture_output=True, text=True).stdout.strip()
    print(f"Blender {bpy_version} (Cycles, CPU, {args.samples} samples, box pixel filter), "
          f"OpenCV {cv2.__version__}; distances in px against the ground truth\n")
    print(row(COLUMNS))
    print(row("---" for _ in COLUMNS))
    shown = {}
    with tempfile.TemporaryDirectory() as tmp:
        for camera in args.cameras:
            frames = args.frames_wide if camera == "wide" else args.frames_rect
            for kind in args.patterns:
                for env in args.environments:
                    for renderer in ("analytic", "blender"):
                        cfg = variant(camera, kind, env, renderer, frames, args.samples)
                        dataset = write_dataset(cfg, Path(tmp) / f"{camera}_{kind}_{env}_"
                                                                 f"{renderer}")
                        truth = dataset.ground_truth
                        [found] = detect_dataset(dataset)
                        e = detection_errors(found, truth.points[0], truth.visible[0])
                        print(row([camera, kind, env, renderer, f"{e['found']}/{e['frames']}",
                                   *(f"{e[k]:.4f}" for k in ("mean_px", "max_px", "mean_dx_px",
                                                             "mean_dy_px")),
                                   f"{dataset.render_time_s / dataset.frames:.2f}"]))
                        sys.stdout.flush()
                        if kind == "checkerboard":
                            shown.setdefault((camera, env), {})[renderer] = dataset
            if args.montage and shown:
                montage(shown, args.montage)
    return 0


if __name__ == "__main__":
    sys.exit(main())
