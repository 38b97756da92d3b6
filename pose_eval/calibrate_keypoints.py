"""`calibrate-keypoints`: a studio's extrinsics and clock offsets from a detector's keypoint files
of people moving in it, with no board (pose_eval.body_calibration).

The user gives the keypoints (OpenPose-style JSON per camera and frame, SMPL's 24 joints or
OpenPose's BODY_25; several people when a tracker gave them ids: pose_eval.observe.read_tracks),
the cameras' intrinsics (any exchange file: their names are the keypoint folders' names, their
poses are ignored) and one known length (a person's height or a baseline). Written to OUT:

* ``cameras.json``: the studio in its floor frame (z up, mm), the suite's own camera format;
* ``<format>/`` for every exchange format (OpenCV and Kalibr hold a rig relative to its first
  camera, so there the floor frame is lost; the others keep it);
* ``report.json`` and ``report.md``: clock offsets (frames and ms), the pairs' shifts and
  inliers, the order the cameras joined, the reprojection RMS, how the vertical was found.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

from stereo_bench import io
from stereo_bench.cli import say
from stereo_bench.config.bounds import ConfigError
from stereo_bench.core.files import write_json, write_text
from stereo_bench.io.rundir import locked
from stereo_bench.run.exchange import write_estimates

from .body import load_body_model
from .body_calibration import Scale, calibrate_from_body
from .body_session import skeleton
from .observe import read_tracks

RIG_RELATIVE = ("opencv", "kalibr")  # formats without a world frame (io.common.cam_from_cam0)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="calibrate-keypoints",
        description="Calibrate a studio's extrinsics and its cameras' clock offsets from 2D "
                    "keypoints of people moving in it, with no board (docs/body_calibration.md).")
    p.add_argument("keypoints", metavar="KEYPOINTS_DIR",
                   help="<camera>/<frame>_keypoints.json files (OpenPose JSON: SMPL's 24 joints "
                        "or BODY_25)")
    p.add_argument("--cameras", required=True, metavar="FILE",
                   help="the cameras' intrinsics: a calibration file or folder in an exchange "
                        "format (docs/formats.md); its camera names are the keypoint folders")
    p.add_argument("--cameras-format", metavar="FORMAT",
                   help="its format (default: guessed from the file names)")
    scale = p.add_mutually_exclusive_group(required=True)
    scale.add_argument("--height-mm", type=float,
                       help="the height of the first person (the lowest tracker id)")
    scale.add_argument("--baseline", nargs=3, metavar=("CAMERA_A", "CAMERA_B", "MM"),
                       help="the distance between two cameras' centres")
    p.add_argument("--fps", type=float, default=30.0, help="frame rate (default: %(default)s)")
    p.add_argument("--max-offset-frames", type=int, default=10,
                   help="how far the clocks may disagree, whole frames; 0: synchronised "
                        "(default: %(default)s)")
    p.add_argument("--threshold-px", type=float, default=6.0,
                   help="RANSAC inlier bound (default: %(default)s)")
    p.add_argument("--out", help="output folder (default: out/<keypoints folder>_calibration)")
    return p


def _scale(args) -> Scale:
    """--height-mm or --baseline as a Scale; its refusal names the option."""
    option = "--height-mm" if args.height_mm is not None else "--baseline"
    try:
        if args.height_mm is not None:
            return Scale(height_mm=args.height_mm)
        a, b, mm = args.baseline
        return Scale(baseline_mm=float(mm), cameras=(a, b))
    except ValueError as e:
        raise ValueError(f"{option}: {str(e).removeprefix('scale: ')}") from None


def check(args) -> None:
    def need(ok, option, expected, value):
        if not ok:
            raise ValueError(f"{option}: expected {expected}, got {value!r}")

    need(math.isfinite(args.fps) and 0 < args.fps <= 10_000, "--fps", "a rate in (0, 10000]",
         args.fps)
    need(0 <= args.max_offset_frames <= 300, "--max-offset-frames", "0..300",
         args.max_offset_frames)
    need(math.isfinite(args.threshold_px) and 0 < args.threshold_px <= 200, "--threshold-px",
         "a bound in (0, 200] px", args.threshold_px)


def calibrate(args) -> tuple[list, dict]:
    """(the cameras in the floor frame, the report)."""
    check(args)
    scale = _scale(args)
    cameras = io.load(args.cameras, args.cameras_format)
    if len(cameras) < 2:
        raise ValueError(f"{args.cameras}: {len(cameras)} camera; calibrating a studio needs at "
                         f"least two")
    pixels, confidence, layout, people = read_tracks(args.keypoints, cameras)
    body, _ = skeleton(layout, load_body_model(), len(people))
    result = calibrate_from_body(cameras, pixels, confidence, body, scale,
                                 args.max_offset_frames, args.threshold_px)
    names = [c.name for c in cameras]
    report = {
        "keypoints": str(args.keypoints), "cameras_file": str(args.cameras), "layout": layout,
        "people": people if people != [-1] else "one (no tracker ids: the first of each file)",
        "frames": int(pixels.shape[1]), "fps": args.fps,
        "scale": ({"height_mm": scale.height_mm} if scale.height_mm is not None else
                  {"baseline_mm": scale.baseline_mm, "cameras": list(scale.cameras)}),
        "offsets_frames": dict(zip(names, map(float, result.offsets_frames))),
        "offsets_ms": dict(zip(names, (float(v) * 1000 / args.fps
                                       for v in result.offsets_frames))),
        "reprojection_rms_px": result.rms_px, "vertical": result.vertical,
        "pairs": result.pairs, "order": result.order,
        "detections": {n: int(np.count_nonzero(confidence[c] > 0)) for c, n in enumerate(names)},
    }
    return result.cameras, report


def markdown(report: dict, refused: dict) -> str:
    lines = [f"# calibrate-keypoints: {report['keypoints']}", "",
             f"{report['frames']} frames of {report['layout']} keypoints, people: "
             f"{report['people']}; scale from {report['scale']}; the vertical from the "
             f"{report['vertical']}. Reprojection RMS {report['reprojection_rms_px']:.2f} px "
             f"(inliers).", "", "| camera | clock offset, frames | ms | detections |",
             "|---|---|---|---|"]
    for name, frames in report["offsets_frames"].items():
        lines.append(f"| {name} | {frames:+.3f} | {report['offsets_ms'][name]:+.1f} | "
                     f"{report['detections'][name]} |")
    lines += ["", f"Cameras joined in the order {', '.join(report['order'])}.", "",
              "| pair | shift, frames | inliers |", "|---|---|---|"]
    lines += [f"| {' - '.join(p['cameras'])} | {p['shift']:+d} | {p['inliers']} |"
              for p in report["pairs"]]
    if refused:
        lines += ["", "Formats that refused this rig:"] + [f"- {f}: {why}"
                                                          for f, why in refused.items()]
    return "\n".join(lines) + "\n"


def write_outputs(cameras, report: dict, out: Path) -> list[str]:
    """cameras.json, every exchange format, report.json, report.md; the formats written."""
    write_json(out / "cameras.json", [c.to_dict() for c in cameras])
    refused, written = {}, []
    for fmt in io.FORMATS:
        options = {"rebase": True} if fmt in RIG_RELATIVE else {}
        _, why = write_estimates({"rig": cameras}, fmt, out / fmt, **options)
        if why:
            refused[fmt] = why["rig"]
        else:
            written.append(fmt)
    report["formats"] = {"written": written, "refused": refused}
    write_json(out / "report.json", report)
    write_text(out / "report.md", markdown(report, refused))
    return written


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    out = Path(args.out or Path("out") / f"{Path(args.keypoints).name}_calibration")
    try:
        cameras, report = calibrate(args)
        with locked(out):
            written = write_outputs(cameras, report, out)
    except (ConfigError, FileNotFoundError, ValueError) as e:
        say("error", "red", str(e))
        return 2
    except OSError as e:
        say("error", "red", f"{e.filename + ': ' if e.filename else ''}{e.strerror or e}")
        return 2
    print(markdown(report, report["formats"]["refused"]), end="")
    print(f"wrote {out}/cameras.json, report.json, report.md and {', '.join(written)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
