"""Where a studio's intrinsics come from, and what it costs its geometry.

Renders one studio session once (walk plus close-ups), then runs the suite's calibration and
rig stages on the same images with the intrinsics of each camera taken from its close-ups only,
from the walk only (far views, the board small and seen at a slant), or from both, and with the
walk's intrinsics refined in the rig's bundle adjustment. Prints, per setting and method, the
camera-centre and rotation errors (reference camera fixed; mean and worst camera) beside the
rig's reprojection error: the far views can give a low reprojection error and a wrong geometry.
Prints figures; passes or fails nothing.

    python benchmarks/studio_intrinsics.py [RIG.yaml] [--out DIR] [--methods M ...]
        [--environment clean|noisy] [--seed S]
"""

import argparse
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

import stereo_bench
from stereo_bench.config.schema import load_rig
from stereo_bench.run.pipeline import run_trial
from stereo_bench.io.rundir import RunPaths

DEFAULT_RIG = Path(__file__).parent.parent / "configs" / "studios" / "h36m_rectangle.yaml"
SETTINGS = [
    ("close-ups", {"intrinsics_views": "closeups"}),
    ("walk only", {"intrinsics_views": "session"}),
    ("walk, refined in rig", {"intrinsics_views": "session", "refine_intrinsics": True}),
    ("all views", {"intrinsics_views": "all"}),
]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("rig", nargs="?", default=str(DEFAULT_RIG))
    ap.add_argument("--out", help="folder for the runs (default: a temporary one)")
    ap.add_argument("--methods", nargs="+", default=["zhang", "bouguet", "opencv"])
    ap.add_argument("--environment", default="noisy", choices=["clean", "noisy"])
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    base = load_rig(args.rig)
    base = base.model_copy(update={
        "seed": args.seed,
        "environment": base.environment.model_copy(update={"kind": args.environment})})
    out = Path(args.out or tempfile.mkdtemp(prefix="studio_intrinsics_"))
    print(f"synthcal-bench {stereo_bench.__version__}, OpenCV {cv2.__version__}, numpy "
          f"{np.__version__}; rig {base.name} ({len(base.cameras)} cameras), environment "
          f"{args.environment}, seed {args.seed}, runs in {out}")
    dataset = None
    rows = []
    for label, change in SETTINGS:
        cfg = base.model_copy(update={"calibration": base.calibration.model_copy(update=change)})
        folder = out / label.replace(" ", "_").replace(",", "")
        t0 = time.perf_counter()
        report = run_trial(cfg, folder, args.methods, dataset_dir=dataset)
        if dataset is None:
            dataset = RunPaths(folder).trial(cfg.seed).dataset.root
        seconds = time.perf_counter() - t0
        for m in args.methods:
            entry = report["rig"][m]
            if "error" in entry:
                rows.append((label, m, entry["error"]))
                continue
            cams = list(entry["camera_errors"].values())[1:]  # the reference scores 0
            centre = [c["centre_mm"] for c in cams]
            rotation = [c["rotation_deg"] for c in cams]
            aligned = [c["centre_mm"] for c in (entry["aligned"] or {}).get(
                "cameras", {}).values()]
            rows.append((label, m, np.mean(centre), np.max(centre), np.max(rotation),
                         np.max(aligned) if aligned else float("nan"), entry["rms_px"],
                         entry["rmse_cal_mm"], seconds))
    print()
    print(f"{'intrinsics from':<22}{'method':<10}{'centre err mm':>15}{'worst':>9}"
          f"{'rot. deg':>10}{'aligned mm':>12}{'rig RMS px':>12}{'RMSE_cal mm':>13}"
          f"{'run s':>8}")
    for row in rows:
        if len(row) == 3:
            print(f"{row[0]:<22}{row[1]:<10}  failed: {row[2]}")
            continue
        label, m, mean_c, worst_c, rot, aligned, rms, rmse, seconds = row
        print(f"{label:<22}{m:<10}{mean_c:>15.3f}{worst_c:>9.3f}{rot:>10.4f}{aligned:>12.3f}"
              f"{rms:>12.4f}{rmse:>13.3f}{seconds:>8.1f}")


if __name__ == "__main__":
    main()
