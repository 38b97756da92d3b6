"""Detection time per frame of every board on the paper's two cameras, beside OpenCV's own pipeline.

For each of the four boards and each camera (rectilinear 4096 x 3072 and wide-angle 640 x 480,
from configs/paper/*_mono.yaml with the board swapped in, as benchmarks/detection_accuracy.py
renders them), the same clean frames are detected, in turn frame by frame so that both see the
same load on this machine, by

* stereo_bench.detect.dataset (its default method): the search on a reduced copy, then every point
  measured at full resolution (the saddle fit, or the disc centroid);
* OpenCV's own pipeline on the full image, as its documentation shows it: findChessboardCorners
  then cornerSubPix (11 x 11 window, 30 iterations or 0.001 px); findCirclesGrid with its default
  blob detector; cv2.aruco.CharucoDetector.detectBoard.

Prints, per pattern, camera and detector: frames found, share of the visible points detected,
mean and max distance to the exact ground truth (px, over the detected points of frames not
flipped), orientation flips, and wall-clock seconds per frame, with the OpenCV version and its
thread count (timings depend on both).  It prints, it does not assert.

    python benchmarks/detection_speed.py [--frames 8] [--keep DIR]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from detection_accuracy import CAMERAS, rig_with_board, row
from stereo_bench.scene.dataset import Dataset, write_dataset
from stereo_bench.detect.boards import METHODS, detect
from stereo_bench.detect.dataset import CameraDetections, detection_errors

COLUMNS = ("pattern", "camera", "detector", "frames found", "points found", "mean", "max",
           "flips", "s/frame")
SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.001)


def opencv_pipeline(gray: np.ndarray, pattern) -> np.ndarray:
    """(N, 2) px in ``object_points()`` order as OpenCV's own pipeline returns them, NaN rows
    for points it did not return (all NaN when it finds no board)."""
    points = np.full((len(pattern.ids()), 2), np.nan)
    if pattern.kind == "checkerboard":
        ok, corners = cv2.findChessboardCorners(gray, pattern.pattern_size)
        if ok:
            points[:] = cv2.cornerSubPix(gray, corners, (11, 11), (-1, -1),
                                         SUBPIX_CRITERIA).reshape(-1, 2)
    elif pattern.kind == "charuco":
        corners, ids, _, _ = cv2.aruco.CharucoDetector(pattern.cv_board()).detectBoard(gray)
        if ids is not None:
            points[ids.ravel()] = corners.reshape(-1, 2)
    else:
        grid = (cv2.CALIB_CB_SYMMETRIC_GRID if pattern.kind == "symmetric_circles"
                else cv2.CALIB_CB_ASYMMETRIC_GRID)
        ok, centres = cv2.findCirclesGrid(gray, pattern.pattern_size, flags=grid)
        if ok:
            points[:] = centres.reshape(-1, 2)
    return points


def dataset_for(root: Path, camera: str, path: Path, kind: str, frames: int) -> Dataset:
    """The clean dataset of ``kind`` on ``camera`` under ``root``: reused if one with ``frames``
    frames is there already (``--keep``), else rendered."""
    out = root / f"{camera}_{kind}"
    try:
        dataset = Dataset.load(out)
        if dataset.frames == frames:
            return dataset
    except (OSError, ValueError):
        pass
    return write_dataset(rig_with_board(path, kind, frames), out)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=8, help="frames per dataset (default 8)")
    parser.add_argument("--keep", type=Path, help="write (or reuse) the datasets here instead of "
                                                  "a temp dir")
    args = parser.parse_args(argv)
    if args.frames < 1:
        raise ValueError(f"--frames: expected a positive frame count, got {args.frames}")

    print(f"OpenCV {cv2.__version__} ({cv2.getNumThreads()} threads), {args.frames} frames per "
          f"dataset, clean renders; distances in px against the ground truth\n")
    print(row(COLUMNS))
    print(row("---" for _ in COLUMNS))
    with tempfile.TemporaryDirectory() as tmp:
        root = args.keep or Path(tmp)
        for kind in METHODS:
            for camera, path in CAMERAS.items():
                dataset = dataset_for(root, camera, path, kind, args.frames)
                pattern, n = dataset.pattern, len(dataset.pattern.ids())
                results = {name: (np.full((dataset.frames, n, 2), np.nan), [0.0])
                           for name in ("stereo_bench", "OpenCV")}
                for f in range(dataset.frames):
                    gray = dataset.image(0, f)
                    if gray.ndim == 3:
                        gray = cv2.cvtColor(gray, cv2.COLOR_BGR2GRAY)
                    for name, run in (("stereo_bench", lambda: detect(gray, pattern).points),
                                      ("OpenCV", lambda: opencv_pipeline(gray, pattern))):
                        start = time.perf_counter()
                        results[name][0][f] = run()
                        results[name][1][0] += time.perf_counter() - start
                truth = dataset.ground_truth
                for name, (points, seconds) in results.items():
                    found = np.isfinite(points).all(-1).any(-1)
                    e = detection_errors(CameraDetections(camera, kind, name, points, found,
                                                          pattern.ids()),
                                         truth.points[0], truth.visible[0])
                    print(row([kind, camera, name, f"{e['found']}/{e['frames']}",
                               f"{100 * e['point_detection_rate']:.1f} %",
                               f"{e['mean_px']:.4f}", f"{e['max_px']:.4f}", e["flips"],
                               f"{seconds[0] / dataset.frames:.3f}"]))
                sys.stdout.flush()


if __name__ == "__main__":
    main()
