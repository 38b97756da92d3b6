"""OpenCV's cv2.calibrateCamera as a reference and baseline (not one of the paper's algorithms).

"opencv": 5 coefficients (k1, k2, p1, p2, k3), default flags. "opencv-MODEL" frees exactly the
lens model's coefficients (lens_models.py) through calibrateCamera's flags: "opencv-radial2" is
CALIB_FIX_K3 | CALIB_ZERO_TANGENT_DIST, "opencv-rational" CALIB_RATIONAL_MODEL (8 coefficients,
whose k1..k6 planar targets cannot identify, TRAPS.md: compare it in projection space, not
coefficient by coefficient). Inputs go in as float32, which alone rounds image points by up to
~7e-5 px on a 4096 px camera and bounds agreement with exact methods.
"opencv-fisheye" is cv2.fisheye.calibrate (Kannala-Brandt k1..k4, skew fixed, extrinsics
recomputed), "opencv-omnidir" cv2.omnidir.calibrate (Mei's xi, k1, k2, p1, p2 and skew), both on
float64 points.
(calibrateCameraExtended would add OpenCV's parameter standard deviations, but took 0.6 s
instead of 0.13 s on 127 views: the reference times the call users make.)
"""

from __future__ import annotations

import time

import cv2
import numpy as np

from ..core.camera import Camera
from .base import CalibrationResult, Observations
from .lens_models import PINHOLE_MODELS, core_lens, free_coefficients, method_name
from .pose import planar_pose
from .refine import CameraModel, free_mask, intrinsic_information, rank_info


def calibrate_camera_flags(free_dist) -> int:
    """calibrateCamera flags that free exactly the coefficients ``free_dist`` (the others stay 0:
    without an initial guess OpenCV starts every coefficient at 0, and a fixed one stays there)."""
    free = set(free_dist)
    rational = bool(free & {"k4", "k5", "k6"})
    flags = cv2.CALIB_RATIONAL_MODEL if rational else 0
    if not free & {"p1", "p2"}:
        flags |= cv2.CALIB_ZERO_TANGENT_DIST
    elif not {"p1", "p2"} <= free:
        raise ValueError(f"opencv: p1 and p2 are freed or fixed together, got {sorted(free)}")
    # Without CALIB_RATIONAL_MODEL, k4..k6 are not part of the model and need no flag.
    for i in range(1, 7 if rational else 4):
        if f"k{i}" not in free:
            flags |= getattr(cv2, f"CALIB_FIX_K{i}")
    return flags


# OpenCV's own calibrations of the wide-angle models: cv2.fisheye with its skew fixed (as its
# users run it); cv2.omnidir with its defaults (skew free, every view its initialization passes).
_FISHEYE_FLAGS = cv2.fisheye.CALIB_RECOMPUTE_EXTRINSIC | cv2.fisheye.CALIB_FIX_SKEW
_CRITERIA = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)


