"""The suite's own calibration, as a reference row beside the other tools: Zhang's method per
camera (k1, k2, p1, p2, k3 as OpenCV's default model, and skew), then the suite's rig bundle
adjustment (multiview.bundle.calibrate_rig, intrinsics kept). Its uncertainty: the Gauss-Newton
parameter covariance of each camera's fit and mrcal's mean-frames projection covariance
(calibrate/uncertainty.py), over the same pixels as every tool's."""

from __future__ import annotations

import time
from pathlib import Path

from ..calibrate import get_calibrator
from ..calibrate.base import fitted_shape
from ..calibrate.uncertainty import median_board_distance, parameter_covariance, \
    projection_covariance
from ..io import opencv_yaml
from ..multiview.bundle import calibrate_rig
from . import Session, ToolResult, board_poses, observations, probe_pixels, read_back

ABOUT = {"synthcal": "the suite's Zhang (k1, k2, p1, p2, k3, skew) per camera, then its rig "
                     "bundle adjustment (a reference)",
         "synthcal-warp": "the same with the board's warp and aspect error fitted per camera, "
                          "then refined with the rig (calibration.fit_board_warp)"}
METHOD = "zhang-brown"


def missing() -> str | None:
    return None


def calibrate(session: Session, out_dir: Path, name: str = "synthcal") -> ToolResult:
    t0 = time.perf_counter()
    warp = name == "synthcal-warp"
    calibrator = get_calibrator(METHOD, **({"board_warp": True} if warp else {}))
    fits = []
    for c in range(len(session.names)):
        obs = observations(session, c)
        fits.append((calibrator.calibrate(obs), obs))
    cams = [r.camera.with_params(name=n) for (r, _), n in zip(fits, session.names)]
    F = session.image_points.shape[1]
    log = {"rms_px": fits[0][0].log.get("rms_px")}
    shape = fitted_shape(session.object_points, [r.log for r, _ in fits]) if warp else None
    if len(cams) > 1:
        rv, tv = board_poses(fits, F)
        rig = calibrate_rig(cams, session.object_points, session.image_points, rv, tv,
                            session.found, board=shape)
        cams, log = rig.cameras, {"rms_px": rig.rms_px,
                                  **({"board_shape": rig.log["board_shape"]} if warp else {})}
    elapsed = time.perf_counter() - t0
    # The covariance is of the flat board's problem: not stated for the warped one.
    uncertainty = {} if warp else {cam.name: _uncertainty(cam, result, obs)
                                   for (result, obs), cam in zip(fits, cams)}
    if len(cams) == 1:
        return read_back(cams, out_dir, "opencv", elapsed, log, uncertainty)
    # OpenCV's multi-camera YAML: the only OpenCV layout of a pair that keeps Zhang's skew.
    return read_back(cams, out_dir, "opencv", elapsed, log, uncertainty,
                     write=lambda cams, out: opencv_yaml.write_multicam(
                         cams, out / opencv_yaml.MULTICAM_FILE))


def _uncertainty(cam, result, obs) -> dict:
    params = get_calibrator(METHOD).model_parameters
    cov = parameter_covariance(result.camera, obs, result.rvecs, result.tvecs, params)
    uv = probe_pixels(cam.width, cam.height)
    d = median_board_distance(obs, result.rvecs, result.tvecs)
    return {"parameters": {k: v for k, v in cov["std"].items() if v is not None},
            "projection": {
                "pixels": uv, "distance_mm": d,
                "covariance": projection_covariance(result.camera, obs, result.rvecs,
                                                    result.tvecs, params, uv, d),
                "board_poses": {int(f): (r, t) for f, r, t in
                                zip(obs.view_ids, result.rvecs, result.tvecs)}}}
