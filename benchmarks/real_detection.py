"""Detection on real photographs: OpenCV's sample stereo images (shared/real/opencv_stereo).

The board has 9 x 6 inner corners (10 x 7 squares, side 1.0: lengths in squares) and almost no
white margin: its outer squares are cut short by the edge of the print, and the dark rim of the
surface it lies on is right beside them.  Per camera this prints the ``opencv`` method's RPE
(all 13 views, 5 coefficients) on this project's detections and on OpenCV's own pipeline
(findChessboardCorners with ADAPTIVE_THRESH | NORMALIZE_IMAGE, cornerSubPix with an 11 x 11
half-window and (COUNT + EPS, 30, 0.01), as OpenCV's stereo_calib sample), the corners more than
1 px apart, the corners the detector left unmeasured, and which of the two disagreeing versions a
calibration from the agreeing corners (within 0.5 px) predicts: the mean distance of each
version's disagreeing corners from that calibration's projections.

    python benchmarks/real_detection.py [--images DIR]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from stereo_bench.calibrate import Observations, get_calibrator
from stereo_bench.detect.boards import detect
from stereo_bench.core.patterns import Checkerboard

IMAGES = Path(__file__).resolve().parents[1].parent / "shared" / "real" / "opencv_stereo"
PATTERN = Checkerboard(squares_x=10, squares_y=7, square_mm=1.0, margin_mm=0.0)
COLUMNS = ("camera", "views", "RPE ours px", "RPE OpenCV px", "> 1 px apart", "unmeasured",
           "disagreeing: ours / OpenCV's px from the agreeing calibration")


def opencv_pipeline(gray: np.ndarray) -> np.ndarray | None:
    ok, corners = cv2.findChessboardCorners(
        gray, PATTERN.pattern_size, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
    if not ok:
        return None
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 30, 0.01)
    return cv2.cornerSubPix(gray, corners, (11, 11), (-1, -1), criteria).reshape(-1, 2).astype(
        np.float64)


def calibrate(views: list[np.ndarray], masks: list[np.ndarray], size: tuple[int, int]):
    obj = PATTERN.object_points()
    obs = Observations([obj[m] for m in masks], [v[m] for v, m in zip(views, masks)], size,
                       list(range(len(views))))
    return get_calibrator("opencv").calibrate(obs)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--images", type=Path, default=IMAGES,
                        help=f"folder of left*.jpg / right*.jpg (default {IMAGES})")
    args = parser.parse_args(argv)
    print(f"OpenCV {cv2.__version__}, {args.images}\n")
    print("| " + " | ".join(COLUMNS) + " |")
    print("|" + "---|" * len(COLUMNS))
    for camera in ("left", "right"):
        ours, theirs, size = [], [], None
        for path in sorted(args.images.glob(f"{camera}*.jpg")):
            gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
            if gray is None:
                raise ValueError(f"{path}: not a readable image")
            size = gray.shape[::-1]
            detection, reference = detect(gray, PATTERN), opencv_pipeline(gray)
            if not detection.found or reference is None:
                print(f"    {path.name}: not found ({detection.error or 'OpenCV pipeline'})")
                continue
            # OpenCV's order is either the board's or its reverse (it reads no colours).
            flipped = reference[::-1]
            if np.nanmean(np.linalg.norm(detection.points - flipped, axis=1)) < np.nanmean(
                    np.linalg.norm(detection.points - reference, axis=1)):
                reference = flipped
            ours.append(detection.points)
            theirs.append(reference)
        if not ours:
            print(f"| {camera} | 0 | | | | | |")
            continue
        seen = [np.isfinite(p).all(axis=1) for p in ours]
        every = [np.ones(len(p), bool) for p in theirs]
        apart = [np.linalg.norm(p - r, axis=1) for p, r in zip(ours, theirs)]
        agree = [s & (a < 0.5) for s, a in zip(seen, apart)]
        judge = calibrate(theirs, agree, size)
        far = {"ours": [], "opencv": []}
        K, dist = judge.camera.K, judge.camera.dist[:5]
        for p, r, s, a, rvec, tvec in zip(ours, theirs, seen, apart, judge.rvecs, judge.tvecs):
            predicted = cv2.projectPoints(PATTERN.object_points(), rvec, tvec, K, dist)[0]
            predicted = predicted.reshape(-1, 2)
            off = s & (a > 1.0)
            far["ours"] += list(np.linalg.norm(p[off] - predicted[off], axis=1))
            far["opencv"] += list(np.linalg.norm(r[off] - predicted[off], axis=1))
        verdict = (f"{np.mean(far['ours']):.2f} / {np.mean(far['opencv']):.2f}" if far["ours"]
                   else "-")
        print(f"| {camera} | {len(ours)} | {calibrate(ours, seen, size).log['rms_px']:.3f} | "
              f"{calibrate(theirs, every, size).log['rms_px']:.3f} | "
              f"{sum(int((s & (a > 1.0)).sum()) for s, a in zip(seen, apart))} | "
              f"{sum(int((~s).sum()) for s in seen)} | {verdict} |")


if __name__ == "__main__":
    main()
