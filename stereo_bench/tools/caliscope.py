"""caliscope's calibration, as its scripting guide runs it (caliscope 0.11, without its GUI):
the detections as its ``ImagePoints`` table (board points in metres, caliscope's unit; its
``keypoint_id`` the point's index on the board), ``run_intrinsic_calibration`` per camera (its
own choice of views, then cv2.calibrateCamera from its own start), then the capture volume:
``CaptureVolume.bootstrap`` (pairwise stereo and a chain of poses), ``optimize``, dropping the
worst 2.5 % of the observations (``filter_by_percentile_error``), ``optimize`` again. Its bundle
adjustment moves the board's points freely (it does not hold the board rigid). The answer is
``CaptureVolume.save``'s camera_array.toml, read back with io.caliscope.

Its heavy parts are not needed: its GUI and video stack (PySide6, PyAV) stay uninstalled, the
modules above import without them.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from ..io import caliscope as caliscope_file
from . import Session, ToolError, ToolResult

ABOUT = ("caliscope 0.11: its intrinsic calibration per camera, then CaptureVolume bootstrap, "
         "optimize, 2.5 % filter, optimize (its scripting guide)")


def missing() -> str | None:
    try:
        from caliscope.core.capture_volume import CaptureVolume  # noqa: F401
    except ImportError as e:
        return f"caliscope cannot be imported ({e}); `make venv` installs it"
    return None


def _points(session: Session):
    import pandas as pd

    from caliscope.core.point_data import ImagePoints

    frames = []
    metres = session.object_points / 1000.0
    for c in range(len(session.names)):
        for f in np.flatnonzero(session.found[c]):
            k = np.flatnonzero(np.isfinite(session.image_points[c, f]).all(-1))
            frames.append(pd.DataFrame({
                "sync_index": f, "cam_id": c, "object_id": 0, "keypoint_id": k,
                "img_loc_x": session.image_points[c, f, k, 0],
                "img_loc_y": session.image_points[c, f, k, 1],
                "obj_loc_x": metres[k, 0], "obj_loc_y": metres[k, 1], "obj_loc_z": metres[k, 2],
                "frame_time": f / 30.0}))
    if not frames:
        raise ToolError("caliscope: no camera found the board")
    return ImagePoints(pd.concat(frames, ignore_index=True))


def calibrate(session: Session, out_dir: Path, name: str = "caliscope") -> ToolResult:
    from caliscope.cameras.camera_array import CameraArray, CameraData
    from caliscope.core.calibrate_intrinsics import run_intrinsic_calibration
    from caliscope.core.capture_volume import CaptureVolume

    if len(session.names) < 2:
        raise ToolError("caliscope: its capture volume joins two or more cameras")
    points = _points(session)
    cameras = CameraArray(cameras={c: CameraData(cam_id=c, size=tuple(s))
                                   for c, s in enumerate(session.sizes)})
    logging.getLogger("caliscope").setLevel(logging.ERROR)  # its progress notes
    t0 = time.perf_counter()
    try:
        for c in range(len(session.names)):
            cameras.cameras[c] = run_intrinsic_calibration(cameras.cameras[c], points).camera
        volume = CaptureVolume.bootstrap(points, cameras).optimize(strict=False)
        volume = volume.filter_by_percentile_error(2.5).optimize(strict=False)
    except (ValueError, KeyError, IndexError, RuntimeError, np.linalg.LinAlgError) as e:
        raise ToolError(f"caliscope: {type(e).__name__}: {e}") from None
    elapsed = time.perf_counter() - t0
    out_dir = Path(out_dir)
    volume.save(out_dir)
    path = out_dir / caliscope_file.FILE
    cams = [c.with_params(name=n) for c, n in zip(caliscope_file.read(path), session.names)]
    report = volume.reprojection_report
    return ToolResult(cams, path, "caliscope", elapsed,
                      {"reported_rmse_px": float(report.overall_rmse)})
