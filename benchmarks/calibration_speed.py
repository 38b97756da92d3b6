"""Time every calibration method beside cv2.calibrateCamera, on the same 127 views, in one run.

The views are the paper's: its rectilinear camera (configs/paper/rectilinear_mono.yaml), the
8 x 11 inner corners of the 9 x 12 checkerboard on the conical-spring trajectory, exact projections
plus Gaussian noise of 0.3 px.

Each method's peer is cv2.calibrateCamera freeing the same distortion coefficients (the method's
lens model; k1 alone for Tsai's one-coefficient model; k1 k2 for Zhang's, which also fits a skew
OpenCV cannot), called as users call it: float32 points, default criteria, no initial guess.
The two are timed alternately, best of ``--repeat`` each, so that a load on the machine weighs
on both; the ratios are the method's time over its peer's, in wall-clock and in CPU time. One BLAS thread (set before numpy
loads) and one OpenCV thread for both, and the versions they ran on (TRAPS.md: OpenCV's speed
depends on its build). Then the accuracy reached: RPE_RMS and the projection difference against
the true camera (mean px, and after compensating a rotation). Figures, not a pass/fail test.

With ``--baseline REV`` each method of git revision REV (a worktree of REV served by a
subprocess, revision.py) calibrates the same views right after the working tree's, best of
``--repeat`` timed in its own process; the table adds its best time and how far the working
tree's camera is from REV's (the largest difference of fx, fy, cx, cy in px).

    python benchmarks/calibration_speed.py [--repeat 3] [--sigma 0.3] [--seed 0]
                                           [--methods zhang bouguet-brown ...] [--baseline REV]
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import time  # noqa: E402
from contextlib import nullcontext  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import scipy  # noqa: E402

from stereo_bench.calibrate import (Observations, available_methods, check_methods,  # noqa: E402
                                    get_calibrator, parse_method)
from stereo_bench.calibrate.lens_models import LENS_MODELS, free_coefficients  # noqa: E402
from stereo_bench.calibrate.opencv_ref import calibrate_camera_flags  # noqa: E402
from stereo_bench.config.schema import load_rig  # noqa: E402
from stereo_bench.evaluate.metrics import projection_difference  # noqa: E402
from stereo_bench.scene.rig import Rig  # noqa: E402
from revision import revision_server  # noqa: E402

CONFIG = Path(__file__).resolve().parent.parent / "configs" / "paper" / "rectilinear_mono.yaml"
# The distortion each base fits without a lens model, for its cv2.calibrateCamera peer.
OWN_DISTORTION = {"zhang": ("k1", "k2"), "bouguet": ("k1", "k2", "p1", "p2"), "tsai": ("k1",),
                  "opencv": free_coefficients("brown")}


# The subprocess that runs a revision's method (revision.serve): answers (method, object
# points, image points, image size, view ids, camera name, repeat) with the revision's camera
# matrix K and its best wall time of ``repeat``, or the error's text.
SERVER = """
import time
import cv2
from revision import serve
from stereo_bench.calibrate import Observations, get_calibrator
cv2.setNumThreads(1)


def answer(request):
    name, obj, img, size, views, camera, repeat = request
    try:
        calibrator, best = get_calibrator(name), float("inf")
        for _ in range(repeat):
            start = time.perf_counter()
            result = calibrator.calibrate(Observations(obj, img, size, views, camera))
            best = min(best, time.perf_counter() - start)
        return result.camera.K, best
    except Exception as e:
        return f"{type(e).__name__}: {e}"


serve(answer)
"""


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


def default_methods() -> list[str]:
    """The listed methods, then every BASE-MODEL variant of the project's own algorithms."""
    own = [b for b in ("zhang", "bouguet") if b in available_methods()]
    return available_methods() + [f"{b}-{m}" for b in own for m in LENS_MODELS]


def peer_distortion(name: str) -> tuple[str, ...]:
    base, model = parse_method(name)
    return OWN_DISTORTION[base] if model is None else free_coefficients(model)


def time_side_by_side(method, peer, repeat: int):
    """Best wall and best CPU (process) times of ``method`` and of ``peer``, (2,) each, run
    alternately; their last results. Both run on one thread, so on a machine shared with other
    work the CPU time is the steadier figure."""
    wall, cpu, out = np.full(2, np.inf), np.full(2, np.inf), [None, None]
    for _ in range(repeat):
        for i, fn in enumerate((method, peer)):
            t0, c0 = time.perf_counter(), time.process_time()
            out[i] = fn()
            wall[i] = min(wall[i], time.perf_counter() - t0)
            cpu[i] = min(cpu[i], time.process_time() - c0)
    return wall, cpu, out


