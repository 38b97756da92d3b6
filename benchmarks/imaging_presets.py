"""What each environment preset does to calibration: OpenCV's own pipeline's RPE against the
preset's target, and the project's detection error against the truth per pattern.

For each preset and each of the paper's two cameras (configs/paper/wide_mono.yaml, 640 x 480;
rectilinear_mono.yaml, 4096 x 3072) the conical-spring frames are rendered with the preset and
calibrated the way OpenCV's samples do it: cv2.findChessboardCorners (ADAPTIVE_THRESH |
NORMALIZE_IMAGE; on an image larger than 1280 px, on a reduced copy, since on noisy 12 MP images
it takes minutes per image), cv2.cornerSubPix at full resolution with an 11 x 11 window (smaller
when the squares are: the window must stay within the squares around a corner),
cv2.calibrateCamera with its 5 coefficients. The RPE_RMS printed is cv2.calibrateCamera's. Then the project's detector runs on
every pattern and its error against the ground truth is printed: mean |e| and the mean signed
error (a bias), in px.

    python benchmarks/imaging_presets.py [--presets office studio] [--cameras wide rect]
        [--frames 127] [--stride 1] [--patterns checkerboard charuco]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import numpy as np

from stereo_bench.config.schema import load_rig, parse_rig
from stereo_bench.scene.dataset import frame_rng, render_settings
from stereo_bench.detect.boards import detect
from stereo_bench.config.environments import PRESETS
from stereo_bench.render import AnalyticRenderer
from stereo_bench.scene.rig import Rig

PAPER = Path(__file__).resolve().parent.parent / "configs" / "paper"
CAMERAS = {"wide": "wide_mono.yaml", "rect": "rectilinear_mono.yaml"}
PATTERNS = ["checkerboard", "symmetric_circles", "asymmetric_circles", "charuco"]
SEARCH_SIDE = 1280
SUBPIX = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.001)  # OpenCV's samples


def frames_of(base: dict, preset: str, pattern: str, frames: int, stride: int, rays=None):
    """(rig, images, truth points (F, N, 2), visible (F, N)) of every stride-th frame."""
    cfg = parse_rig({**base, "pattern": {"kind": pattern}, "environment": {"kind": preset},
                     "trajectory": {**base["trajectory"], "frames": frames}})
    rig = Rig.from_config(cfg)
    cam = rig.cameras[0]
    settings = render_settings(cfg, rig, cam)
    renderer = AnalyticRenderer(cam, rig.pattern, settings, rays)
    R, t = rig.cam_from_board(cam)
    omega, v = rig.board_velocity(cam, settings.motion.speed_mm_s)
    gt = rig.ground_truth()
    keep = range(0, frames, stride)
    images = [renderer.render(R[f], t[f], frame_rng(cfg.seed, 0, f), (omega[f], v[f]))
              for f in keep]
    return rig, images, gt.points[0][list(keep)], gt.visible[0][list(keep)], renderer.rays


def opencv_pipeline(images, pattern) -> tuple[float, int]:
    """(RPE_RMS px of cv2.calibrateCamera, views used) of OpenCV's sample pipeline."""
    size = pattern.pattern_size
    obj = pattern.object_points().astype(np.float32)
    objs, imgs = [], []
    for img in images:
        # On a large image findChessboardCorners takes minutes when noise defeats it; search
        # a copy of at most SEARCH_SIDE px, then refine at full resolution (as users do).
        scale = min(1.0, SEARCH_SIDE / max(img.shape))
        small = img if scale == 1.0 else cv2.resize(img, None, fx=scale, fy=scale,
                                                    interpolation=cv2.INTER_AREA)
        ok, c = cv2.findChessboardCorners(
            small, size, cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
        if not ok:
            continue
        c = ((c + 0.5) / scale - 0.5).astype(np.float32)  # pixel centres at (0, 0)
        spacing = np.linalg.norm(np.diff(c.reshape(size[1], size[0], 2), axis=1), axis=-1).min()
        half = int(max(2, min(11, spacing / 2 - 1)))
        c = cv2.cornerSubPix(img, c, (half, half), (-1, -1), SUBPIX)
        # findChessboardCorners may start at either end of the board; the pattern's order
        # does not matter to calibrateCamera as long as it is one consistent grid.
        objs.append(obj)
        imgs.append(c)
    if len(objs) < 3:
        return float("nan"), len(objs)
    h, w = images[0].shape
    rms, *_ = cv2.calibrateCamera(objs, imgs, (w, h), None, None)
    return float(rms), len(objs)


def detection_error(rig, images, truth, visible) -> tuple[float, np.ndarray, float]:
    """(mean |e| px, mean signed e (2,) px, share of frames found) of the project's detector."""
    errs, found = [], 0
    for img, p, vis in zip(images, truth, visible):
        d = detect(img, rig.pattern)
        if not d.found:
            continue
        found += 1
        ok = vis & np.all(np.isfinite(d.points), axis=1)
        errs.append(d.points[ok] - p[ok])
    e = np.concatenate(errs) if errs else np.full((1, 2), np.nan)
    return float(np.linalg.norm(e, axis=1).mean()), e.mean(0), found / len(images)


def write_montage(path: Path, presets: list[str], frame: int = 20) -> None:
    """One frame of the wide camera under every preset, labelled, in rows of three."""
    base = load_rig(PAPER / CAMERAS["wide"]).model_dump(mode="json")
    tiles = []
    for preset in presets:
        # The same pose in every preset: the frame-th of a trajectory of frame + 1 frames.
        _, images, _, _, _ = frames_of(base, preset, "checkerboard", frame + 1, frame, None)
        img = cv2.cvtColor(images[-1], cv2.COLOR_GRAY2BGR)
        cv2.putText(img, preset, (12, 34), cv2.FONT_HERSHEY_SIMPLEX, 1.0, (0, 0, 255), 2)
        tiles.append(img)
    while len(tiles) % 3:
        tiles.append(np.full_like(tiles[0], 255))
    rows = [np.hstack(tiles[i:i + 3]) for i in range(0, len(tiles), 3)]
    cv2.imwrite(str(path), cv2.resize(np.vstack(rows), None, fx=0.6, fy=0.6,
                                      interpolation=cv2.INTER_AREA))
    print(f"wrote {path}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--presets", nargs="+", default=list(PRESETS))
    ap.add_argument("--cameras", nargs="+", default=list(CAMERAS), choices=list(CAMERAS))
    ap.add_argument("--patterns", nargs="+", default=PATTERNS, choices=PATTERNS)
    ap.add_argument("--frames", type=int, default=127)
    ap.add_argument("--stride", type=int, default=1)
    ap.add_argument("--montage", type=Path, help="also write one frame per preset side by side "
                    "(the wide camera's checkerboard) to this PNG, and stop")
    args = ap.parse_args()
    if args.montage:
        write_montage(args.montage, args.presets)
        return
    print(f"OpenCV {cv2.__version__}, numpy {np.__version__}; {args.frames} frames of the "
          f"conical spring, every {args.stride}")
    for cam_name in args.cameras:
        base = load_rig(PAPER / CAMERAS[cam_name]).model_dump(mode="json")
        rays = None
        print(f"\n{cam_name} camera ({CAMERAS[cam_name]})")
        print(f"  {'preset':<19} {'target':>7} {'OpenCV RPE':>10} {'views':>6}   detection "
              f"per pattern: mean |e| px, signed (x, y) px, found")
        for preset in args.presets:
            t0 = time.perf_counter()
            target = PRESETS[preset].target_rpe_px
            cells = []
            rpe, views = float("nan"), 0
            for pattern in args.patterns:
                rig, images, truth, visible, rays = frames_of(base, preset, pattern,
                                                              args.frames, args.stride, rays)
                if pattern == "checkerboard":
                    rpe, views = opencv_pipeline(images, rig.pattern)
                mean, signed, share = detection_error(rig, images, truth, visible)
                cells.append(f"{pattern} {mean:.3f} ({signed[0]:+.3f}, {signed[1]:+.3f}) "
                             f"{100 * share:.0f}%")
            tgt = f"{target:.2f}" if target else "-"
            print(f"  {preset:<19} {tgt:>7} {rpe:>10.3f} {views:>6}   " + "; ".join(cells)
                  + f"  [{time.perf_counter() - t0:.0f} s]", flush=True)


if __name__ == "__main__":
    main()
