"""Time every calibration method, and cv2.calibrateCamera itself, on the same 127 views.

The views are the paper's: its rectilinear camera (configs/paper/rectilinear_mono.yaml), the
8 x 11 inner corners of the 9 x 12 checkerboard on the conical-spring trajectory, exact projections
plus Gaussian noise of 0.3 px. Prints wall-clock times (best of ``--repeat``) next to the OpenCV
version they ran on (TRAPS.md: OpenCV's speed depends on its build), and the accuracy reached.

    python benchmarks/calibration_speed.py [--repeat 3] [--sigma 0.3] [--seed 0]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import numpy as np

from stereo_bench.calibrate import Observations, available_methods, get_calibrator
from stereo_bench.config import load_rig
from stereo_bench.metrics import projection_difference
from stereo_bench.rig import Rig

CONFIG = Path(__file__).resolve().parent.parent / "configs" / "paper" / "rectilinear_mono.yaml"


def paper_observations(sigma: float, seed: int):
    rig = Rig.from_config(load_rig(CONFIG))
    camera = rig.cameras[0]
    gt = rig.ground_truth()
    seen = gt.visible[0].all(axis=1)  # whole boards only, as a checkerboard detector returns them
    rng = np.random.default_rng(seed)
    image = [p + rng.normal(0.0, sigma, p.shape) for p in gt.points[0][seen]]
    board = rig.pattern.object_points()
    obs = Observations([board] * len(image), image, camera.size,
                       np.flatnonzero(seen).tolist(), camera.name)
    return obs, camera.with_params(rvec=np.zeros(3), tvec=np.zeros(3))


def best_time(fn, repeat: int):
    times, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return min(times), out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--sigma", type=float, default=0.3)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    obs, truth = paper_observations(args.sigma, args.seed)
    print(f"OpenCV {cv2.__version__}, numpy {np.__version__}; {obs.n_views} views x "
          f"{obs.n_points // obs.n_views} corners of camera {truth.name!r} "
          f"({truth.width}x{truth.height}), noise {args.sigma} px")
    print(f"{'method':<28}{'time s':>9}{'RPE_RMS px':>12}{'proj. diff mean px':>20}"
          f"{'rot.-compensated':>18}")

    obj = [o.astype(np.float32) for o in obs.object_points]
    img = [p.astype(np.float32) for p in obs.image_points]
    t, (rms, *_) = best_time(lambda: cv2.calibrateCamera(obj, img, obs.image_size, None, None),
                             args.repeat)
    print(f"{'cv2.calibrateCamera (raw)':<28}{t:>9.3f}{rms:>12.4f}{'':>20}")

    for name in available_methods():
        try:
            calibrator = get_calibrator(name)
            t, result = best_time(lambda: calibrator.calibrate(obs), args.repeat)
        except Exception as e:  # a method failing to import or run is reported, not fatal
            print(f"{name:<28}  failed: {type(e).__name__}: {e}")
            continue
        diff = projection_difference(result.camera, truth)
        print(f"{name:<28}{t:>9.3f}{result.log['rms_px']:>12.4f}{diff['mean_px']:>20.4f}"
              f"{diff['rotation_compensated_mean_px']:>18.4f}")


if __name__ == "__main__":
    main()
