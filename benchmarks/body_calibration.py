"""Calibration from the body graded against the truth: the issue's table and its curves.

For each studio (configs/studios/), number of people and keypoint detector, ``--seeds`` sessions
of people walking for ``--frames`` frames, each camera's clock offset drawn per seed uniformly
within +-``--max-offset-ms`` (camera 0 at 0), calibrated by pose_eval.body_session and graded by
pose_eval.metrics.studio_errors: rotation and centre errors after a similarity alignment (mean
over cameras), the scale error of the known height, the worst clock error, the vertical's error,
the reprojection RMS and the wall time, each as its mean [95 % interval] over the seeds.
Detectors: ``gaussN`` (N px Gaussian keypoints, occluded joints 3x) or ``blazepose_fit``
(BlazePose's error as fitted on rendered bodies, pose_eval/data/blazepose_fit.json).

    python benchmarks/body_calibration.py table [--rigs h36m_rectangle ring8] [--people 1 2]
        [--detectors gauss1 blazepose_fit] [--seeds 5] [--frames 300] [--workers 2] [--json F]
    python benchmarks/body_calibration.py curves [--rig h36m_rectangle] [--seeds 3] [--json F]

``curves`` varies one thing at a time from 1 person, 300 frames, blazepose_fit: the number of
frames (100, 300, 1000), the keypoint noise (Gaussian 1, 3, 10 px) and the number of people
(1, 2, 3). Figures, not a pass/fail test.

    python benchmarks/body_calibration.py rendered BODY_DIR [BODY_DIR ...]

calibrates from BlazePose itself on Blender renders: each BODY_DIR is a body rendered by
``stereo-bench study`` (OUT/bodies/<rig>/<motion>_<frames>f_<samples>s: cameras.json and
blazepose_<camera>.npy, its raw landmarks), the folders' frames joined as segments of one
session (synchronised cameras: the clocks are still searched, so their error is measured).
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from concurrent.futures import ProcessPoolExecutor  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from stereo_bench.config.schema import load_rig  # noqa: E402
from stereo_bench.run.sweep_stats import t_interval  # noqa: E402
from pose_eval.body import load_body_model  # noqa: E402
from pose_eval.body_session import Session, calibrate_session  # noqa: E402
from pose_eval.detector_fit import load_fit, observe_fitted  # noqa: E402
from pose_eval.observe import DetectorModel, observe  # noqa: E402
from pose_eval.report import BODY_ERRORS  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SHOWN = ["rotation_deg", "centre_mm", "scale_pct", "offset_frames", "vertical_deg", "rms_px",
         "seconds"]


def _draw(detector: str):
    if detector == "blazepose_fit":
        fit = load_fit(None)
        return lambda cams, scene, rng: observe_fitted(cams, scene, fit, rng)
    model = DetectorModel(noise_px=float(detector.removeprefix("gauss")))
    return lambda cams, scene, rng: observe(cams, scene, model, rng)


def one(job: dict) -> dict:
    """One graded session (a worker's task)."""
    warnings.simplefilter("ignore")  # a walk leaving a view is expected and counted
    cams = load_rig(ROOT / "configs/studios" / f"{job['rig']}.yaml").cameras_true()
    rng = np.random.default_rng([job["seed"], 977])
    offsets = np.r_[0.0, rng.uniform(-1, 1, len(cams) - 1) * job["max_offset_ms"]]
    session = Session(job["people"], job["frames"], "height", job["max_offset_frames"])
    start = time.perf_counter()
    try:
        _, errors, _ = calibrate_session(cams, offsets, session, load_body_model(),
                                         _draw(job["detector"]), [job["seed"]])
    except ValueError as e:
        return {**job, "error": str(e)}
    return {**job, **errors, "seconds": time.perf_counter() - start}


def run(jobs: list[dict], workers: int) -> list[dict]:
    """Every job's figures, in the jobs' order; each printed as it ends."""
    results = []
    with ProcessPoolExecutor(workers) as pool:
        for r in pool.map(one, jobs):
            shown = {k: round(v, 4) if isinstance(v, float) else v for k, v in r.items()}
            print(json.dumps(shown), flush=True)
            results.append(r)
    return results


def _cell(values) -> str:
    s = t_interval(values)
    if s["n"] == 0:
        return "failed"
    digits = 3 if abs(s["mean"]) < 10 else 1
    if s["n"] == 1:
        return f"{s['mean']:.{digits}f}"
    return f"{s['mean']:.{digits}f} [{s['ci_low']:.{digits}f}, {s['ci_high']:.{digits}f}]"


def table(results: list[dict], keys: list[str]) -> str:
    labels = dict(BODY_ERRORS, seconds="wall time, s")
    lines = ["| " + " | ".join(keys) + " | n | " + " | ".join(labels[k] for k in SHOWN) + " |",
             "|" + "---|" * (len(keys) + 1 + len(SHOWN))]
    groups: dict[tuple, list[dict]] = {}
    for r in results:
        groups.setdefault(tuple(r[k] for k in keys), []).append(r)
    for group, rows in groups.items():
        done = [r for r in rows if "error" not in r]
        lines.append("| " + " | ".join(map(str, group)) + f" | {len(done)}/{len(rows)} | "
                     + " | ".join(_cell([r[k] for r in done]) for k in SHOWN) + " |")
        lines += [f"|   failed: {r['error']} |" for r in rows if "error" in r]
    return "\n".join(lines)


def rendered(folders: list[str], max_offset_frames: int) -> dict:
    """The calibration from BlazePose's keypoints of rendered bodies, graded (module notes)."""
    from stereo_bench.core.camera import Camera
    from pose_eval.body_session import skeleton
    from pose_eval.body_calibration import Scale, calibrate_from_body
    from pose_eval.metrics import studio_errors
    from pose_eval.photoreal import smpl_keypoints
    from pose_eval.scene import rig_axes

    cams = [Camera.from_dict(d) for d in json.loads(
        (Path(folders[0]) / "cameras.json").read_text())]
    parts = []
    for folder in folders:
        found = [Camera.from_dict(d) for d in json.loads(
            (Path(folder) / "cameras.json").read_text())]
        if [c.to_dict() for c in found] != [c.to_dict() for c in cams]:
            raise SystemExit(f"{folder}: other cameras than {folders[0]}'s")
        found = [smpl_keypoints(np.load(Path(folder) / f"blazepose_{c.name}.npy"))
                 for c in cams]
        parts.append((np.stack([f[0] for f in found]), np.stack([f[1] for f in found])))
    pixels = np.concatenate([p[0] for p in parts], axis=1)
    confidence = np.concatenate([p[1] for p in parts], axis=1)
    segments = np.concatenate([np.full(p[0].shape[1], k) for k, p in enumerate(parts)])
    model = load_body_model()
    body, stature = skeleton("smpl24", model, 1)
    start = time.perf_counter()
    result = calibrate_from_body(cams, pixels, confidence, body, Scale(height_mm=stature),
                                 max_offset_frames, segments=segments)
    errors = studio_errors(result.cameras, cams, result.offsets_frames, np.zeros(len(cams)),
                           np.array([0.0, 0.0, 1.0]), rig_axes(cams).up)
    return {**errors, "rms_px": result.rms_px, "seconds": time.perf_counter() - start,
            "frames": int(pixels.shape[1]), "vertical_from": result.vertical,
            "mirrored_views": result.mirrored_views,
            "detected": float(np.mean(confidence > 0))}


def plot(results: list[dict], path: str) -> None:
    """The curves as a figure: per varied thing, the centre error (mm) and the worst clock
    error (frames) with 95 % intervals over the seeds."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    curves = [("frames", "frames", "session frames (BlazePose's fitted error)"),
              ("noise", "detector", "keypoint noise, px (Gaussian)"),
              ("people", "people", "people walking (BlazePose's fitted error)")]
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    for ax, (curve, key, label) in zip(axes, curves):
        rows = [r for r in results if r.get("curve") == curve and "error" not in r]
        xs = sorted({r[key] for r in rows}, key=lambda v: float(str(v).removeprefix("gauss")))
        pos = [float(str(x).removeprefix("gauss")) for x in xs]
        twin = ax.twinx()
        for axis, measure, colour, name in ((ax, "centre_mm", "C0", "centre error, mm"),
                                            (twin, "offset_frames", "C3",
                                             "clock error, frames")):
            stats = [t_interval([r[measure] for r in rows if r[key] == x]) for x in xs]
            mean = np.array([s["mean"] for s in stats])
            low = np.array([s["ci_low"] for s in stats])
            high = np.array([s["ci_high"] for s in stats])
            axis.errorbar(pos, mean, yerr=[np.nan_to_num(mean - low), np.nan_to_num(high - mean)],
                          marker="o", color=colour, capsize=3, label=name)
            axis.set_ylabel(name, color=colour)
            axis.set_ylim(bottom=0)
        ax.set_xscale("log" if curve != "people" else "linear")
        ax.set_xticks(pos, [str(x).removeprefix("gauss") for x in xs])
        ax.set_xlabel(label)
    fig.suptitle("Calibration from the body, Human3.6M-like studio: errors against the truth "
                 "(mean, 95 % interval over seeds)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("what", choices=["table", "curves", "rendered"])
    p.add_argument("bodies", nargs="*", help="rendered: the body folders")
    p.add_argument("--rigs", nargs="+", default=["h36m_rectangle", "ring8"])
    p.add_argument("--rig", default="h36m_rectangle", help="the studio of the curves")
    p.add_argument("--people", nargs="+", type=int, default=[1, 2])
    p.add_argument("--detectors", nargs="+", default=["gauss1", "blazepose_fit"])
    p.add_argument("--seeds", type=int, default=5)
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--max-offset-ms", type=float, default=60.0)
    p.add_argument("--max-offset-frames", type=int, default=10)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--json", help="write every session's figures here")
    p.add_argument("--plot", help="curves: draw them into this PNG")
    args = p.parse_args()
    base = {"frames": args.frames, "max_offset_ms": args.max_offset_ms,
            "max_offset_frames": args.max_offset_frames}
    if args.what == "rendered":
        print(json.dumps(rendered(args.bodies, args.max_offset_frames), indent=1))
        return
    if args.what == "table":
        jobs = [{**base, "rig": rig, "people": n, "detector": d, "seed": s}
                for rig in args.rigs for n in args.people for d in args.detectors
                for s in range(args.seeds)]
        keys = ["rig", "people", "detector"]
    else:
        start = {**base, "rig": args.rig, "people": 1, "detector": "blazepose_fit"}
        jobs = [{**start, "curve": "frames", "frames": f, "seed": s}
                for f in (100, 300, 1000) for s in range(args.seeds)]
        jobs += [{**start, "curve": "noise", "detector": f"gauss{n}", "seed": s}
                 for n in (1, 3, 10) for s in range(args.seeds)]
        jobs += [{**start, "curve": "people", "people": n, "seed": s}
                 for n in (1, 2, 3) for s in range(args.seeds)]
        keys = ["curve", "frames", "detector", "people"]
    began = time.perf_counter()
    results = run(jobs, args.workers)
    print(table(results, keys))
    print(f"\n{len(jobs)} sessions in {time.perf_counter() - began:.0f} s on {args.workers} "
          f"worker(s)")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
    if args.plot and args.what == "curves":
        plot(results, args.plot)


if __name__ == "__main__":
    main()
