"""The project's studio rig calibration beside pycolmap's bundle adjuster and OpenCV's
calibrateMultiview.

One synthetic studio: 8 cameras (1920 x 1080, fx ~ 1370 px, i.e. ~70 deg across, each with its
own distortion; every other one with k3, so COLMAP's FULL_OPENCV, the rest OPENCV) on a 4 m
ring, 2 m up, looking at the centre of the volume; a board of 11 x 8 points at 60 mm moves
through the volume for ``--frames`` frames, facing a random horizontal direction and tilting; a
camera sees a frame when it faces the board's front (within 70 deg) and all points are in its
image. Exact projections plus Gaussian noise of ``--sigma`` px. Each camera's cam_from_board
comes from cv2.solvePnP, as a calibration would give it; ``stereo.calibrate_rig`` and
``colmap_ref.colmap_rig_bundle`` then start from the same initial rig (``stereo.rig_start``)
and fixed true intrinsics, and minimize the same cost. ``multiview_ref.opencv_multiview``
(OpenCV >= 5, else its column reads n/a) takes the same observations and fixed intrinsics, but
starts from its own initialization and minimizes its own robustly weighted cost (its notes).

Prints per camera the error of its centre (mm, in camera 0's frame) and of its rotation (deg)
against the truth for the three solvers side by side, how far colmap's and OpenCV's rigs are
from the project's, the RMS reprojection errors (through the project's camera model) and the
wall times (best of ``--repeat``; each includes its solver's initialization), with the versions
they ran on. One BLAS thread (set before numpy loads), one OpenCV thread, and one Ceres thread
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

from stereo_bench.camera import (Camera, look_at_rotation, matrix_to_rodrigues,  # noqa: E402
                                 rodrigues_to_matrix)
from stereo_bench.stereo import calibrate_rig, rig_errors, rig_start  # noqa: E402


def studio(C: int, rng) -> list[Camera]:
    cams = []
    for k in range(C):
        a = 2 * np.pi * k / C
        pos = np.array([4000 * np.cos(a), 4000 * np.sin(a), 2000.0 + 150 * (k % 2)])
        R = look_at_rotation(pos, np.array([0, 0, 1000.0]), np.array([0, 0, 1.0]))
        dist = [rng.uniform(-0.12, 0.02), rng.uniform(-0.02, 0.06), rng.normal(0, 5e-4),
                rng.normal(0, 5e-4), 0.01 * (k % 2), 0, 0, 0]
        cams.append(Camera(f"cam{k}", 1920, 1080, 1370 * rng.uniform(0.97, 1.03),
                           1370 * rng.uniform(0.97, 1.03), 959.5 + rng.normal(0, 8),
                           539.5 + rng.normal(0, 8), 0.0, dist, matrix_to_rodrigues(R),
                           -R @ pos))
    return cams


def board() -> np.ndarray:
    gx, gy = np.meshgrid(np.arange(11) * 60.0, np.arange(8) * 60.0)
    return np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], -1)


def observe(cams, obj, frames: int, sigma: float, rng) -> np.ndarray:
    """Image points (C, F, N, 2), NaN where a camera does not see the frame."""
    R_wb = []
    for yaw in rng.uniform(0, 2 * np.pi, frames):
        facing = look_at_rotation(np.zeros(3), [np.cos(yaw), np.sin(yaw), 0], [0, 0, 1.0]).T
        R_wb.append(facing @ rodrigues_to_matrix(rng.normal(0, 0.25, 3)))
    R_wb = np.stack(R_wb)
    centre = np.stack([rng.uniform(-800, 800, frames), rng.uniform(-800, 800, frames),
                       rng.uniform(600, 1800, frames)], -1)
    t_wb = centre - R_wb @ obj.mean(0)
    Xw = np.einsum("fij,nj->fni", R_wb, obj) + t_wb[:, None]
    img = np.full((len(cams), frames, len(obj), 2), np.nan)
    for c, cam in enumerate(cams):
        uv = cam.project(Xw)
        towards = cam.center - centre
        towards /= np.linalg.norm(towards, axis=-1, keepdims=True)
        front = np.einsum("fi,fi->f", R_wb[:, :, 2], towards) < -np.cos(np.radians(70))
        inside = np.all((uv >= 5) & (uv <= [cam.width - 6, cam.height - 6]), axis=(-1, -2))
        ok = front & inside
        img[c, ok] = uv[ok] + rng.normal(0, sigma, uv[ok].shape)
    return img


def board_poses(cams, obj, img):
    """Each camera's own cam_from_board by cv2.solvePnP (IPPE): (C, F, 3) x 2, found (C, F)."""
    found = np.all(np.isfinite(img), axis=(-1, -2))
    rv = np.full(img.shape[:2] + (3,), np.nan)
    tv = np.full(img.shape[:2] + (3,), np.nan)
    for c, cam in enumerate(cams):
        for f in np.flatnonzero(found[c]):
            ok, r, t = cv2.solvePnP(obj, img[c, f], cam.K, cam.dist, flags=cv2.SOLVEPNP_IPPE)
            if ok:
                rv[c, f], tv[c, f] = r.ravel(), t.ravel()
    return rv, tv, found & np.all(np.isfinite(tv), -1)


