"""Detection time per frame of every board on the paper's two cameras, beside OpenCV's own pipeline.

For each of the four boards and each camera (rectilinear 4096 x 3072 and wide-angle 640 x 480,
from configs/paper/*_mono.yaml with the board swapped in, as benchmarks/detection_accuracy.py
renders them, clean unless ``--environment`` names another imaging preset), the same frames are
detected, in turn frame by frame so that both see the same load on this machine, by

* stereo_bench.detect.dataset (its default method): the search on a reduced copy, then every point
  measured at full resolution (the saddle fit, or the disc centroid);
* OpenCV's own pipeline on the full image, as its documentation shows it: findChessboardCorners
  then cornerSubPix (11 x 11 window, 30 iterations or 0.001 px); findCirclesGrid with its default
  blob detector; cv2.aruco.CharucoDetector.detectBoard.

With ``--baseline REV`` the detection of git revision REV (checked out with ``git worktree add``
into a temporary directory and run in a subprocess that imports stereo_bench from there) is
timed on the same frames in the same turn, and the table says how far the working tree's points
are from that revision's (max |difference|, px, and whether the same points are NaN).

Prints, per pattern, camera and detector: frames found, share of the visible points detected,
mean and max distance to the exact ground truth (px, over the detected points of frames not
flipped), orientation flips, and wall-clock ms per frame with its ratio to OpenCV's, with the
OpenCV version and its thread count (timings depend on both).  It prints, it does not assert.

    python benchmarks/detection_speed.py [--frames 8] [--repeat 1] [--keep DIR] [--baseline REV]
        [--environment noisy] [--patterns checkerboard charuco]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
import time
from contextlib import contextmanager, nullcontext
from pathlib import Path

import cv2
import numpy as np

from detection_accuracy import CAMERAS, rig_with_board, row
from revision import revision_server
from stereo_bench.config.environments import PRESETS as ENVIRONMENTS
from stereo_bench.scene.dataset import Dataset, write_dataset
from stereo_bench.detect.boards import METHODS, detect
from stereo_bench.detect.dataset import CameraDetections, detection_errors

COLUMNS = ("pattern", "camera", "detector", "frames found", "points found", "mean", "max",
           "flips", "ms/frame", "x OpenCV")
SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.001)
# The subprocess that runs a revision's detection (revision.serve): answers (kind, pattern
# fields, gray image) with (points, seconds in detect).
SERVER = """
import time
from revision import serve
try:
    from stereo_bench.core.patterns import pattern_from_config
    from stereo_bench.detect.boards import detect
except ImportError:  # revisions before the packages (stereo_bench/detect.py, patterns.py)
    from stereo_bench.detect import detect
    from stereo_bench.patterns import pattern_from_config


def answer(request):
    kind, fields, gray = request
    pattern = pattern_from_config(kind, **fields)
    start = time.perf_counter()
    points = detect(gray, pattern).points
    return points, time.perf_counter() - start


