"""pycolmap's bundle adjuster as a COLMAP user calibrates a rig from a board: each camera's
OpenCV model as COLMAP has it (``OPENCV``: fx, fy, cx, cy, k1, k2, p1, p2) started by
cv2.calibrateCamera with k3 fixed at 0, the rig started from the cameras' board poses
(bundle.rig_start), then COLMAP's own adjustment of the rig, the board poses and every camera's
OPENCV intrinsics together, the board's points held as known 3D points
(multiview/colmap_ref.py, which says why this embedding is COLMAP's exact problem). The answer
is written as a COLMAP text model and read back."""

from __future__ import annotations

import time
from pathlib import Path

import cv2

from ..calibrate.opencv_ref import OpenCVCalibrator
from ..multiview.bundle import rig_start
from ..multiview.colmap_ref import colmap_rig_bundle
from . import Session, ToolError, ToolResult, board_poses, observations, read_back

ABOUT = "COLMAP's OPENCV cameras and rig refined together by pycolmap's bundle adjuster"


def missing() -> str | None:
    try:
        import pycolmap  # noqa: F401
    except ImportError:
        return "pycolmap is not installed (pip install pycolmap==4.2.1)"
    return None


def calibrate(session: Session, out_dir: Path, name: str = "pycolmap") -> ToolResult:
    if len(session.names) < 2:
        raise ToolError("pycolmap: its rig adjustment joins two or more cameras")
    t0 = time.perf_counter()
    calibrator = OpenCVCalibrator(flags=cv2.CALIB_FIX_K3)
    fits = [(calibrator.calibrate(obs), obs) for obs in
            (observations(session, c) for c in range(len(session.names)))]
    cams = [r.camera.with_params(name=n) for (r, _), n in zip(fits, session.names)]
    rv, tv = board_poses(fits, session.image_points.shape[1])
    start = rig_start(cams, session.image_points, rv, tv, session.found)
    try:
        rig = colmap_rig_bundle(cams, session.object_points, session.image_points, start.R,
                                start.t, start.board_rvecs, start.board_tvecs, start.seen,
                                refine_intrinsics=True)
    except (RuntimeError, ValueError) as e:
        raise ToolError(f"pycolmap: {e}") from None
    log = {"rms_px": rig.rms_px, "iterations": rig.iterations,
           "camera_models": rig.log["camera_models"]}
    return read_back(rig.cameras, out_dir, "colmap", time.perf_counter() - t0, log)