def measure(methods: list[str], obs, truth, repeat: int, baseline) -> dict:
    """Print a row per method (beside its cv2.calibrateCamera peer, and ``baseline``'s run of
    it when given); returns the methods' (wall, CPU) time ratios over the peer's."""
    obj = [o.astype(np.float32) for o in obs.object_points]
    img = [p.astype(np.float32) for p in obs.image_points]
    ratios = {}
    for name in methods:
        dist = peer_distortion(name)
        flags = calibrate_camera_flags(dist)
        # calibrateCamera's outputs; the camera built as opencv_ref builds it, for the metric
        peer = lambda: cv2.calibrateCamera(obj, img, obs.image_size, None, None, flags=flags)
        try:
            calibrator = get_calibrator(name)
            (t, t_cv), cpu, (result, (rms_cv, K, d_cv, *_)) = time_side_by_side(
                lambda: calibrator.calibrate(obs), peer, repeat)
        except Exception as e:  # a method failing to import or run is reported, not fatal
            print(f"{name:<20}  failed: {type(e).__name__}: {e}")
            continue
        ratios[name] = t / t_cv, cpu[0] / cpu[1]
        ours = projection_difference(result.camera, truth)
        cam_cv = result.camera.from_K(truth.name, truth.width, truth.height, K,
                                      np.ravel(d_cv)[:8])
        theirs = projection_difference(cam_cv, truth)
        row = (f"{name:<20}{' '.join(dist):<26}{t:>8.3f}{t_cv:>8.3f}{t / t_cv:>7.2f}"
               f"{cpu[0] / cpu[1]:>10.2f}{result.log['rms_px']:>12.4f}{rms_cv:>9.4f}"
               f"{ours['mean_px']:>15.4f}{theirs['mean_px']:>8.4f}"
               f"{ours['rotation_compensated_mean_px']:>12.4f}"
               f"{theirs['rotation_compensated_mean_px']:>8.4f}")
        if baseline:
            reply = baseline((name, obs.object_points, obs.image_points, obs.image_size,
                              obs.view_ids, obs.camera_name, repeat))
            if isinstance(reply, str):
                row += f"  base failed: {reply}"
            else:
                K_base, t_base = reply
                dK = np.abs(result.camera.K - K_base)[[0, 1, 0, 1], [0, 1, 2, 2]].max()
                row += f"{t_base:>8.3f}{t / t_base:>8.2f}{dK:>12.1e}"
        print(row)
    return ratios


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--sigma", type=float, default=0.3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--methods", nargs="+", default=None,
                    help="method names (default: the listed methods and the BASE-MODEL "
                         "variants of zhang and bouguet)")
    ap.add_argument("--baseline", metavar="REV", help="also time git revision REV's methods "
                                                      "on the same views")
    args = ap.parse_args()
    methods = args.methods or default_methods()
    check_methods(methods)
    cv2.setNumThreads(1)  # TRAPS.md: the thread count changes OpenCV's results (and its time)

    obs, truth = paper_observations(args.sigma, args.seed)
    print(f"OpenCV {cv2.__version__}, numpy {np.__version__}, scipy {scipy.__version__}; BLAS "
          f"threads {os.environ['OPENBLAS_NUM_THREADS']}, OpenCV threads "
          f"{cv2.getNumThreads()}; {obs.n_views} views x {obs.n_points // obs.n_views} corners "
          f"of camera {truth.name!r} ({truth.width}x{truth.height}), noise {args.sigma} px; "
          f"best of {args.repeat}, method and peer run alternately")
    header = (f"{'method':<20}{'cv2 peer frees':<26}{'time s':>8}{'cv2 s':>8}{'ratio':>7}"
              f"{'CPU ratio':>10}{'RPE_RMS px':>12}{'cv2 RPE':>9}{'proj. diff px':>15}{'cv2':>8}"
              f"{'rot.-comp.':>12}{'cv2':>8}")
    if args.baseline:
        header += f"{'base s':>8}{'x base':>8}{'max |dK| px':>12}"
    print(header)
    with revision_server(args.baseline, SERVER) if args.baseline else nullcontext() as base:
        ratios = measure(methods, obs, truth, args.repeat, base)
    for i, kind in enumerate(("wall", "CPU")):
        if ratios:
            worst = max(ratios, key=lambda n: ratios[n][i])
            print(f"{kind} time over cv2.calibrateCamera's: median "
                  f"{np.median([r[i] for r in ratios.values()]):.2f}, largest "
                  f"{ratios[worst][i]:.2f} ({worst})")


if __name__ == "__main__":
    main()
