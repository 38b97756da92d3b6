"""The project's studio rig calibration beside pycolmap's bundle adjuster and OpenCV's
calibrateMultiview.

One synthetic studio, built by the package (config.parse_rig, rig.Rig and its ground truth): 8
cameras (1920 x 1080, fx ~ 1370 px, i.e. ~70 deg across, each with its own distortion; every
other one with k3, so COLMAP's FULL_OPENCV, the rest OPENCV) on a 4 m ring at heights 2.0 / 2.15
m, looking at the centre of the volume; a checkerboard of 11 x 8 inner corners at 60 mm carried
through the volume for ``--frames`` frames of a calibration session (trajectory.kind: session:
the board walks, tilts and turns so that its front faces each camera in turn); a camera sees a
frame when every point is visible in the ground truth (front towards it, inside its image).
Exact projections plus Gaussian noise of ``--sigma`` px. Each camera's cam_from_board comes from
its own view (pose.planar_pose), as a calibration starts it; ``bundle.calibrate_rig`` and
``colmap_ref.colmap_rig_bundle`` then start from the same initial rig (``bundle.rig_start``)
and fixed true intrinsics, and minimize the same cost. ``opencv_ref.opencv_multiview``
(OpenCV >= 5, else its column reads n/a) takes the same observations and fixed intrinsics, but
starts from its own initialization and minimizes its own robustly weighted cost (its notes).

Prints per camera the error of its centre (mm, in camera 0's frame) and of its rotation (deg)
against the truth for the three solvers side by side, how far colmap's and OpenCV's rigs are
from the project's, the RMS reprojection errors (through the project's camera model) and the
wall times (best of ``--repeat``; each includes its solver's initialization), with the versions
they ran on, and the project's wall time over each peer's (measured in the same run, one after
the other). One BLAS thread (set before numpy loads), one OpenCV thread, and one Ceres thread
unless ``--threads`` gives Ceres more; figures, not a pass/fail test.

    python benchmarks/studio_bundle.py [--frames 200] [--sigma 0.3] [--seed 0] [--repeat 1]
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import time  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import scipy  # noqa: E402

from stereo_bench.config.schema import parse_rig  # noqa: E402
from stereo_bench.scene.rig import Rig  # noqa: E402
from stereo_bench.multiview.bundle import calibrate_rig, rig_errors, rig_start  # noqa: E402
from stereo_bench.calibrate.pose import planar_pose  # noqa: E402


def studio(C: int, frames: int, seed: int, rng) -> Rig:
    """The studio of the module notes; each camera's lens drawn from ``rng``, the session's
    path from ``seed``."""
    lenses = [{"width": 1920, "height": 1080, "fx": 1370 * rng.uniform(0.97, 1.03),
               "fy": 1370 * rng.uniform(0.97, 1.03), "cx": 959.5 + rng.normal(0, 8),
               "cy": 539.5 + rng.normal(0, 8),
               "dist": [rng.uniform(-0.12, 0.02), rng.uniform(-0.02, 0.06), rng.normal(0, 5e-4),
                        rng.normal(0, 5e-4), 0.01 * (k % 2)]} for k in range(C)]
    return Rig.from_config(parse_rig({
        "name": "studio_bundle", "seed": seed,
        "studio": {"layout": "ring", "count": C, "radius_mm": 4000.0,
                   "height_mm": [2000.0, 2150.0], "lenses": lenses},
        "pattern": {"kind": "checkerboard", "squares_x": 12, "squares_y": 9, "square_mm": 60.0},
        "trajectory": {"kind": "session", "frames": frames}}))


def best_of(fn, repeat: int):
    best, out = np.inf, None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cameras", type=int, default=8)
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--sigma", type=float, default=0.3, help="pixel noise (px)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--threads", type=int, default=1, help="Ceres threads (-1: all cores)")
    args = ap.parse_args()

    try:
        import pycolmap

        from stereo_bench.multiview.colmap_ref import colmap_rig_bundle
    except ImportError as e:
        raise SystemExit(f"{e} (pip install pycolmap)")
    from pycolmap._core import __ceres_version__ as ceres_version
    opencv_multiview, opencv_missing = None, f"OpenCV {cv2.__version__} has no calibrateMultiview"
    if hasattr(cv2, "calibrateMultiviewExtended"):  # OpenCV >= 5
        from stereo_bench.multiview.opencv_ref import opencv_multiview

    rng = np.random.default_rng(args.seed)
    rig = studio(args.cameras, args.frames, args.seed, rng)
    truth, obj, gt = rig.cameras, rig.pattern.object_points(), rig.ground_truth()
    found = gt.visible.all(-1)  # (C, F): every point of the board in view
    img = np.where(found[..., None, None], gt.points, np.nan)
    img += rng.normal(0, args.sigma, img.shape)
    rv, tv = np.full(found.shape + (3,), np.nan), np.full(found.shape + (3,), np.nan)
    for c, f in zip(*np.nonzero(found)):
        rv[c, f], tv[c, f] = planar_pose(truth[c], obj, img[c, f])
    intr = [cam.with_params(rvec=np.zeros(3), tvec=np.zeros(3)) for cam in truth]
    per_frame = found.sum(0)

    print(f"pycolmap {pycolmap.__version__} ({pycolmap.COLMAP_build}; Ceres {ceres_version}), "
          f"numpy {np.__version__}, scipy {scipy.__version__}, OpenCV {cv2.__version__} "
          f"({'calibrateMultiview' if opencv_multiview else 'no calibrateMultiview'}); "
          f"BLAS threads {os.environ['OPENBLAS_NUM_THREADS']}, OpenCV threads 1, Ceres threads "
          f"{args.threads}")
    print(f"{args.cameras} cameras 1920x1080 on a 4 m ring, board {len(obj)} points, a session of "
          f"{args.frames} frames, noise {args.sigma} px; frames per camera "
          f"{found.sum(1).tolist()}; frames seen by 2+ cameras {(per_frame >= 2).sum()}, "
          f"by 1 {(per_frame == 1).sum()}, by none {(per_frame == 0).sum()}")

    t_ours, ours = best_of(lambda: calibrate_rig(intr, obj, img, rv, tv, found), args.repeat)

    def colmap():
        s = rig_start(intr, img, rv, tv, found)
        return colmap_rig_bundle(intr, obj, img, s.R, s.t, s.board_rvecs, s.board_tvecs, s.seen,
                                 num_threads=args.threads)

    t_colmap, ref = best_of(colmap, args.repeat)
    if opencv_multiview is not None:
        t_cv, mv = best_of(lambda: opencv_multiview(intr, obj, img, found), args.repeat)
    else:
        t_cv, mv = None, None

    def na(value, spec: str) -> str:
        return "n/a" if value is None else format(value, spec)

    results = {"project": ours, "colmap": ref, "opencv": mv}
    # rig_errors' centre_mm: between two rigs' centres of a camera, each in its camera 0's frame
    truth_err = {k: None if r is None else rig_errors(r.cameras, truth)
                 for k, r in results.items()}
    from_ours = {k: None if results[k] is None else rig_errors(results[k].cameras, ours.cameras)
                 for k in ("colmap", "opencv")}

    def cell(errors, k, key, c, spec):
        return na(None if errors[k] is None else errors[k][key][c], spec)

    names = ("project", "colmap", "opencv")
    print()
    print(f"{'':<21}{'centre error mm':>33}{'rotation error deg':>33}"
          f"{'colmap - project':>24}{'opencv - project':>24}")
    print(f"{'camera':<8}{'model':<13}" + "".join(f"{n:>11}" for n in names) * 2
          + f"{'centre mm':>12}{'rot. deg':>12}" * 2)
    for c, cam in enumerate(truth):
        print(f"{cam.name:<8}{ref.log['camera_models'][c]:<13}"
              + "".join(f"{cell(truth_err, n, 'centre_mm', c, '.4f'):>11}" for n in names)
              + "".join(f"{cell(truth_err, n, 'rotation_deg', c, '.5f'):>11}" for n in names)
              + "".join(f"{cell(from_ours, k, 'centre_mm', c, '.2e'):>12}"
                        f"{cell(from_ours, k, 'rotation_deg', c, '.2e'):>12}"
                        for k in ("colmap", "opencv")))
    print()
    print(f"{'':<34}{'project':>18}{'colmap':>18}{'opencv':>18}")
    rows = [("initial RMS px", f"{ours.log['initial_rms_px']:.6f}",
             f"{ref.log['initial_rms_px']:.6f}", "own start" if mv else "n/a"),
            ("final RMS px", f"{ours.rms_px:.12f}", f"{ref.rms_px:.12f}",
             na(mv and mv.rms_px, ".12f")),
            ("observations", ours.log["n_observations"], ref.log["n_observations"],
             na(mv and mv.log["n_observations"], "d")),
            ("Jacobian evaluations", ours.iterations, ref.iterations,
             "not reported" if mv else "n/a"),
            ("wall time s (best of {})".format(args.repeat), f"{t_ours:.3f}", f"{t_colmap:.3f}",
             na(t_cv, ".3f")),
            ("  of which the solver s", "", f"{ref.log['solve_time_s']:.3f}",
             na(mv and mv.log["opencv_time_s"], ".3f")),
            # the ratio the project is judged by: its wall time over each peer's, same run
            ("project's wall time / this one's", "1.00", f"{t_ours / t_colmap:.2f}",
             na(t_cv and t_ours / t_cv, ".2f"))]
    for name, a, b, c in rows:
        print(f"{name:<34}{a!s:>18}{b!s:>18}{c!s:>18}")
    print(f"RMS relative difference colmap/project - 1: {ref.rms_px / ours.rms_px - 1:.2e}"
          + ("" if mv is None else f", opencv/project - 1: {mv.rms_px / ours.rms_px - 1:.2e}"))
    print(f"project: {ours.log['message']}")
    print(f"colmap:  {ref.log['brief_report']} ({ref.log['message'].rstrip('.')}; linear solver "
          f"{ref.log['linear_solver']}, {ref.log['n_images']} images, "
          f"{ref.log['dropped_observations']} observations dropped)")
    if mv is None:
        print(f"opencv:  n/a ({opencv_missing})")
    else:
        pairs = ", ".join(f"{a}-{b}" for a, b in mv.log["initialization_pairs"])
        print(f"opencv:  its own RMS {mv.log['opencv_rms_px']:.12f} px (its float32 points); "
              f"{mv.log['n_views']} views; left out {mv.log['left_out']}; initialization "
              f"pairs {pairs}")


if __name__ == "__main__":
    main()
