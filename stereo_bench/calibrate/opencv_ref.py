"""OpenCV's cv2.calibrateCamera as a reference and baseline (not one of the paper's algorithms).

"opencv": 5 coefficients (k1, k2, p1, p2, k3), default flags. "opencv-rational": 8 coefficients
(CALIB_RATIONAL_MODEL), whose k1..k6 planar targets cannot identify (TRAPS.md): compare it in
projection space, not coefficient by coefficient. Inputs go in as float32, which alone rounds
image points by up to ~7e-5 px on a 4096 px camera and bounds agreement with exact methods.
(calibrateCameraExtended would add OpenCV's parameter standard deviations, but took 0.6 s
instead of 0.13 s on 127 views: the reference times the call users make.)
"""

from __future__ import annotations

import time

import cv2
import numpy as np

from ..camera import Camera
from .base import CalibrationResult, Observations
from .refine import OpenCVModel, free_mask, intrinsic_information, rank_info

# The parameters cv2.calibrateCamera estimates (it never estimates skew in the pinhole model).
_FREE = {False: ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"),
         True: ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")}


class OpenCVCalibrator:
    def __init__(self, rational: bool = False, flags: int = 0):
        """``flags`` are OR-ed into calibrateCamera's (e.g. CALIB_FIX_K3)."""
        self.name = "opencv-rational" if rational else "opencv"
        self.rational = rational
        self.model_parameters = _FREE[rational]
        self.flags = int(flags) | (cv2.CALIB_RATIONAL_MODEL if rational else 0)

    def calibrate(self, obs: Observations) -> CalibrationResult:
        t0 = time.perf_counter()
        obj = [o.astype(np.float32) for o in obs.object_points]
        img = [p.astype(np.float32).reshape(-1, 1, 2) for p in obs.image_points]
        # One thread: OpenCV's parallel reductions change the result in the 7th digit with the
        # thread count (TRAPS.md), and the same config and seed must give the same numbers.
        threads = cv2.getNumThreads()
        cv2.setNumThreads(1)
        try:
            rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(obj, img, obs.image_size, None,
                                                             None, flags=self.flags)
        finally:
            cv2.setNumThreads(threads)
        camera = Camera.from_K(obs.camera_name, *obs.image_size, K, np.ravel(dist)[:8])
        rvecs = np.array(rvecs, dtype=np.float64).reshape(-1, 3)
        tvecs = np.array(tvecs, dtype=np.float64).reshape(-1, 3)
        elapsed = time.perf_counter() - t0
        # OpenCV does not say when its problem is rank deficient (the rational model from planar
        # views, TRAPS.md): check the information of its free intrinsics at its solution.
        model = OpenCVModel()
        free = free_mask(model.param_names, _FREE[self.rational])
        info = intrinsic_information(model, model.params_of(camera), free, obs.object_points,
                                     rvecs, tvecs)
        log = {"method": self.name, "opencv_version": cv2.__version__, "flags": self.flags,
               "rms_px": float(rms), "time_s": elapsed,
               "rank": rank_info(info, list(_FREE[self.rational])),
               "notes": "cv2.calibrateCamera on float32 points"}
        return CalibrationResult(camera, rvecs, tvecs, log)
