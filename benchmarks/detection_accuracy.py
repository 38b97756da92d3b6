"""Detection accuracy of every board and detector on the paper's two cameras, on clean renders.

For each of the four boards and each camera (rectilinear 4096 x 3072 and wide-angle 640 x 480, from
configs/paper/*_mono.yaml with the board swapped in), render a clean dataset along the paper's
conical-spring trajectory with fewer frames, detect it with every method of stereo_bench.detect.dataset
and compare with the exact ground truth.  Prints one table: frame detection rate, share of the
visible points detected, distance statistics over the detected points (px), signed mean error,
orientation flips, and wall-clock detection time per frame (this machine, the OpenCV version
printed above the table).

    python benchmarks/detection_accuracy.py [--frames 24] [--keep DIR]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import cv2

from stereo_bench.config.schema import load_rig, parse_rig
from stereo_bench.scene.dataset import write_dataset
from stereo_bench.detect.boards import METHODS
from stereo_bench.detect.dataset import detect_dataset, detection_errors

CONFIGS = Path(__file__).resolve().parents[1] / "configs" / "paper"
CAMERAS = {"rectilinear": CONFIGS / "rectilinear_mono.yaml", "wide": CONFIGS / "wide_mono.yaml"}
COLUMNS = ("pattern", "camera", "detector", "frames found", "points found", "mean", "RMS", "max",
           "mean dx", "mean dy", "flips", "s/frame")


def rig_with_board(path: Path, kind: str, frames: int, environment: str = "clean"):
    """The rig of ``path`` with its board replaced by a default ``kind``, ``frames`` frames and
    the imaging ``environment`` (a preset name)."""
    data = load_rig(path).model_dump(mode="json")
    data["pattern"] = {"kind": kind}
    data["trajectory"]["frames"] = frames
    data["environment"] = {"kind": environment}
    data["name"] = f"{data['name']}_{kind}"
    return parse_rig(data, f"{path} with pattern {kind}, environment {environment}")


def row(cells) -> str:
    return "| " + " | ".join(str(c) for c in cells) + " |"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=24, help="frames per dataset (default 24)")
    parser.add_argument("--keep", type=Path, help="write the datasets here instead of a temp dir")
    args = parser.parse_args(argv)

    print(f"OpenCV {cv2.__version__}, {args.frames} frames per dataset, clean renders; "
          f"distances in px\n")
    print(row(COLUMNS))
    print(row("---" for _ in COLUMNS))
    with tempfile.TemporaryDirectory() as tmp:
        root = args.keep or Path(tmp)
        for kind, methods in METHODS.items():
            for camera, path in CAMERAS.items():
                dataset = write_dataset(rig_with_board(path, kind, args.frames),
                                        root / f"{camera}_{kind}")
                truth = dataset.ground_truth
                for method in methods:
                    start = time.perf_counter()
                    [detections] = detect_dataset(dataset, method)
                    seconds = (time.perf_counter() - start) / dataset.frames
                    e = detection_errors(detections, truth.points[0], truth.visible[0])
                    print(row([kind, camera, method, f"{e['found']}/{e['frames']}",
                               f"{100 * e['point_detection_rate']:.1f} %",
                               *(f"{e[k]:.4f}" for k in ("mean_px", "rms_px", "max_px",
                                                         "mean_dx_px", "mean_dy_px")),
                               e["flips"], f"{seconds:.2f}"]))
                    for frame, reason in detections.errors.items():
                        print(f"    frame {frame}: {reason}", file=sys.stderr)
                    sys.stdout.flush()


if __name__ == "__main__":
    main()
