"""Time the analytic renderer per frame on the paper's two cameras, on one core.

The frames are the paper's: the 9 x 12 checkerboard on the conical-spring trajectory of
configs/paper/rectilinear_mono.yaml (4096 x 3072) and wide_mono.yaml (640 x 480), rendered in
trajectory order from the near end (board filling the view) to the far end, so the per-frame
mean includes the texture rasterisations a real run pays as the board moves away (each
environment first draws one frame untimed: compiling the kernels and the board's first
texture are a run's once, not a frame's). Everything runs single-threaded
(OMP/OPENBLAS/MKL_NUM_THREADS=1 before numpy loads, cv2.setNumThreads(1)). CPU time is what
the core spent (robust to other load on the machine), wall time is printed beside it. The
per-camera precomputation (PixelRays) is timed separately. OpenCV's speed depends on its build
(TRAPS.md), so its version is printed.

Every environment preset is timed beside the clean render of the same frames (the imaging
model: defocus, motion blur, the photon sensor, JPEG, vignetting, light and the board as made).
Each frame's PNG encoding (the dataset's record) is timed beside OpenCV's encoder, with the
files' mean sizes.

With ``--baseline REV`` git revision REV renders the same frames in a subprocess that imports
stereo_bench from a worktree of REV (revision.py), frame by frame in turn with the working
tree's, timed in its own process the same way; the table says how far the working tree's
images are from REV's (the largest difference in grey levels and the share of pixels that
differ).

    python benchmarks/render_speed.py [--stride 2] [--supersampling 2 4] [--environments ...]
        [--baseline REV]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"  # before numpy is imported

import argparse  # noqa: E402
import time  # noqa: E402
from contextlib import nullcontext  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from stereo_bench.config.schema import load_rig, parse_rig  # noqa: E402
from stereo_bench.scene.dataset import render_settings  # noqa: E402
from stereo_bench.config.environments import PRESETS  # noqa: E402
from stereo_bench.render import AnalyticRenderer, PixelRays  # noqa: E402
from stereo_bench.scene.rig import Rig  # noqa: E402
from revision import revision_server  # noqa: E402

PAPER = Path(__file__).resolve().parent.parent / "configs" / "paper"
RIGS = {"rectilinear": ("rectilinear_mono.yaml", 0.3), "wide": ("wide_mono.yaml", 0.010)}


def timed(fn):
    cpu, wall = time.process_time(), time.perf_counter()
    out = fn()
    return out, time.process_time() - cpu, time.perf_counter() - wall


def frame_renderer(config: dict, rays: dict):
    """render(f) -> the frame f of the rig ``config`` (a rig file's fields, its first camera),
    its sensor noise from one generator over the frames in order; ``rays``: PixelRays by image
    size, filled on first use (the per-camera precomputation, not a frame's)."""
    cfg = parse_rig(config)
    rig = Rig.from_config(cfg)  # the board as made differs per environment
    cam = rig.cameras[0]
    if (cam.width, cam.height) not in rays:
        rays[cam.width, cam.height] = PixelRays(cam)
    settings = render_settings(cfg, rig, cam)
    renderer = AnalyticRenderer(cam, rig.pattern, settings, rays[cam.width, cam.height])
    R, t = rig.cam_from_board(cam)
    omega, v = rig.board_velocity(cam, settings.motion.speed_mm_s)
    rng = np.random.default_rng(0)
    return lambda f: renderer.render(R[f], t[f], rng, (omega[f], v[f]))


# The subprocess that renders a revision's frames (revision.serve): ("rig", config) makes its
# renderer, ("frame", f) renders frame f and is answered (image, CPU seconds). It imports this
# file's frame_renderer with the revision's stereo_bench, and draws a first frame untimed as
# measure does.
SERVER = """
import time
import cv2
from render_speed import frame_renderer
from revision import serve
cv2.setNumThreads(1)
rays, renderer = {}, []


def answer(request):
    kind, arg = request
    if kind == "rig":
        frame_renderer(arg, rays)(0)
        renderer[:] = [frame_renderer(arg, rays)]
        return None
    start = time.process_time()
    image = renderer[0](arg)
    return image, time.process_time() - start


serve(answer)
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--stride", type=int, default=2, help="render every STRIDE-th frame")
    ap.add_argument("--supersampling", type=int, nargs="+", default=[2])
    ap.add_argument("--environments", nargs="+", default=list(PRESETS))
    ap.add_argument("--baseline", metavar="REV", help="also render the frames with git "
                                                      "revision REV and compare")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    print(f"OpenCV {cv2.__version__}, numpy {np.__version__}; one core: cv2.setNumThreads(1), "
          f"OMP/OPENBLAS/MKL_NUM_THREADS=1")
    with revision_server(args.baseline, SERVER) if args.baseline else nullcontext() as base:
        for name, (config, aim) in RIGS.items():
            measure(name, load_rig(PAPER / config).model_dump(mode="json"), aim, args, base)


def measure(name: str, base_config: dict, aim: float, args, baseline) -> None:
    """Print a table of every environment on the rig ``base_config``'s first camera."""
    # Imported here: the baseline's subprocess imports this file with an older stereo_bench,
    # which needs only frame_renderer's imports.
    from stereo_bench.core.files import encode_png

    rig = Rig.from_config(parse_rig(base_config))
    cam = rig.cameras[0]
    frames = range(0, len(rig.cam_from_board(cam)[0]), args.stride)
    rays, cpu, wall = timed(lambda: {(cam.width, cam.height): PixelRays(cam)})
    print(f"\n{name} {cam.width}x{cam.height}: precompute PixelRays {cpu:.2f} s CPU "
          f"({wall:.2f} s wall), {rays[cam.width, cam.height].xy.nbytes / 2**20:.0f} MiB; "
          f"{len(frames)} frames of {rig.pattern.kind}; clean aim < {aim * 1e3:.0f} "
          f"ms/frame, the imaging model's aim at most 3x clean")
    header = (f"  {'s':>2} {'environment':<19} {'CPU ms/frame mean [min..max]':>30} "
              f"{'wall ms/frame':>14} {'x clean':>8} {'PNG ms':>8} {'OpenCV':>8} "
              f"{'MB':>7} {'OpenCV':>7}")
    if baseline:
        header += f" {'base ms':>8} {'x base':>7} {'max |d|':>8} {'differ':>8}"
    print(header)
    for s in args.supersampling:
        clean_ms = None
        for env in args.environments:
            config = {**base_config, "environment": {"kind": env, "supersampling": s}}
            # One frame first, untimed, with a renderer of its own: compiling the kernels (a
            # revision's fresh worktree has none cached) and the board's first texture level
            # are the run's once, not a frame's.
            frame_renderer(config, rays)(frames[0])
            render = frame_renderer(config, rays)
            if baseline:
                baseline(("rig", config))
            times, png, base_ms, diffs = [], [], [], []
            for f in frames:
                image, cpu, wall = timed(lambda: render(f))
                times.append((cpu, wall))
                ours, ours_s, _ = timed(lambda: encode_png(image))
                theirs, theirs_s, _ = timed(lambda: cv2.imencode(".png", image)[1])
                png.append((ours_s, theirs_s, len(ours), theirs.size))
                if baseline:
                    old, old_s = baseline(("frame", f))
                    base_ms.append(1e3 * old_s)
                    d = np.abs(image.astype(np.int16) - old)
                    diffs.append((int(d.max()), np.count_nonzero(d) / d.size))
            times, png = np.array(times), np.array(png)
            cpu_ms, wall_ms = 1e3 * times[:, 0], 1e3 * times[:, 1]
            clean_ms = clean_ms or (cpu_ms.mean() if env == "clean" else None)
            ratio = f"{cpu_ms.mean() / clean_ms:8.1f}" if clean_ms else " " * 8
            ours_ms, cv_ms = 1e3 * png[:, 0].mean(), 1e3 * png[:, 1].mean()
            ours_mb, cv_mb = png[:, 2].mean() / 1e6, png[:, 3].mean() / 1e6
            line = (f"  {s:>2} {env:<19} {cpu_ms.mean():>12.1f} [{cpu_ms.min():6.1f}.."
                    f"{cpu_ms.max():6.1f}] {wall_ms.mean():>14.1f} {ratio} "
                    f"{ours_ms:8.1f} {cv_ms:8.1f} {ours_mb:7.2f} {cv_mb:7.2f}")
            if baseline:
                diff = np.array(diffs)
                line += (f" {np.mean(base_ms):8.1f} {cpu_ms.mean() / np.mean(base_ms):7.2f} "
                         f"{int(diff[:, 0].max()):8d} {100 * diff[:, 1].mean():7.4f}%")
            print(line, flush=True)


if __name__ == "__main__":
    main()