serve(answer)
"""


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


def dataset_for(root: Path, camera: str, path: Path, kind: str, frames: int,
                environment: str) -> Dataset:
    """The dataset of ``kind`` on ``camera`` in ``environment`` under ``root``: reused if one
    with ``frames`` frames is there already (``--keep``), else rendered."""
    out = root / (f"{camera}_{kind}" if environment == "clean" else
                  f"{camera}_{kind}_{environment}")
    try:
        dataset = Dataset.load(out)
        if dataset.frames == frames:
            return dataset
    except (OSError, ValueError):
        pass
    return write_dataset(rig_with_board(path, kind, frames, environment), out)


@contextmanager
def revision_detector(rev: str):
    """A function (gray, pattern) -> (points, seconds) that runs ``rev``'s detection
    (revision.revision_server with ``SERVER``), timed inside the subprocess around detect
    alone."""
    with revision_server(rev, SERVER) as ask:
        def run(gray, pattern):
            fields = {f.name: getattr(pattern, f.name) for f in dataclasses.fields(pattern)
                      if f.init}
            return ask((pattern.kind, fields, gray))
        yield run


def timed(run):
    """A detector (gray, pattern) -> (points, seconds) from one that returns points only."""
    def detector(gray, pattern):
        start = time.perf_counter()
        points = run(gray, pattern)
        return points, time.perf_counter() - start
    return detector


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=8, help="frames per dataset (default 8)")
    parser.add_argument("--keep", type=Path, help="write (or reuse) the datasets here instead of "
                                                  "a temp dir")
    parser.add_argument("--baseline", metavar="REV", help="also time git revision REV's "
                                                          "detection on the same frames")
    parser.add_argument("--environment", default="clean", choices=ENVIRONMENTS,
                        help="the imaging preset the frames are rendered in (default clean)")
    parser.add_argument("--patterns", nargs="+", choices=list(METHODS), default=list(METHODS),
                        help="the boards measured (default: all four)")
    parser.add_argument("--repeat", type=int, default=1, help="detect each frame this many "
                        "times with each detector (a small camera's few ms vary from run to run)")
    args = parser.parse_args(argv)
    for option, value in (("--frames", args.frames), ("--repeat", args.repeat)):
        if value < 1:
            parser.error(f"{option}: expected a positive count, got {value}")

    with tempfile.TemporaryDirectory() as tmp, (
            revision_detector(args.baseline) if args.baseline else nullcontext()) as baseline:
        detectors = {"stereo_bench": timed(lambda gray, pattern: detect(gray, pattern).points),
                     "OpenCV": timed(opencv_pipeline)}
        columns = COLUMNS
        if baseline:
            detectors = {f"stereo_bench@{args.baseline}": baseline, **detectors}
            columns += ("max |new - base| px", "same NaN rows")
        print(f"OpenCV {cv2.__version__} ({cv2.getNumThreads()} threads), {args.frames} frames "
              f"per dataset, each detected {args.repeat} time(s) per detector, "
              f"{args.environment} renders; distances in px against the ground truth\n")
        print(row(columns))
        print(row("---" for _ in columns))
        root = args.keep or Path(tmp)
        for kind in args.patterns:
            for camera, path in CAMERAS.items():
                measure(dataset_for(root, camera, path, kind, args.frames, args.environment),
                        camera, kind, detectors, args.baseline, args.repeat)


def measure(dataset: Dataset, camera: str, kind: str, detectors: dict, baseline: str | None,
            repeat: int = 1):
    """Detect every frame of ``dataset`` ``repeat`` times with each detector in turn (frame by
    frame, so all see the same load) and print a row per detector, its mean time a detection
    beside OpenCV's."""
    pattern, n = dataset.pattern, len(dataset.pattern.ids())
    points = {name: np.full((dataset.frames, n, 2), np.nan) for name in detectors}
    seconds = dict.fromkeys(detectors, 0.0)
    # One untimed detection each first: a process's one-off costs (loading the compiled
    # measurement kernels, OpenCV's first calls) are not a frame's.
    for run in detectors.values():
        run(dataset.image(0, 0), pattern)
    for f in range(dataset.frames):
        gray = dataset.image(0, f)
        if gray.ndim == 3:
            gray = cv2.cvtColor(gray, cv2.COLOR_BGR2GRAY)
        for _ in range(repeat):
            for name, run in detectors.items():
                points[name][f], spent = run(gray, pattern)
                seconds[name] += spent / repeat
    truth = dataset.ground_truth
    for name in detectors:
        found = np.isfinite(points[name]).all(-1).any(-1)
        e = detection_errors(CameraDetections(camera, kind, name, points[name], found,
                                              pattern.ids()),
                             truth.points[0], truth.visible[0])
        cells = [kind, camera, name, f"{e['found']}/{e['frames']}",
                 f"{100 * e['point_detection_rate']:.1f} %", f"{e['mean_px']:.4f}",
                 f"{e['max_px']:.4f}", e["flips"], f"{1e3 * seconds[name] / dataset.frames:.1f}",
                 f"{seconds[name] / seconds['OpenCV']:.2f}"]
        if baseline:
            old, new = points[f"stereo_bench@{baseline}"], points["stereo_bench"]
            same = np.array_equal(np.isnan(old), np.isnan(new))
            cells += ([f"{np.nanmax(np.abs(new - old), initial=0.0):.1e}", "yes" if same else "NO"]
                      if name == "stereo_bench" else ["", ""])
        print(row(cells))
    sys.stdout.flush()


if __name__ == "__main__":
    main()
