"""Run inside mrcal's own environment (it never imports stereo_bench): read the models
mrcal-calibrate-cameras wrote and report, per camera, mrcal's projection covariance at given
pixels and distance, and the board poses of its solve, as JSON on stdout.

    python mrcal_worker.py REQUEST.json

REQUEST {"mode": "uncertainty", "models": [paths, camera order], "pixels": [[[u, v], ...] per
camera], "distance": [mm per camera]}. Reply: {"cameras": [{"covariance": (P, 2, 2) px^2 or
null, "error": why not, "board_poses": {frame index of the solve: [r(3), t(3)]
cam_from_board}}]}. The covariance is mrcal.projection_uncertainty(what="covariance") of the
points at that distance along the model's rays (its default mean-frames method, the noise taken
from the solve's residuals).

REQUEST {"mode": "lens", "models": [...], "true_rays": [(G, 3) unit rays per camera, of grid
pixels], "grid": [(G, 2) px], "pixels": [(M, 2) px per camera], "pixel_rays": [(M, 3) their true
unit rays]}, for a lens the suite's camera model cannot hold (a splined one). Reply per camera:
"R" (3 x 3) the rotation that best maps the model's rays of the pixels (where boards were seen)
onto the true ones (its frame is a gauge: v_true ~ R v), "direct" and "compensated" (G,) px, how
far the model projects each true ray of the grid from its pixel as is and rotated back by R,
and "rays" (M, 3), the model's unit rays of the pixels."""

import json
import sys

import mrcal
import numpy as np


def _poses(model, icam: int) -> dict:
    """cam_from_board of every frame of the solve, for camera ``icam`` (camera 0 the reference
    of mrcal-calibrate-cameras' solve)."""
    inputs = model.optimization_inputs()
    frames = inputs.get("rt_ref_frame", inputs.get("frames_rt_toref"))
    extrinsics = inputs.get("rt_cam_ref", inputs.get("extrinsics_rt_fromref"))
    rt_cam_ref = np.zeros(6) if icam == 0 else np.asarray(extrinsics)[icam - 1]
    out = {}
    for f, rt_ref_frame in enumerate(np.asarray(frames)):
        rt = mrcal.compose_rt(rt_cam_ref, rt_ref_frame)
        out[str(f)] = rt.tolist()
    return out


def _lens(request: dict) -> dict:
    reply = []
    for path, true_rays, grid, pixels, pixel_rays in zip(
            request["models"], request["true_rays"], request["grid"], request["pixels"],
            request["pixel_rays"]):
        lens = mrcal.cameramodel(path).intrinsics()
        v_true = np.asarray(true_rays, dtype=float)
        q = np.asarray(grid, dtype=float)
        px = np.asarray(pixels, dtype=float).reshape(-1, 2)
        rays = mrcal.unproject(px, *lens, normalize=True)
        R = mrcal.align_procrustes_vectors_R01(np.asarray(pixel_rays, dtype=float), rays)
        direct = np.linalg.norm(mrcal.project(v_true, *lens) - q, axis=-1)
        compensated = np.linalg.norm(mrcal.project(v_true @ R, *lens) - q, axis=-1)
        reply.append({"R": R.tolist(), "direct": direct.tolist(),
                      "compensated": compensated.tolist(), "rays": rays.tolist()})
    return {"cameras": reply}


def main() -> None:
    request = json.load(open(sys.argv[1]))
    if request.get("mode") == "lens":
        json.dump(_lens(request), sys.stdout)
        return
    reply = []
    for icam, (path, pixels, distance) in enumerate(zip(request["models"], request["pixels"],
                                                        request["distance"])):
        model = mrcal.cameramodel(path)
        entry = {"board_poses": _poses(model, icam)}
        q = np.asarray(pixels, dtype=float)
        v = mrcal.unproject(q, *model.intrinsics(), normalize=True)
        try:
            cov = mrcal.projection_uncertainty(distance * v, model, what="covariance")
            entry["covariance"] = np.asarray(cov).tolist()
        except Exception as e:  # mrcal raises plain Exceptions (a singular solve)
            entry["covariance"] = None
            entry["error"] = str(e).strip().splitlines()[-1] if str(e).strip() else repr(e)
        reply.append(entry)
    json.dump({"cameras": reply}, sys.stdout)


if __name__ == "__main__":
    main()
