"""Every method on OpenCV's real sample stereo pair, with the project's detector beside OpenCV's own
pipeline's detections, and the rig beside cv2.stereoCalibrate.

OpenCV's pipeline (shared/real/README.md): findChessboardCorners with ADAPTIVE_THRESH and
NORMALIZE_IMAGE, cornerSubPix 11x11 (30 iterations or 0.01 px, as OpenCV's stereo_calib
sample), calibrateCamera with 5 coefficients, stereoCalibrate with FIX_INTRINSIC. Both
sets of detections go through the same calibration and held-out stages
(stage.calibrate_cameras, diagnostics.heldout), so a difference is the detector's.

    python benchmarks/real_calibration.py [--methods zhang,bouguet,opencv,...] [--square-mm 1]
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import cv2
import numpy as np

from stereo_bench.calibrate import check_methods
from stereo_bench.config.schema import CalibrationConfig
from stereo_bench.detect.dataset import CameraDetections, detect_dataset
from stereo_bench.calibrate.diagnostics import heldout
from stereo_bench.evaluate.stage import calibrate_cameras
from stereo_bench.scene.image_folders import ImageFolders
from stereo_bench.core.patterns import Checkerboard
from stereo_bench.run.pipeline import rig_of
from stereo_bench.io.rundir import TrialPaths

REAL = Path(__file__).resolve().parents[2] / "shared" / "real" / "opencv_stereo"


def opencv_detections(source: ImageFolders) -> list[CameraDetections]:
    """OpenCV's own pipeline on every image, as the project's CameraDetections."""
    pattern = source.pattern
    n = len(pattern.object_points())
    out = []
    for c, cam in enumerate(source.cameras):
        points = np.full((source.frames, n, 2), np.nan)
        found = np.zeros(source.frames, bool)
        errors = {}
        for f in range(source.frames):
            gray = source.image(c, f)
            ok, corners = cv2.findChessboardCorners(
                gray, pattern.pattern_size,
                flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
            if not ok:
                errors[f] = "not found"
                continue
            corners = cv2.cornerSubPix(gray, corners, (11, 11), (-1, -1),
                                       (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30,
                                        0.01))
            points[f], found[f] = corners.reshape(-1, 2), True
        out.append(CameraDetections(cam.name, pattern.kind, "opencv", points, found,
                                    pattern.ids(), errors))
    return out


def stereo_calibrate(source, dets, cams) -> tuple[float, float, float]:
    """cv2.stereoCalibrate with FIX_INTRINSIC on the frames both cameras found in full (it
    takes no missing point): (RMS px, |T|, rotation deg)."""
    both = dets[0].found & dets[1].found
    for d in dets:
        both &= np.isfinite(d.points).all(axis=(1, 2))
    obj = [source.object_points.astype(np.float32)] * int(both.sum())
    img = [[d.points[f].astype(np.float32) for f in np.flatnonzero(both)] for d in dets]
    rms, *_, R, T, _, _ = cv2.stereoCalibrate(
        obj, img[0], img[1], cams[0].K, cams[0].dist[:5], cams[1].K, cams[1].dist[:5],
        source.cameras[0].size, flags=cv2.CALIB_FIX_INTRINSIC)
    return rms, float(np.linalg.norm(T)), float(np.degrees(np.linalg.norm(cv2.Rodrigues(R)[0])))


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--methods", default="zhang,zhang-brown,bouguet,opencv,opencv-rational,tsai")
    p.add_argument("--square-mm", type=float, default=1.0,
                   help="the board's square (default 1: lengths in squares, as OpenCV's sample)")
    p.add_argument("--folds", type=int, default=5)
    args = p.parse_args(argv)
    methods = [m.strip() for m in args.methods.split(",")]
    check_methods(methods)
    source = ImageFolders.open({"left": str(REAL / "left*.jpg"), "right": str(REAL / "right*.jpg")},
                               Checkerboard(squares_x=10, squares_y=7, square_mm=args.square_mm))
    print(f"OpenCV {cv2.__version__}; {source.frames} frames of {REAL}")
    detectors = {"project": detect_dataset(source), "opencv": opencv_detections(source)}
    calibration = CalibrationConfig()
    rows, rigs = [], {}
    for name, dets in detectors.items():
        with tempfile.TemporaryDirectory() as tmp:
            trial = TrialPaths(Path(tmp))
            for d in dets:
                d.save(trial.detection(d.camera))
            entries, estimates, _ = calibrate_cameras(source, dets, methods, trial, calibration)
            for m in methods:
                for cam in source.cameras:
                    e = entries[m][cam.name]
                    if "error" in e:
                        rows.append((name, m, cam.name, e["error"]))
                        continue
                    h = heldout(m, estimates[m, cam.name].obs, k=args.folds)
                    rows.append((name, m, cam.name, e["rpe_rms_px"], h["heldout_rms_px"],
                                 estimates[m, cam.name].result.camera))
                try:
                    rig, _ = rig_of(source, trial, m, calibration)
                    rigs[name, m] = rig
                except ValueError as err:
                    rigs[name, m] = str(err)
            if "opencv" in methods:
                cams = [estimates["opencv", c.name].result.camera for c in source.cameras]
                rigs[name, "stereoCalibrate"] = stereo_calibrate(source, dets, cams)
    print("\nPer camera (RPE and k-fold held-out RMS, px; fx fy cx cy):")
    print(f"{'detector':9s} {'method':16s} {'camera':6s} {'RPE':>7s} {'held-out':>9s}   intrinsics")
    for row in rows:
        if len(row) == 4:
            print(f"{row[0]:9s} {row[1]:16s} {row[2]:6s} failed: {row[3]}")
            continue
        d, m, cam, rpe, ho, est = row
        print(f"{d:9s} {m:16s} {cam:6s} {rpe:7.4f} {ho:9.4f}   {est.fx:.2f} {est.fy:.2f} "
              f"{est.cx:.2f} {est.cy:.2f}")
    print(f"\nRig (right from left; |T| in mm for {args.square_mm:g} mm squares):")
    for (d, m), rig in rigs.items():
        if isinstance(rig, str):
            print(f"{d:9s} {m:16s} failed: {rig}")
        elif m == "stereoCalibrate":
            rms, base, rot = rig
            print(f"{d:9s} {'cv2.stereoCalibrate':16s} RMS {rms:.4f} px  |T| {base:.4f}  "
                  f"rotation {rot:.4f} deg (FIX_INTRINSIC, the opencv method's intrinsics)")
        else:
            right = rig.cameras[1]
            print(f"{d:9s} {m:16s} RMS {rig.rms_px:.4f} px  |T| "
                  f"{np.linalg.norm(right.center):.4f}  rotation "
                  f"{np.degrees(np.linalg.norm(right.rvec)):.4f} deg")


if __name__ == "__main__":
    main()
