"""Throughput of SynthCal's triangulation, beside aniposelib's and OpenCV's.

10,000 frames x 24 joints seen by 4 cameras (the paper's rectilinear and wide-angle cameras, two
of each, on a 3 m ring around a walking volume): exact projections plus Gaussian noise, pixels
outside an image missing (NaN). Runs on one core (the process is pinned to one CPU and BLAS to
one thread before numpy loads). Prints, per method, points/s, total time (best of ``--repeat``)
and the mean 3D error against the truth. The DLT is timed in both forms that triangulate.py
weighs: its closed 3x3 normal equations and a batched SVD of the (M, 2C, 4) system. Peers in the
same run: aniposelib's CameraGroup.triangulate (4 cameras; version 0.8 needs jax) and, for the
points two cameras share, cv2.undistortPoints + cv2.triangulatePoints beside our DLT of the same
pairs. Then the renderer's per-camera precomputation (PixelRays) of both paper cameras.
``--baseline REV`` times the package as committed at git revision REV (``git archive``, into a
temporary folder) beside the working tree in the same run, for before/after figures.

    python benchmarks/triangulation_speed.py [--frames 10000] [--sigma 1.0] [--repeat 2]
        [--baseline HEAD] [--no-pixel-rays]
"""

from __future__ import annotations

import os

os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
os.environ.setdefault("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false")

import argparse  # noqa: E402
import importlib  # noqa: E402
import importlib.util  # noqa: E402
import io  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tarfile  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from stereo_bench.core.camera import Camera  # noqa: E402
from stereo_bench.core.poses import look_at_rotation, matrix_to_rodrigues  # noqa: E402
from stereo_bench.render import PixelRays  # noqa: E402
from stereo_bench.multiview.triangulate import (  # noqa: E402
    refine_points, triangulate_dlt, triangulate_midpoint)

RECT = Camera("rect", 4096, 3072, 3000, 3000, 2048, 1536, 0, [0.05, 0.02, 0.001, 0, 0, 0, 0, 0])
WIDE = Camera("wide", 640, 480, 600, 450, 320, 240, 0, [0.5, 0.1, 0.03, 0, 0, 0, 0, 0])


def ring_rig() -> list[Camera]:
    """Four cameras 3 m from the origin at 90 degree steps, 0.9 m up, looking at (0, 0, 0.9 m)."""
    cams = []
    for k, base in enumerate([RECT, WIDE, RECT, WIDE]):
        a = np.pi / 2 * k
        pos = np.array([3000 * np.cos(a), 3000 * np.sin(a), 900.0])
        R = look_at_rotation(pos, np.array([0, 0, 900.0]), np.array([0, 0, 1.0]))
        cams.append(base.with_params(name=f"{base.name}{k}", rvec=matrix_to_rodrigues(R),
                                     tvec=-R @ pos))
    return cams


def joints(frames: int, rng) -> np.ndarray:
    """(F, 24, 3) mm: a fixed 24-joint body (0.6 x 0.4 x 1.8 m) walking a 1.2 m circle."""
    body = rng.uniform([-300, -200, 0], [300, 200, 1800], (24, 3))
    phase = np.linspace(0, 4 * np.pi, frames)
    centre = np.stack([1200 * np.cos(phase), 1200 * np.sin(phase), np.zeros(frames)], -1)
    return centre[:, None] + body + rng.normal(0, 20, (frames, 24, 3))


def observe(cams, X, sigma, rng) -> np.ndarray:
    uv = np.stack([cam.project(X) for cam in cams])
    uv += rng.normal(0, sigma, uv.shape)
    for c, cam in enumerate(cams):
        inside = np.all((uv[c] >= 0) & (uv[c] <= [cam.width - 1, cam.height - 1]), axis=-1)
        uv[c][~inside] = np.nan
    return uv


