"""Run inside mrcal's own environment (it never imports stereo_bench): read the models
mrcal-calibrate-cameras wrote and report, per camera, mrcal's projection covariance at given
pixels and distance, and the board poses of its solve, as JSON on stdout.

    python mrcal_worker.py REQUEST.json

REQUEST: {"models": [paths, camera order], "pixels": [[[u, v], ...] per camera],
"distance": [mm per camera]}. Reply: {"cameras": [{"covariance": (P, 2, 2) px^2 or null,
"error": why not, "board_poses": {frame index of the solve: [r(3), t(3)] cam_from_board}}]}.
The covariance is mrcal.projection_uncertainty(what="covariance") of the points at that
distance along the model's rays (its default mean-frames method, the noise taken from the
solve's residuals)."""

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


def main() -> None:
    request = json.load(open(sys.argv[1]))
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
