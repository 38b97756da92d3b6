"""Time the analytic renderer per frame on the paper's two cameras, on one core.

The frames are the paper's: the 9 x 12 checkerboard on the conical-spring trajectory of
configs/paper/rectilinear_mono.yaml (4096 x 3072) and wide_mono.yaml (640 x 480), rendered in
trajectory order from the near end (board filling the view) to the far end, so the per-frame
mean includes the texture rasterisations a real run pays. Everything runs single-threaded
(OMP/OPENBLAS/MKL_NUM_THREADS=1 before numpy loads, cv2.setNumThreads(1)). CPU time is what
the core spent (robust to other load on the machine), wall time is printed beside it. The
per-camera precomputation (PixelRays) is timed separately. OpenCV's speed depends on its build
(TRAPS.md), so its version is printed.

Every environment preset is timed beside the clean render of the same frames (the imaging
model: defocus, motion blur, the photon sensor, JPEG, vignetting, light and the board as made).
Each frame's PNG encoding (the dataset's record) is timed beside OpenCV's encoder, with the
files' mean sizes.

    python benchmarks/render_speed.py [--stride 2] [--supersampling 2 4] [--environments ...]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"  # before numpy is imported

import argparse  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from stereo_bench.config.schema import load_rig, parse_rig  # noqa: E402
from stereo_bench.core.files import encode_png  # noqa: E402
from stereo_bench.scene.dataset import render_settings  # noqa: E402
from stereo_bench.config.environments import PRESETS  # noqa: E402
from stereo_bench.render import AnalyticRenderer, PixelRays  # noqa: E402
from stereo_bench.scene.rig import Rig  # noqa: E402

PAPER = Path(__file__).resolve().parent.parent / "configs" / "paper"
RIGS = {"rectilinear": ("rectilinear_mono.yaml", 0.3), "wide": ("wide_mono.yaml", 0.010)}


def timed(fn):
    cpu, wall = time.process_time(), time.perf_counter()
    out = fn()
    return out, time.process_time() - cpu, time.perf_counter() - wall


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--stride", type=int, default=2, help="render every STRIDE-th frame")
    ap.add_argument("--supersampling", type=int, nargs="+", default=[2])
    ap.add_argument("--environments", nargs="+", default=list(PRESETS))
    args = ap.parse_args()
    cv2.setNumThreads(1)
    print(f"OpenCV {cv2.__version__}, numpy {np.__version__}; one core: cv2.setNumThreads(1), "
          f"OMP/OPENBLAS/MKL_NUM_THREADS=1")
    for name, (config, aim) in RIGS.items():
        base = load_rig(PAPER / config).model_dump(mode="json")
        rig = Rig.from_config(parse_rig(base))
        cam = rig.cameras[0]
        R, t = rig.cam_from_board(cam)
        frames = range(0, len(R), args.stride)
        rays, cpu, wall = timed(lambda: PixelRays(cam))
        print(f"\n{name} {cam.width}x{cam.height}: precompute PixelRays {cpu:.2f} s CPU "
              f"({wall:.2f} s wall), {rays.xy.nbytes / 2**20:.0f} MiB; "
              f"{len(frames)} frames of {rig.pattern.kind}; clean aim < {aim * 1e3:.0f} "
              f"ms/frame, the imaging model's aim at most 3x clean")
        print(f"  {'s':>2} {'environment':<19} {'CPU ms/frame mean [min..max]':>30} "
              f"{'wall ms/frame':>14} {'x clean':>8} {'PNG ms':>8} {'OpenCV':>8} "
              f"{'MB':>7} {'OpenCV':>7}")
        for s in args.supersampling:
            clean_ms = None
            for env in args.environments:
                cfg = parse_rig({**base, "environment": {"kind": env, "supersampling": s}})
                rig = Rig.from_config(cfg)  # the board as made differs per environment
                settings = render_settings(cfg, rig, cam)
                renderer = AnalyticRenderer(cam, rig.pattern, settings, rays)
                omega, v = rig.board_velocity(cam, settings.motion.speed_mm_s)
                rng = np.random.default_rng(0)
                times, png = [], []
                for f in frames:
                    image, cpu, wall = timed(lambda: renderer.render(R[f], t[f], rng,
                                                                     (omega[f], v[f])))
                    times.append((cpu, wall))
                    ours, ours_s, _ = timed(lambda: encode_png(image))
                    theirs, theirs_s, _ = timed(lambda: cv2.imencode(".png", image)[1])
                    png.append((ours_s, theirs_s, len(ours), theirs.size))
                times, png = np.array(times), np.array(png)
                cpu_ms, wall_ms = 1e3 * times[:, 0], 1e3 * times[:, 1]
                clean_ms = clean_ms or (cpu_ms.mean() if env == "clean" else None)
                ratio = f"{cpu_ms.mean() / clean_ms:8.1f}" if clean_ms else " " * 8
                ours_ms, cv_ms = 1e3 * png[:, 0].mean(), 1e3 * png[:, 1].mean()
                ours_mb, cv_mb = png[:, 2].mean() / 1e6, png[:, 3].mean() / 1e6
                print(f"  {s:>2} {env:<19} {cpu_ms.mean():>12.1f} [{cpu_ms.min():6.1f}.."
                      f"{cpu_ms.max():6.1f}] {wall_ms.mean():>14.1f} {ratio} "
                      f"{ours_ms:8.1f} {cv_ms:8.1f} {ours_mb:7.2f} {cv_mb:7.2f}")


if __name__ == "__main__":
    main()