def dlt_svd(cams, uv) -> np.ndarray:
    """The same weighted DLT solved by batched SVD of the homogeneous (M, 2C, 4) system."""
    C, P = uv.shape[0], uv.shape[1]
    A = np.zeros((P, 2 * C, 4))
    for c, cam in enumerate(cams):
        seen = np.all(np.isfinite(uv[c]), axis=-1)
        xy = np.zeros((P, 2))
        xy[seen] = cam.unproject(uv[c, seen])
        Pm = np.hstack([cam.R, cam.tvec[:, None]])
        for i, f in ((0, cam.fx), (1, cam.fy)):
            row = xy[:, i, None] * Pm[2] - Pm[i]
            A[:, 2 * c + i] = row * (seen * f / np.linalg.norm(row[:, :3], axis=-1))[:, None]
    Xh = np.linalg.svd(A)[2][:, -1]
    return Xh[:, :3] / Xh[:, 3:]


def best_time(fn, repeat: int):
    """(wall s, CPU s, result) of the fastest of ``repeat`` runs; CPU time shows a busy machine."""
    best, out = (np.inf, np.inf), None
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        best = min(best, (time.perf_counter() - t0, time.process_time() - c0))
    return *best, out


def aniposelib_triangulate(cams):
    """aniposelib's CameraGroup.triangulate for our cameras, or the reason it is unavailable."""
    try:
        import aniposelib
        import jax  # noqa: F401  (aniposelib 0.8 imports it inside triangulate)
        from aniposelib.cameras import Camera as ACamera, CameraGroup
    except ImportError as e:
        return None, f"aniposelib not installed ({e})"
    group = CameraGroup([ACamera(matrix=c.K, dist=c.dist, size=c.size, rvec=c.rvec, tvec=c.tvec,
                                 name=c.name) for c in cams])
    name = f"aniposelib {aniposelib.__version__} (jax {jax.__version__})"
    return (lambda uv: group.triangulate(uv, undistort=True)), name


def baseline_package(rev: str, folder: Path):
    """stereo_bench as committed at ``rev``, imported as ``stereo_bench_baseline``."""
    root = Path(__file__).resolve().parent.parent
    try:
        tar = subprocess.run(["git", "-C", str(root), "archive", rev, "stereo_bench"],
                             check=True, capture_output=True).stdout
    except subprocess.CalledProcessError as e:
        raise ValueError(f"--baseline: git archive {rev!r} failed: "
                         f"{e.stderr.decode().strip()}") from None
    tarfile.open(fileobj=io.BytesIO(tar)).extractall(folder, filter="data")
    pkg = folder / "stereo_bench"
    spec = importlib.util.spec_from_file_location("stereo_bench_baseline", pkg / "__init__.py",
                                                  submodule_search_locations=[str(pkg)])
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return {name: importlib.import_module(f"{spec.name}.{name}")
            for name in ("camera", "triangulate", "render")}


