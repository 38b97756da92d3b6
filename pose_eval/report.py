"""pose-eval's report: mean ± std over trials, tables in the layout of the paper's Table 5, plots.

Table 5 has one row per rig and environment and one column per calibration method; here every
table also carries the ``gt`` column, the same keypoints triangulated through the TRUE cameras:
the floor that keypoint noise alone leaves. Table 5 redone leads the report: per method, its
MPJPE beside the floor and its cost (MPJPE minus gt's on the same keypoints of the same trial,
pose_eval.metrics.excess_mpjpe) with the cost's spread over trials: mean, std, min and max.
"""

from __future__ import annotations

import math

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402 (after choosing the headless backend)
import numpy as np  # noqa: E402

from stereo_bench.report.markdown import summarize  # noqa: E402
from stereo_bench.run.sweep_stats import t_interval  # noqa: E402

from .motion import JOINT_NAMES, PARENTS  # noqa: E402

COST, FLOOR = "excess_mpjpe_mm", "gt_mpjpe_mm"  # paired with gt in each trial (cli.evaluate_trial)
BODY = "body"  # the method name of the calibration from the body (pose_eval.body_session)
#: The calibration from the body's errors against the truth (metrics.studio_errors), as reported.
BODY_ERRORS = [("rotation_deg", "rotation, deg (mean over cameras)"),
               ("rotation_deg_max", "rotation, deg (worst camera)"),
               ("centre_mm", "centre, mm (mean over cameras)"),
               ("centre_mm_max", "centre, mm (worst camera)"),
               ("scale_pct", "scale, %"),
               ("offset_frames", "clock, frames (worst camera)"),
               ("vertical_deg", "vertical, deg"),
               ("rms_px", "reprojection RMS, px (inliers)")]
MEASURES = [("mpjpe_mm", "MPJPE (standard) mm"),
            (COST, "Cost of the calibration: MPJPE minus gt's, same keypoints, mm"),
            (FLOOR, "gt's MPJPE in the trials the method succeeded in, mm"),
            ("paper_mpjpe_mm", "MPJPE (paper's formula) mm"),
            ("pa_mpjpe_mm", "PA-MPJPE mm")]
STAGES = [("triangulated", "triangulated"), ("fitted", "SMPL fit")]


def spread(values: list[float]) -> dict:
    """summarize's mean, std and n over the finite values, with their min and max (NaN when
    there are none): how far apart trials fall, which a std over 2-3 trials hardly tells."""
    finite = [v for v in values if math.isfinite(v)]
    return {**summarize(finite), "min": min(finite, default=math.nan),
            "max": max(finite, default=math.nan)}


def aggregate(trials: list[dict]) -> dict:
    """Summaries of one method over its trials (each {"triangulated": pose_metrics, ["fitted":
    pose_metrics]} or {"error": message}).

    Returns {stage: {measure: spread, "per_joint_mm": {joint: summary}, "missing_joints":
    total}, "failures": [messages], "trials": n}.
    """
    done = [t for t in trials if "error" not in t]
    agg = {"trials": len(trials), "failures": [t["error"] for t in trials if "error" in t]}
    for stage, _ in STAGES:
        entries = [t[stage] for t in done if stage in t]
        if not entries and stage != "triangulated":
            continue
        agg[stage] = {key: spread([e.get(key, math.nan) for e in entries])
                      for key, _ in MEASURES}
        agg[stage]["per_joint_mm"] = {
            j: summarize([e["per_joint_mm"][j] for e in entries]) for j in JOINT_NAMES}
        agg[stage]["missing_joints"] = sum(e["missing_joints"] for e in entries)
        agg[stage]["total_joints"] = sum(e["total_joints"] for e in entries)
    return agg


