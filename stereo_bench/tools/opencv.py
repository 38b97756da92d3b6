"""OpenCV's calibration as its users run it.

* ``opencv-stereo``: cv2.calibrateCameraExtended on each camera (its default model k1, k2, p1,
  p2, k3; the Extended form of calibrateCamera, for the standard deviations users read), then
  cv2.stereoCalibrate with CALIB_FIX_INTRINSIC on the frames both cameras saw in full: the
  recipe of OpenCV's stereo_calib sample and of most stereo tutorials. Pairs only.
* ``opencv-multiview``: cv2.calibrateMultiview (OpenCV >= 5) with the intrinsics left to it (it
  runs calibrateCamera per camera, then its joint adjustment; multiview/opencv_ref.py).

Both write OpenCV FileStorage YAML (io.opencv_yaml), read back for scoring. The uncertainty is
calibrateCameraExtended's ``stdDeviationsIntrinsics`` (fx, fy, cx, cy, k1, k2, p1, p2, k3):
OpenCV's sigma^2 (J^T J)^-1 with sigma^2 from its residuals."""

from __future__ import annotations

import time
from pathlib import Path

import cv2
import numpy as np

from ..core.camera import Camera
from ..multiview.opencv_ref import opencv_multiview
from ..core.poses import matrix_to_rodrigues
from . import Session, ToolError, ToolResult, observations, read_back

ABOUT = {"opencv-stereo": "cv2.calibrateCamera per camera, then cv2.stereoCalibrate "
                          "(CALIB_FIX_INTRINSIC)",
         "opencv-multiview": "cv2.calibrateMultiview, intrinsics by its own calibrateCamera"}
#: The names of calibrateCameraExtended's stdDeviationsIntrinsics, in its order (first nine).
STD_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")


def missing() -> str | None:
    return None if hasattr(cv2, "calibrateMultiview") else (
        f"OpenCV {cv2.__version__} has no calibrateMultiview (OpenCV >= 5)")


def _calibrate_camera(session: Session, c: int):
    obs = observations(session, c)
    obj = [o.astype(np.float32) for o in obs.object_points]
    img = [p.astype(np.float32).reshape(-1, 1, 2) for p in obs.image_points]
    rms, K, dist, _, _, std, _, _ = cv2.calibrateCameraExtended(obj, img, obs.image_size, None,
                                                                None)
    camera = Camera.from_K(session.names[c], *session.sizes[c], K, np.ravel(dist)[:5])
    return camera, float(rms), dict(zip(STD_NAMES, np.ravel(std)[:len(STD_NAMES)].tolist()))


def _stereo(session: Session, out_dir: Path) -> ToolResult:
    if len(session.names) != 2:
        raise ToolError(f"opencv-stereo: cv2.stereoCalibrate joins a pair; this rig has "
                        f"{len(session.names)} camera(s) (opencv-multiview calibrates a studio)")
    t0 = time.perf_counter()
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)  # the same numbers on every machine (TRAPS.md)
    try:
        fits = [_calibrate_camera(session, c) for c in range(2)]
        both = np.flatnonzero(session.full_views().all(axis=0))
        if len(both) == 0:
            raise ToolError("opencv-stereo: no frame in which both cameras saw the whole board "
                            "(cv2.stereoCalibrate needs the same points in both views)")
        obj = [session.object_points.astype(np.float32)] * len(both)
        img = [[session.image_points[c, f].astype(np.float32).reshape(-1, 1, 2) for f in both]
               for c in range(2)]
        (a, b) = (fits[0][0], fits[1][0])
        rms, *_, R, T, _, _ = cv2.stereoCalibrate(obj, img[0], img[1], a.K, a.dist, b.K, b.dist,
                                                   a.size, flags=cv2.CALIB_FIX_INTRINSIC)
    except cv2.error as e:
        raise ToolError(f"opencv-stereo: OpenCV refused the session: {e.err or e}") from None
    finally:
        cv2.setNumThreads(threads)
    elapsed = time.perf_counter() - t0
    cams = [a, b.with_params(rvec=matrix_to_rodrigues(R), tvec=np.ravel(T))]
    log = {"rms_px": float(rms), "camera_rms_px": {f[0].name: f[1] for f in fits},
           "stereo_frames": int(len(both)), "opencv_version": cv2.__version__}
    uncertainty = {cam.name: {"parameters": std} for (cam, _, std) in fits}
    return read_back(cams, out_dir, "opencv", elapsed, log, uncertainty)


def _multiview(session: Session, out_dir: Path) -> ToolResult:
    blank = [Camera.from_K(n, *s, np.eye(3), np.zeros(5)) for n, s in
             zip(session.names, session.sizes)]
    try:
        rig = opencv_multiview(blank, session.object_points, session.image_points,
                               session.found, fix_intrinsics=False)
    except (RuntimeError, ValueError) as e:
        raise ToolError(f"opencv-multiview: {e}") from None
    log = {"rms_px": rig.log["opencv_rms_px"], "views": rig.log["n_views"],
           "left_out": rig.log["left_out"], "opencv_version": cv2.__version__}
    return read_back(rig.cameras, out_dir, "opencv", rig.time_s, log)


def calibrate(session: Session, out_dir: Path, name: str) -> ToolResult:
    return _stereo(session, out_dir) if name == "opencv-stereo" else _multiview(session, out_dir)