class OpenCVCalibrator:
    lens_models = PINHOLE_MODELS + ("fisheye", "omnidir")
    own_model = "OpenCV's default model (k1, k2, p1, p2, k3)"

    def __init__(self, flags: int = 0, lens_model: str | None = None):
        """``lens_model``: None is OpenCV's default 5 coefficients (as "brown"). ``flags`` are
        OR-ed into calibrateCamera's (e.g. CALIB_FIX_K3); model_parameters stays the model's."""
        self.name = method_name("opencv", lens_model)
        self.lens = core_lens(lens_model)
        dist = free_coefficients("brown" if lens_model is None else lens_model)
        # cv2.calibrateCamera and cv2.fisheye (as run here) never estimate skew; cv2.omnidir does.
        self.model_parameters = ("fx", "fy", "cx", "cy", *dist) + (
            ("skew",) if self.lens == "mei" else ())
        self.flags = int(flags) | (calibrate_camera_flags(dist) if self.lens == "opencv" else
                                   _FISHEYE_FLAGS if self.lens == "kannala_brandt" else 0)

    def _wide(self, obs: Observations):
        """(camera, rvecs, tvecs, rms, notes) from cv2.fisheye.calibrate or cv2.omnidir.calibrate
        on float64 points (both take them)."""
        obj = [o.reshape(1, -1, 3) for o in obs.object_points]
        img = [p.reshape(1, -1, 2) for p in obs.image_points]
        if self.lens == "kannala_brandt":
            rms, K, D, rvecs, tvecs = cv2.fisheye.calibrate(obj, img, obs.image_size, None, None,
                                                            flags=self.flags, criteria=_CRITERIA)
            camera = Camera.from_K(obs.camera_name, *obs.image_size, K, np.ravel(D),
                                   model=self.lens)
            return camera, rvecs, tvecs, rms, "cv2.fisheye.calibrate"
        rms, K, xi, D, rvecs, tvecs, idx = cv2.omnidir.calibrate(
            obj, img, obs.image_size, None, None, None, self.flags, _CRITERIA)
        camera = Camera.from_K(obs.camera_name, *obs.image_size, K,
                               np.concatenate([np.ravel(xi), np.ravel(D)]), model=self.lens)
        used = np.ravel(idx).astype(int) if idx is not None else np.zeros(0, int)
        # omnidir leaves out the views its initialization rejects: their poses with its camera.
        poses = {int(i): (np.ravel(r), np.ravel(t)) for i, r, t in zip(used, rvecs, tvecs)}
        rv, tv = zip(*[poses.get(i) or planar_pose(camera, o, p)
                       for i, (o, p) in enumerate(zip(obs.object_points, obs.image_points))])
        left_out = [obs.view_ids[i] for i in range(obs.n_views) if i not in poses]
        note = "cv2.omnidir.calibrate" + (f"; views left out by its initialization: {left_out}"
                                          if left_out else "")
        return camera, rv, tv, rms, note

    def calibrate(self, obs: Observations) -> CalibrationResult:
        t0 = time.perf_counter()
        obj = [o.astype(np.float32) for o in obs.object_points]
        img = [p.astype(np.float32).reshape(-1, 1, 2) for p in obs.image_points]
        notes = "cv2.calibrateCamera on float32 points"
        # One thread: OpenCV's parallel reductions change the result in the 7th digit with the
        # thread count (TRAPS.md), and the same config and seed must give the same numbers.
        threads = cv2.getNumThreads()
        cv2.setNumThreads(1)
        try:
            if self.lens != "opencv":
                try:
                    camera, rvecs, tvecs, rms, notes = self._wide(obs)
                except cv2.error as e:  # its own initialization fails on some wide views
                    raise ValueError(f"{self.name}: OpenCV refused the views of "
                                     f"{obs.camera_name!r}: {e.err or e}") from None
                except ValueError as e:  # it diverged to a camera that cannot exist
                    raise ValueError(f"{self.name}: OpenCV's calibration of "
                                     f"{obs.camera_name!r} diverged: {e}") from None
            else:
                rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(obj, img, obs.image_size, None,
                                                                 None, flags=self.flags)
                camera = Camera.from_K(obs.camera_name, *obs.image_size, K, np.ravel(dist)[:8])
        finally:
            cv2.setNumThreads(threads)
        rvecs = np.array(rvecs, dtype=np.float64).reshape(-1, 3)
        tvecs = np.array(tvecs, dtype=np.float64).reshape(-1, 3)
        elapsed = time.perf_counter() - t0
        # OpenCV does not say when its problem is rank deficient (the rational model from planar
        # views, TRAPS.md): check the information of its free intrinsics at its solution.
        model = CameraModel(self.lens)
        free = free_mask(model.param_names, self.model_parameters)
        info = intrinsic_information(model, model.params_of(camera), free, obs.object_points,
                                     rvecs, tvecs)
        log = {"method": self.name, "opencv_version": cv2.__version__, "flags": self.flags,
               "rms_px": float(rms), "time_s": elapsed,
               "rank": rank_info(info, list(self.model_parameters)),
               "notes": notes}
        return CalibrationResult(camera, rvecs, tvecs, log)