def centres_in_cam0(cameras) -> np.ndarray:
    """Camera centres (C, 3) mm in camera 0's frame."""
    R0, t0 = cameras[0].R, cameras[0].tvec
    return np.stack([R0 @ cam.center + t0 for cam in cameras])


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

        from stereo_bench.colmap_ref import colmap_rig_bundle
    except ImportError as e:
        raise SystemExit(f"{e} (pip install pycolmap)")
    from pycolmap._core import __ceres_version__ as ceres_version
    opencv_multiview, opencv_missing = None, f"OpenCV {cv2.__version__} has no calibrateMultiview"
    if hasattr(cv2, "calibrateMultiviewExtended"):  # OpenCV >= 5
        from stereo_bench.multiview_ref import opencv_multiview

    rng = np.random.default_rng(args.seed)
    truth = studio(args.cameras, rng)
    obj = board()
    img = observe(truth, obj, args.frames, args.sigma, rng)
    rv, tv, found = board_poses(truth, obj, img)
    intr = [cam.with_params(rvec=np.zeros(3), tvec=np.zeros(3)) for cam in truth]
    per_frame = found.sum(0)

    print(f"pycolmap {pycolmap.__version__} ({pycolmap.COLMAP_build}; Ceres {ceres_version}), "
          f"numpy {np.__version__}, scipy {scipy.__version__}, OpenCV {cv2.__version__} "
          f"({'calibrateMultiview' if opencv_multiview else 'no calibrateMultiview'}); "
          f"BLAS threads {os.environ['OPENBLAS_NUM_THREADS']}, OpenCV threads 1, Ceres threads "
          f"{args.threads}")
    print(f"{args.cameras} cameras 1920x1080 on a 4 m ring, board {len(obj)} points, "
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

    c_true = centres_in_cam0(truth)
    c_ours = centres_in_cam0(ours.cameras)
    results = {"project": ours, "colmap": ref, "opencv": mv}
    centre = {k: None if r is None else np.linalg.norm(centres_in_cam0(r.cameras) - c_true, axis=-1)
              for k, r in results.items()}
    rot = {k: None if r is None else rig_errors(r.cameras, truth)["rotation_deg"]
           for k, r in results.items()}
    d_centre = {k: None if results[k] is None else
                np.linalg.norm(centres_in_cam0(results[k].cameras) - c_ours, axis=-1)
                for k in ("colmap", "opencv")}
    d_rot = {k: None if results[k] is None else
             rig_errors(results[k].cameras, ours.cameras)["rotation_deg"]
             for k in ("colmap", "opencv")}

    def cell(d, k, c, spec):
        return na(None if d[k] is None else d[k][c], spec)

    names = ("project", "colmap", "opencv")
    print()
    print(f"{'':<21}{'centre error mm':>33}{'rotation error deg':>33}"
          f"{'colmap - project':>24}{'opencv - project':>24}")
    print(f"{'camera':<8}{'model':<13}" + "".join(f"{n:>11}" for n in names) * 2
          + f"{'centre mm':>12}{'rot. deg':>12}" * 2)
    for c, cam in enumerate(truth):
        print(f"{cam.name:<8}{ref.log['camera_models'][c]:<13}"
              + "".join(f"{cell(centre, n, c, '.4f'):>11}" for n in names)
              + "".join(f"{cell(rot, n, c, '.5f'):>11}" for n in names)
              + "".join(f"{cell(d_centre, k, c, '.2e'):>12}{cell(d_rot, k, c, '.2e'):>12}"
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
             na(mv and mv.log["opencv_time_s"], ".3f"))]
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