def body_summary(session, offsets_ms, errors: list[dict]) -> dict:
    """The calibration from the body over the trials: its settings, each error's mean and 95 %
    interval (sweep_stats.t_interval) over the trials it succeeded in, and its failures."""
    done = [e for e in errors if "error" not in e]
    return {"session": {"people": session.people, "frames": session.frames,
                        "scale": session.scale, "max_offset_frames": session.max_offset_frames,
                        "time_offset_ms": None if offsets_ms is None else
                        [float(v) for v in offsets_ms]},
            "errors": {k: t_interval([e[k] for e in done]) for k, _ in BODY_ERRORS},
            "vertical_from_floor": int(sum(e["vertical_from_floor"] for e in done)),
            "trials": len(errors), "failures": [e["error"] for e in errors if "error" in e]}


def _mean_interval(s: dict) -> str:
    if s["n"] == 0:
        return "failed"
    if s["n"] == 1:
        return f"{s['mean']:.3f}"
    return f"{s['mean']:.3f} [{s['ci_low']:.3f}, {s['ci_high']:.3f}]"


def body_lines(body: dict) -> list[str]:
    """The calibration from the body's section of the report."""
    s = body["session"]
    ok = body["trials"] - len(body["failures"])
    lines = ["## Calibration from the body", "",
             f"The studio calibrated with no board, from {s['people']} "
             f"{'person' if s['people'] == 1 else 'people'} walking for {s['frames']} frames "
             f"(method `{BODY}` in the tables above), scale from the "
             f"{'person height' if s['scale'] == 'height' else 'baseline of cameras 0 and 1'}, "
             f"clocks searched over +-{s['max_offset_frames']} frames"
             + (f", true offsets {s['time_offset_ms']} ms" if s["time_offset_ms"] else "")
             + f". Errors against the truth after a similarity alignment, mean [95 % interval] "
             f"over {ok} of {body['trials']} trial(s); the vertical came from the floor in "
             f"{body['vertical_from_floor']} of them (else from the body's axis).", "",
             "| error | value |", "|---|---|"]
    lines += [f"| {label} | {_mean_interval(body['errors'][k])} |" for k, label in BODY_ERRORS]
    return lines + [""]


def fmt(s: dict) -> str:
    if s["n"] == 0:
        return "failed"
    return f"{s['mean']:.3f}" if s["n"] == 1 else f"{s['mean']:.3f} ± {s['std']:.3f}"


def headline_stage(results: dict) -> str:
    return "fitted" if results["settings"]["fit_smpl"] else "triangulated"


def cost_table(results: dict, stage: str) -> list[str]:
    """Table 5 redone, one row per method: its MPJPE and gt's (the floor) over the trials where
    it succeeded, and its cost's mean, std, min and max over them (one trial has no spread, and
    says so)."""
    methods = results["methods"]
    lines = ["| Method | MPJPE mm | gt floor mm | Cost mm | Cost std | Cost min | Cost max "
             "| Trials |", "|---|---|---|---|---|---|---|---|"]
    for name, m in methods.items():
        if stage not in m:
            lines.append(f"| {name} | failed | | | | | | 0 of {m['trials']} |")
            continue
        mpjpe, floor, cost = (m[stage][k] for k in ("mpjpe_mm", FLOOR, COST))
        cells = [fmt(mpjpe), fmt(floor)]
        if name == "gt":
            cells += ["0 (the floor)", "", "", ""]
        elif cost["n"] == 0:
            cells += ["failed", "", "", ""]
        elif cost["n"] == 1:
            cells += [f"{cost['mean']:+.3f}", "no spread: 1 trial", "", ""]
        else:
            cells += [f"{cost[k]:+.3f}" if k != "std" else f"{cost[k]:.3f}"
                      for k in ("mean", "std", "min", "max")]
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {cost['n']} of {m['trials']} |")
    return lines