def opencv_pair(cams, uv):
    """cv2.undistortPoints (default criteria) + cv2.triangulatePoints for cameras 0 and 1."""
    def run():
        P = [np.hstack([cam.R, cam.tvec[:, None]]) for cam in cams]
        n = [cv2.undistortPoints(uv[c].reshape(-1, 1, 2), cam.K, cam.dist).reshape(-1, 2).T
             for c, cam in enumerate(cams)]
        Xh = cv2.triangulatePoints(P[0], P[1], n[0], n[1])
        return (Xh[:3] / Xh[3]).T
    return run


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=10000)
    ap.add_argument("--sigma", type=float, default=1.0, help="pixel noise (px)")
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--baseline", metavar="REV", help="also time the package at git revision REV")
    ap.add_argument("--no-pixel-rays", action="store_true", help="skip the PixelRays timing")
    args = ap.parse_args()
    tmp = tempfile.TemporaryDirectory()
    base = baseline_package(args.baseline, Path(tmp.name)) if args.baseline else None

    rng = np.random.default_rng(args.seed)
    cams = ring_rig()
    X = joints(args.frames, rng)
    uv = observe(cams, X, args.sigma, rng)
    flat = uv.reshape(len(cams), -1, 2)
    n = X.shape[0] * X.shape[1]
    finite = np.all(np.isfinite(flat), axis=-1)
    seen = finite.sum(0)
    print(f"numpy {np.__version__}, OpenCV {cv2.__version__}, 1 CPU; {args.frames} frames x "
          f"{X.shape[1]} joints x {len(cams)} cameras ({', '.join(c.name for c in cams)}), "
          f"noise {args.sigma} px; views per point: "
          + ", ".join(f"{k}: {np.mean(seen == k):.1%}" for k in range(len(cams) + 1)))

    anipose, anipose_name = aniposelib_triangulate(cams)
    methods = {
        "(Camera.unproject alone, in every method)":
            lambda: [cam.unproject(flat[c, finite[c]]) for c, cam in enumerate(cams)],
        "DLT (3x3 normal equations)": lambda: triangulate_dlt(cams, uv),
        "DLT (batched SVD)": lambda: dlt_svd(cams, flat).reshape(X.shape),
        "midpoint": lambda: triangulate_midpoint(cams, uv),
        "refined (DLT + Gauss-Newton)": lambda: refine_points(cams, uv, triangulate_dlt(cams, uv)),
    }
    if base is not None:
        bcams = [base["camera"].Camera.from_dict(c.to_dict()) for c in cams]
        methods[f"({args.baseline}: Camera.unproject alone)"] = \
            lambda: [cam.unproject(flat[c, finite[c]]) for c, cam in enumerate(bcams)]
        methods[f"{args.baseline}: DLT"] = lambda: base["triangulate"].triangulate_dlt(bcams, uv)
    if anipose is not None:
        methods[f"{anipose_name} triangulate"] = lambda: anipose(flat).reshape(X.shape)
    two = (seen >= 2).reshape(X.shape[:-1])  # the error is over points seen twice or more
    print(f"{'method':42s} {'points/s':>9s} {'total s':>8s} {'CPU s':>7s} "
          f"{'mean 3D error mm':>17s}")
    for name, fn in methods.items():
        t, cpu, Y = best_time(fn, args.repeat)
        err = f"{np.linalg.norm(Y - X, axis=-1)[two].mean():.3g}" if name[0] != "(" else "-"
        print(f"{name:42s} {n / t:9.0f} {t:8.2f} {cpu:7.2f} {err:>17s}")
    if anipose is None:
        print(anipose_name)

    pair = finite[0] & finite[1]
    truth, both = X.reshape(-1, 3)[pair], flat[:2, pair]
    print(f"\n2 cameras ({cams[0].name}, {cams[1].name}): {pair.sum()} points seen by both")
    pair_methods = {
        f"OpenCV {cv2.__version__} undistortPoints + triangulatePoints": opencv_pair(cams[:2], both),
        "DLT (3x3 normal equations)": lambda: triangulate_dlt(cams[:2], both),
    }
    if base is not None:
        pair_methods[f"{args.baseline}: DLT"] = \
            lambda: base["triangulate"].triangulate_dlt(bcams[:2], both)
    for name, fn in pair_methods.items():
        t, cpu, Y = best_time(fn, args.repeat)
        err = np.linalg.norm(Y - truth, axis=-1).mean()
        print(f"{name:42s} {pair.sum() / t:9.0f} {t:8.2f} {cpu:7.2f} {err:17.3g}")

    if args.no_pixel_rays:
        return
    print("\nPixelRays (the ray of every pixel, per camera): CPU s (wall s)")
    for cam in (WIDE, RECT):
        builds = {"working tree": lambda: PixelRays(cam)}
        if base is not None:
            bcam = base["camera"].Camera.from_dict(cam.to_dict())
            builds[args.baseline] = lambda: base["render"].PixelRays(bcam)
        rays = {}
        for name, fn in builds.items():
            t, cpu, rays[name] = best_time(fn, 1)
            print(f"  {cam.name} {cam.width}x{cam.height} {name:>12s}: {cpu:6.2f} ({t:.2f})")
        if len(rays) == 2:
            new, old = rays.values()
            print(f"  {cam.name}: largest difference of the float32 rays "
                  f"{np.abs(new.xy - old.xy).max():.2g}, of the exact node rays "
                  f"{np.abs(new.node_xy - old.node_xy).max():.2g}")


if __name__ == "__main__":
    main()