def markdown(results: dict) -> str:
    """The report: settings, Table 5 redone (costs), Table-5 tables per measure, per-joint
    errors, counts, failures."""
    s, methods = results["settings"], results["methods"]
    names = list(methods)
    rig, env = results["rig"], results["environment"]
    stages = [(k, label) for k, label in STAGES if any(k in m for m in methods.values())]
    where = (f"body at the point the cameras look at, {s['distance_mm']:.0f} mm from them on "
             f"average (they surround it), facing camera 0" if s.get("surrounded") else
             f"body at {s['distance_mm']:.0f} mm from the rig")
    lines = [
        f"# pose-eval: {rig} ({env})", "",
        f"Motion `{s['motion']}`, {s['frames']} frames, {where}; keypoints: {s['keypoints']}; "
        f"triangulation: "
        f"{'robust (outlier views rejected)' if s['robust'] else 'weighted DLT + ML refinement'}"
        f"{'; then an SMPL fit' if s['fit_smpl'] else ''}. "
        f"Mean ± std over {s['trials']} trial(s).",
        "",
        "`gt` triangulates the same keypoints through the true cameras: the floor that the "
        "keypoints alone leave. Standard MPJPE averages the joint errors; the paper's formula "
        "takes per frame the root of the SUM of squared joint errors (about sqrt(24) = 4.9x "
        "larger). PA-MPJPE aligns each frame by a similarity transform first. The cost of a "
        "calibration is its MPJPE minus gt's in the same trial (same keypoints, the joints both "
        "reconstructed), so keypoint noise common to both cancels.", ""]
    lines += [f"**Warning:** {w}" for w in results.get("warnings", [])]
    lines += [""] if results.get("warnings") else []
    for stage, label in stages:
        lines += [f"## The cost of each calibration ({label}): Table 5 redone, {rig} ({env})",
                  ""] + cost_table(results, stage) + [""]
    if "body_calibration" in results:
        lines += body_lines(results["body_calibration"])
    for key, title in MEASURES:
        if key in (COST, FLOOR):  # in Table 5 redone above, paired, with the spread
            continue
        lines += [f"## {title}", "",
                  "| Cameras | Environment | Stage | " + " | ".join(names) + " |",
                  "|---|---|---|" + "---|" * len(names)]
        for stage, label in stages:
            cells = [fmt(m[stage][key]) if stage in m else "failed" for m in methods.values()]
            lines.append(f"| {rig} | {env} | {label} | " + " | ".join(cells) + " |")
        lines.append("")
    stage = headline_stage(results)
    lines += [f"## Per joint ({dict(STAGES)[stage]}), mean error mm", "",
              "| joint | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
    for j in JOINT_NAMES:
        cells = [fmt(m[stage]["per_joint_mm"][j]) if stage in m else "failed"
                 for m in methods.values()]
        lines.append(f"| {j} | " + " | ".join(cells) + " |")
    detector = results.get("detector_2d")
    if detector:
        lines += ["", "## The 2D detector against the projected true joints", "",
                  "BlazePose's landmarks mapped to SMPL's joints (pose_eval/photoreal.py), px over "
                  "the joint views it detected. Part of this is the gap between the two joint "
                  "definitions, which the gt row above carries too. The spine and collar joints have no "
                  "BlazePose landmark: never detected, they count as missing in every row.", "",
                  "| joint | detected | of | mean px | median px |", "|---|---|---|---|---|"]
        for j, row in detector.items():
            mean = "-" if row["mean_px"] is None else f"{row['mean_px']:.1f}"
            median = "-" if row["median_px"] is None else f"{row['median_px']:.1f}"
            lines.append(f"| {j} | {row['detected']} | {row['views']} | {mean} | {median} |")
    lines += ["", "## Counts", "",
              "| method | missing joints | of |", "|---|---|---|"]
    for name, m in methods.items():
        if stage in m:
            lines.append(f"| {name} | {m[stage]['missing_joints']} | {m[stage]['total_joints']} |")
    d = results["detections"]
    lines += ["", "Keypoint views over all trials: " + ", ".join(
        f"{k} {v}" for k, v in d.items() if k != "under_two_views") + "."]
    under = results.get("under_two_views", {})
    if under:
        lines += ["", "Joints detected by fewer than two cameras, not triangulated (frames over "
                  "all trials, counted in the missing joints): " + ", ".join(
                      f"{j} {n}" for j, n in under.items()) + "."]
    failures = [f"- {name}: {msg}" for name, m in methods.items() for msg in m["failures"]]
    if failures:
        lines += ["", "## Failures", ""] + failures
    return "\n".join(lines) + "\n"


def plot_mpjpe(results: dict, path) -> None:
    """What each calibration costs: left, the floor (gt's MPJPE, the keypoints alone); right,
    each method's cost (its MPJPE minus gt's on the same keypoints of the same trial) as its
    mean with every trial's value, on a log scale when the costs differ by decades."""
    stage = headline_stage(results)
    methods = {n: m for n, m in results["methods"].items() if n != "gt"}
    floor = results["methods"].get("gt", {}).get(stage, {}).get("mpjpe_mm", {})
    fig, (left, right) = plt.subplots(1, 2, figsize=(2.6 + 1.1 * max(len(methods), 1), 3.6),
                                      gridspec_kw={"width_ratios": [1, max(len(methods), 1)]})
    left.bar([0], [floor.get("mean", math.nan)], color="0.6")
    left.bar_label(left.containers[0], labels=[f"{floor.get('mean', math.nan):.1f}"],
                   fontsize=8)
    left.set_xticks([0], ["gt"])
    left.set_ylabel(f"MPJPE mm ({dict(STAGES)[stage]})")
    left.set_title("floor: true cameras", fontsize=9)
    names = list(methods)
    means, trial_costs = [], []
    for name, m in methods.items():
        means.append(m.get(stage, {}).get(COST, {}).get("mean", math.nan))
        entries = [t["methods"].get(name, {}) for t in results.get("trials", [])]
        trial_costs.append([e[stage][COST] for e in entries
                            if stage in e and e[stage].get(COST) is not None])
    x = np.arange(len(names))
    shown = np.abs(np.array(means, float))
    if names:
        bars = right.bar(x, shown, color="C0", alpha=0.8)
        right.bar_label(bars, labels=[f"{v:+.3g}" for v in means], fontsize=8)
        for i, costs in enumerate(trial_costs):
            right.plot(np.full(len(costs), x[i]), np.abs(costs), "k.", ms=4,
                       label="each trial" if i == 0 and costs else None)
        positive = shown[np.isfinite(shown) & (shown > 0)]
        if len(positive) > 1 and positive.max() >= 10 * positive.min():
            right.set_yscale("log")
        right.margins(y=0.2)
        if any(trial_costs):
            right.legend(fontsize=7)
    right.set_xticks(x, names, rotation=20)
    right.set_ylabel("|cost| mm (MPJPE minus gt's, paired)")
    right.set_title("each calibration's cost", fontsize=9)
    fig.suptitle(f"{results['rig']} ({results['environment']}), "
                 f"{results['settings']['trials']} trial(s)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_skeleton(truth: np.ndarray, estimate: np.ndarray, path, title: str) -> None:
    """Truth and estimate of one frame (24, 3) mm, drawn along SMPL's kinematic tree.

    Coordinates are taken as (right, depth, up), e.g. the rig's axes (pose_eval.scene.rig_axes).
    """
    fig = plt.figure(figsize=(5, 5))
    ax = fig.add_subplot(projection="3d")
    for joints, style, label in ((truth, "k-", "truth"), (estimate, "r--", "estimate")):
        for j, p in enumerate(PARENTS[1:], start=1):
            seg = joints[[p, j]]
            ax.plot(*seg.T, style, lw=1.5, label=label if j == 1 else None)
    centre, half = truth.mean(0), np.ptp(truth, axis=0).max() / 2 + 50
    ax.set(xlim=(centre[0] - half, centre[0] + half), ylim=(centre[1] - half, centre[1] + half),
           zlim=(centre[2] - half, centre[2] + half), xlabel="right mm", ylabel="depth mm",
           zlabel="up mm", title=title)
    ax.set_box_aspect((1, 1, 1))  # equal scales: bones keep their lengths on the page
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
