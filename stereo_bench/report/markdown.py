"""Tables from metrics: mean ± std over trials, in the layout of the paper's Tables 2 and 3.

A single number cannot tell 0.49 px from 0.51 px, so every figure is aggregated over the
trials (re-renders with different seeds) it was measured on, and printed as mean ± std.
"""

from __future__ import annotations

import math
from pathlib import Path

import json

import numpy as np

from ..io.rundir import RunPaths
from ..core.files import write_json, write_text

# (column title, path into one calibration entry)
CALIBRATION_COLUMNS = [
    ("RPE_RMS px", ("rpe_rms_px",)),
    ("paper RMSE", ("paper_rmse",)),
    ("proj. diff mean px", ("projection_difference", "mean_px")),
    ("proj. diff max px", ("projection_difference", "max_px")),
    ("rot.-comp. diff mean px", ("projection_difference", "rotation_compensated_mean_px")),
    ("valid image fraction", ("validity", "valid_fraction")),
    ("fx err px", ("parameter_errors", "fx")),
    ("fy err px", ("parameter_errors", "fy")),
    ("cx err px", ("parameter_errors", "cx")),
    ("cy err px", ("parameter_errors", "cy")),
    ("k1 err", ("parameter_errors", "k1")),
    ("board rot. err deg", ("board_pose", "rotation_deg_mean")),
    ("board transl. err mm", ("board_pose", "translation_mm_mean")),
    ("time s", ("wall_time_s",)),
]
RIG_COLUMNS = [
    ("RMSE_cal mm", ("rmse_cal_mm",)),
    ("centre RMSE mm", ("centre_rmse_mm",)),
    ("max error mm", ("max_error_mm",)),
    ("rel. rotation err deg", ("rig_errors", "rotation_deg")),
    ("rel. translation err mm", ("rig_errors", "translation_mm")),
    ("baseline err mm", ("rig_errors", "baseline_mm")),
    ("centre err mm", ("rig_errors", "centre_mm")),
    ("stereo RMS px", ("rms_px",)),
]
# Per camera of a rig: errors with the reference camera fixed, then after a similarity alignment.
RIG_CAMERA_COLUMNS = [
    ("rotation err deg", ("camera_errors", "rotation_deg")),
    ("centre err mm", ("camera_errors", "centre_mm")),
    ("aligned rotation err deg", ("aligned", "rotation_deg")),
    ("aligned centre err mm", ("aligned", "centre_mm")),
    ("RMS px", ("camera_errors", "rms_px")),
]
# compare-tools: (key of run/compare.seed_figures, title, unit), in the table's order.
COMPARE_FIGURES = [("focal_error_px", "focal length error", "px"),
                   ("principal_point_error_px", "principal point error", "px"),
                   ("projection_difference_mean_px", "projection diff. mean", "px"),
                   ("projection_difference_max_px", "projection diff. max", "px"),
                   ("rmse_cal_mm", "RMSE_cal", "mm"),
                   ("centre_error_mm", "camera centre error", "mm"),
                   ("rotation_error_deg", "camera rotation error", "deg"),
                   ("aligned_centre_error_mm", "centre error, aligned", "mm"),
                   ("time_s", "time", "s")]

DETECTION_COLUMNS = [
    ("rate", ("detection_rate",)),
    ("mean px", ("mean_px",)),
    ("RMS px", ("rms_px",)),
    ("max px", ("max_px",)),
    ("signed mean x px", ("mean_dx_px",)),
    ("signed mean y px", ("mean_dy_px",)),
    ("flips", ("flips",)),
]


def _get(entry: dict, path: tuple) -> float:
    """The number at ``path``; for a per-camera list (rig errors of cameras 1..C-1), the one of
    largest magnitude, i.e. the worst camera."""
    for key in path:
        if not isinstance(entry, dict) or key not in entry:
            return math.nan
        entry = entry[key]
    if isinstance(entry, list) and entry:
        entry = max(entry, key=abs)
    return float(entry) if isinstance(entry, (int, float)) else math.nan


def summarize(values: list[float]) -> dict:
    """mean, std (ddof=1 when n > 1) and n over the finite values (a value strict JSON wrote as
    null, for one that was not a number, is not one)."""
    v = np.array([x for x in values if isinstance(x, (int, float)) and np.isfinite(x)])
    if len(v) == 0:
        return {"mean": math.nan, "std": math.nan, "n": 0}
    return {"mean": float(v.mean()), "std": float(v.std(ddof=1)) if len(v) > 1 else 0.0,
            "n": int(len(v))}


def aggregate(trials: list[dict]) -> dict:
    """Mean ± std of every table figure over trials (each a metrics.json of evaluate_dataset).

    Returns {"detection": {camera: {column: summary}}, "calibration": {method: {camera:
    {column: summary, "failures": [messages]}}}}.
    """
    first = trials[0]
    agg = {"trials": len(trials), "detection": {}, "calibration": {}}
    for cam in first["cameras"]:
        agg["detection"][cam] = {title: summarize([_get(t["detection"][cam], path)
                                                   for t in trials])
                                 for title, path in DETECTION_COLUMNS}
    for m in first["methods"]:
        agg["calibration"][m] = {}
        for cam in first["cameras"]:
            entries = [t["calibration"][m][cam] for t in trials]
            row = {title: summarize([_get(e, path) for e in entries])
                   for title, path in CALIBRATION_COLUMNS}
            row["failures"] = [e["error"] for e in entries if "error" in e]
            row["not_valid_everywhere"] = sum(
                1 for e in entries if e.get("validity", {}).get("usable") is False)
            agg["calibration"][m][cam] = row
    if first.get("rig"):
        agg["rig"] = {}
        for m in first["methods"]:
            entries = [t["rig"][m] for t in trials]
            row = {title: summarize([_get(e, path) for e in entries]) for title, path in RIG_COLUMNS}
            row["failures"] = [e["error"] for e in entries if "error" in e]
            row["notes"] = sorted({e["note"] for e in entries if "note" in e})
            agg["rig"][m] = row
        if len(first["cameras"]) > 2:
            agg.update(_studio(trials))
    rig_entries = [e for e in first.get("rig", {}).values() if "settings" in e]
    agg["calibration_settings"] = {"intrinsics_views": first.get("intrinsics_views", "all"),
                                   **(rig_entries[0]["settings"] if rig_entries else {})}
    agg["warnings"] = sorted({w for t in trials for w in t.get("warnings", [])})
    agg["notes"] = [n for t in trials for n in t.get("notes", [])]
    agg["timing"] = {k: summarize([t.get("timing", {}).get(k, math.nan) for t in trials])
                     for k in ("render_s", "detect_s", "calibrate_s", "rig_s")}
    return agg


def _header(*titles: str) -> list[str]:
    """A Markdown table's header and separator lines."""
    return ["| " + " | ".join(titles) + " |", "|" + "---|" * len(titles)]


def _titles(columns: list) -> list[str]:
    return [t for t, _ in columns]


def _camera_value(entry: dict, cam: str, path: tuple) -> float:
    group, key = path
    block = entry.get(group) or {}
    if group == "aligned":
        block = block.get("cameras", {})
    value = block.get(cam, {}).get(key)
    return math.nan if value is None else float(value)


def _studio(trials: list[dict]) -> dict:
    """For rigs of 3+ cameras: per camera and method the rig's errors (RIG_CAMERA_COLUMNS), the
    RMSE_cal per shell of distance from the volume's centre, and the covisibility of the first
    trial (frames each pair of cameras saw together, from the detections)."""
    first = trials[0]
    out = {"rig_cameras": {}, "rig_regions": {}, "covisibility": None}
    for m in first["methods"]:
        entries = [t["rig"][m] for t in trials if "error" not in t["rig"][m]]
        if not entries:
            continue
        out["rig_cameras"][m] = {
            cam: {title: summarize([_camera_value(e, cam, path) for e in entries])
                  for title, path in RIG_CAMERA_COLUMNS} for cam in first["cameras"]}
        shells = {(r["from_mm"], r["to_mm"]): [] for e in entries
                  for r in e.get("rmse_cal_by_region", [])}
        for e in entries:
            for r in e.get("rmse_cal_by_region", []):
                shells[(r["from_mm"], r["to_mm"])].append(r["rmse_cal_mm"])
        out["rig_regions"][m] = [{"from_mm": lo, "to_mm": hi, "rmse_cal_mm": summarize(v)}
                                 for (lo, hi), v in sorted(shells.items())]
        if out["covisibility"] is None:
            out["covisibility"] = {"cameras": first["cameras"],
                                   "frames": entries[0]["log"]["covisibility"]}
    return out


def _studio_markdown(agg: dict) -> list[str]:
    lines = ["", "## Per camera of the rig", "",
             "Errors of each camera's pose in the reference camera's frame, then after the "
             "similarity that best maps the estimated camera centres onto the true ones (what "
             "is left once the choice of reference and the scale are forgiven), beside the "
             "reprojection error: a low RMS px does not mean a right geometry.", "",
             *_header("camera", "method", *_titles(RIG_CAMERA_COLUMNS))]
    for m, cams in agg["rig_cameras"].items():
        for cam, row in cams.items():
            lines.append(f"| {cam} | {m} | "
                         + " | ".join(fmt(row[t]) for t, _ in RIG_CAMERA_COLUMNS) + " |")
    shells = sorted({(r["from_mm"], r["to_mm"]) for rows in agg["rig_regions"].values()
                     for r in rows}, key=lambda s: s[0])
    if shells:
        def label(lo, hi):
            return f"{lo / 1000:g}-{hi / 1000:g} m" if hi is not None else f">{lo / 1000:g} m"
        lines += ["", "RMSE_cal (mm) by distance of the board's points from the volume's "
                  "centre:", "", *_header("method", *(label(*s) for s in shells))]
        for m, rows in agg["rig_regions"].items():
            by = {(r["from_mm"], r["to_mm"]): r["rmse_cal_mm"] for r in rows}
            lines.append(f"| {m} | " + " | ".join(
                fmt(by[s]) if s in by else "-" for s in shells) + " |")
    cov = agg.get("covisibility")
    if cov:
        names = cov["cameras"]
        lines += ["", "Frames the rig calibration has of each pair of cameras together: the "
                  "board detected by both in a usable view (at least 8 points, not on a line) "
                  "with a pose through each camera's estimate (diagonal: per camera; first "
                  "trial, first method):", "",
                  *_header("", *names)]
        for name, row in zip(names, cov["frames"]):
            lines.append(f"| {name} | " + " | ".join(str(v) for v in row) + " |")
    return lines


def fmt(s: dict, digits: int = 3) -> str:
    if s["n"] == 0:
        return "failed"
    if s["n"] == 1:
        return f"{s['mean']:.{digits}g}"
    return f"{s['mean']:.{digits}g} ± {s['std']:.2g}"


def markdown(agg: dict, title: str) -> str:
    """Detection table plus the calibration table (rows: camera x method)."""
    settings = agg.get("calibration_settings", {})
    said = f"intrinsics from {settings.get('intrinsics_views', 'all')} views"
    if "loss" in settings:
        said += (f"; rig bundle adjustment: {settings['loss']} loss"
                 + (f" (scale {settings['loss_scale_px']:g} px)" if settings["loss"] != "linear"
                    else "")
                 + (", intrinsics refined" if settings["refine_intrinsics"] else
                    ", intrinsics fixed"))
    lines = [f"# {title}", "", f"Mean ± std over {agg['trials']} trial(s). Calibration: {said}.",
             "",
             "## Detection against ground truth", "",
             *_header("camera", *_titles(DETECTION_COLUMNS))]
    for cam, row in agg["detection"].items():
        lines.append(f"| {cam} | " + " | ".join(fmt(row[t]) for t, _ in DETECTION_COLUMNS) + " |")
    lines += ["", "## Calibration against ground truth (layout of the paper's Tables 2 and 3)", "",
              "`paper RMSE` is the paper's RMSE over [fx, fy, cx, cy, k1..k6]: it mixes pixels with "
              "unitless coefficients, so compare it only with the paper. `proj. diff` is how far "
              "the estimate projects the true camera's rays over the whole image, the error a "
              "user of the calibration sees.", "",
              *_header("camera", "method", *_titles(CALIBRATION_COLUMNS))]
    failures, invalid = [], []
    for m, cams in agg["calibration"].items():
        for cam, row in cams.items():
            bad = row.get("not_valid_everywhere", 0)
            mark = " (folds) †" if bad else ""
            # A figure missing from every trial without a failure does not apply (the lens
            # parameters of a lens model other than the true one's): "–", not "failed".
            lines.append(f"| {cam} | {m}{mark} | "
                         + " | ".join(fmt(row[t]) if row[t]["n"] or row["failures"] else "–"
                                      for t, _ in CALIBRATION_COLUMNS) + " |")
            failures += [f"- {cam} / {m}: {msg}" for msg in row["failures"]]
            if bad:
                invalid.append(f"- {cam} / {m}: in {bad} of {agg['trials']} trial(s) the "
                               f"estimate folds or has a pole inside the image (valid over "
                               f"{fmt(row['valid image fraction'])} of it); its projection "
                               f"difference covers only the valid part")
    if invalid:
        lines += ["", "† Estimates that cannot be used over the whole image:", ""] + invalid
    if "rig" in agg:
        lines += ["", "## Rig calibration and triangulation (layout of the paper's Table 4)", "",
                  "RMSE_cal: the board's feature points triangulated through each method's "
                  "calibrated rig against their true positions in the reference camera's frame. "
                  "Rig errors are of the worst non-reference camera.", "",
                  *_header("method", *_titles(RIG_COLUMNS))]
        for m, row in agg["rig"].items():
            lines.append(f"| {m} | " + " | ".join(fmt(row[t]) for t, _ in RIG_COLUMNS) + " |")
            failures += [f"- rig / {m}: {msg}" for msg in row["failures"]]
        rig_notes = [f"- {m}: {n}" for m, row in agg["rig"].items() for n in row.get("notes", [])]
        if rig_notes:
            lines += [""] + rig_notes
        if agg.get("rig_cameras"):
            lines += _studio_markdown(agg)
    if failures:
        lines += ["", "## Failures", ""] + failures
    if agg.get("warnings"):
        lines += ["", "## Warnings about the data", ""] + [f"- {w}" for w in agg["warnings"]]
    if agg.get("notes"):
        lines += ["", "## Stages redone in this run", ""] + [f"- {n}" for n in agg["notes"]]
    timing = agg.get("timing", {})
    if timing:
        lines += ["", "Stage times (s per trial): " + ", ".join(
            f"{k[:-2]} {fmt(v)}" for k, v in timing.items() if v["n"])]
    return "\n".join(lines) + "\n"


def run_title(cfg) -> str:
    return f"{cfg.name}: {cfg.pattern.kind}, {cfg.environment.kind}"


def write_report(out: Path, trials: list[dict], title: str) -> dict:
    """RUN/results.json (every number, strict JSON) and RUN/report.md; returns the aggregate."""
    run = RunPaths(out)
    agg = aggregate(trials)
    write_json(run.results, {"aggregate": agg, "trials": trials})
    write_text(run.report, markdown(agg, title))
    return agg


# ----------------------------------------------------------------------------------------------
# A real capture (capture.py): what can be known without ground truth
# ----------------------------------------------------------------------------------------------

def _num(value, digits: int = 3) -> str:
    return "–" if not isinstance(value, (int, float)) or not math.isfinite(value) \
        else f"{value:.{digits}g}" if abs(value) >= 1e4 else f"{value:.{digits}f}"


def _std(entry: dict, name: str) -> str:
    unc = entry.get("uncertainty", {}).get("parameters")
    if not unc or name not in unc.get("values", {}):
        return "–"
    s = unc["std"].get(name)
    return f"{unc['values'][name]:.2f} ± {_num(s, 2) if s is not None else 'inf'}"


def _capture_camera_rows(results: dict, cam: str) -> list[str]:
    lines = _header("method", "RPE px", "held-out px", "held-out / RPE", "flagged views",
                    "flagged points", "residual correlation (null, p)", "valid image",
                    "proj. σ centre px",
                    "proj. σ worst px", "fx", "fy", "cx", "cy")
    for m in results["methods"]:
        e = results["calibration"][m].get(cam, {})
        if "error" in e:
            lines.append(f"| {m} | failed: {e['error']} |" + " |" * 12)
            continue
        h, d = e.get("heldout", {}), e.get("diagnostics", {})
        proj = e.get("uncertainty", {}).get("projection", {})
        rnd = d.get("randomness", {})
        # A statistic beside its null, not a yes/no: on real images nearly every camera's
        # residuals are correlated (a detector bias, a lens between models), so the verdict
        # alone would say the same of all of them; the size tells them apart.
        random_ = ("–" if "p_value" not in rnd else
                   f"{rnd['statistic']:.2f} ({rnd['null_mean']:.2f}, {rnd['p_value']:.3f})")
        views = h.get("views", [])
        scored = sum(v.get("heldout_rms_px") is not None for v in views)
        # Held out over fewer views than the fit (a fold failed) is not the same figure.
        some = f" ({scored}/{len(views)} views)" if scored < len(views) else ""
        lines.append(
            f"| {m} | {_num(e.get('rpe_rms_px'), 4)} | {_num(h.get('heldout_rms_px'), 4)}{some} | "
            f"{_num(h.get('ratio'), 3)} | {len(d.get('views', {}).get('flagged', []))} | "
            f"{len(d.get('points', {}).get('flagged', []))} | {random_} | {_num(e['validity']['valid_fraction'] * 100, 1)} % | "
            f"{_num(proj.get('centre_px'), 3)} | {_num(proj.get('worst_px'), 3)} | "
            + " | ".join(_std(e, n) for n in ("fx", "fy", "cx", "cy")) + " |")
    return lines


def _agreement_rows(rows: list[dict]) -> list[str]:
    lines = _header("methods", "mean px", "max px", "after best rotation: mean px", "max px",
                    "rotation deg")
    for r in rows:
        if "error" in r:
            lines.append(f"| {' – '.join(r['methods'])} | {r['error']} | | | | |")
            continue
        lines.append(f"| {' – '.join(r['methods'])} | {_num(r['mean_px'])} | {_num(r['max_px'])}"
                     f" | {_num(r['rotation_compensated_mean_px'])} | "
                     f"{_num(r['rotation_compensated_max_px'])} | {_num(r['rotation_deg'])} |")
    return lines


def _capture_rig_rows(results: dict) -> list[str]:
    cams = [c["name"] for c in results["cameras"]]
    lines = _header("method", "RMS px", "camera", "baseline mm", "rotation deg",
                    "board shape RMSE mm", "board scale error %", "OpenCV baseline mm",
                    "OpenCV rotation deg", "difference deg", "difference mm")
    for m, e in results["rig"].items():
        if "error" in e:
            lines.append(f"| {m} | not reported: {e['error']} |" + " |" * 9)
            continue
        ref = e.get("opencv_multiview", {})
        geo = e["board_geometry"]
        for cam in cams:
            if cam == e["reference"]:
                continue
            if cam in e.get("left_out", {}):
                lines.append(f"| {m} | | {cam} | left out: no estimate |" + " |" * 7)
                continue
            r = ref.get("cameras", {}).get(cam, {})
            theirs = (f"{_num(r.get('baseline_mm'))} | {_num(r.get('rotation_deg'))} | "
                      f"{_num(r.get('difference_rotation_deg'))} | "
                      f"{_num(r.get('difference_centre_mm'))}") if r else \
                f"{ref.get('error', '–')} | | |"
            lines.append(f"| {m} | {_num(e['rms_px'])} | {cam} | {_num(e['baseline_mm'][cam])} | "
                         f"{_num(e['rotation_deg'][cam])} | {_num(geo['rmse_mm'])} | "
                         f"{_num(geo['scale_error_pct'])} | {theirs} |")
    return lines


def capture_markdown(results: dict, title: str) -> str:
    """report.md of a real capture (capture.calibrate_capture's results)."""
    names = [c["name"] for c in results["cameras"]]
    p = results["pattern"]
    lines = [f"# {title}", "",
             f"{len(names)} camera(s) ({', '.join(names)}), {results['frames']} frames, board "
             f"{p['kind']} ({', '.join(f'{k} {v}' for k, v in p.items() if k != 'kind')}). "
             "There is no ground truth: every figure below comes from the images alone.", "",
             "## Detection", ""]
    lines += _header("camera", "frames found", "views left out", "first failure")
    for cam in names:
        d = results["detection"][cam]
        left = d["views_left_out"]
        first = next(iter(d["errors"].items()), None)
        lines.append(f"| {cam} | {d['found']} / {d['frames']} | "
                     f"{len(left) if isinstance(left, dict) else left} | "
                     f"{f'{first[0]}: {first[1]}' if first else '–'} |")
    lines += ["", "## Each camera", "",
              "RPE: the RMS reprojection error of the views the estimate was fitted to. Held-out: "
              "k-fold cross-validation over views, each held-out view's pose fitted with the "
              "trained intrinsics fixed. Residual correlation: the correlation of neighbouring "
              "points' residuals, beside its mean under the null (residuals that are noise) and "
              "its Monte Carlo p-value; well above its null, the residuals are not noise (a "
              "lens model too simple, a bent board or a detector bias). Projection σ: mrcal's "
              "mean-frames projection uncertainty (1σ of the worst direction) at the median "
              "board distance. Values are ± 1σ from the calibration's own covariance.", ""]
    for cam in names:
        cov = next((results["calibration"][m][cam]["diagnostics"]["coverage"]
                    for m in results["methods"]
                    if "diagnostics" in results["calibration"][m].get(cam, {})), None)
        lines += [f"### {cam}", ""]
        if cov:
            lines += [f"Features cover {cov['cell_fraction'] * 100:.0f} % of a "
                      f"{cov['grid'][0]} x {cov['grid'][1]} grid of the image; their convex hull "
                      f"{cov['hull_fraction'] * 100:.0f} % of it.", ""]
        lines += _capture_camera_rows(results, cam) + [""]
        warps = [(m, e["log"]) for m in results["methods"]
                 if "board_warp_mm" in (e := results["calibration"][m].get(cam, {})).get("log",
                                                                                         {})]
        if warps:
            lines += ["Board shape fitted (mrcal's two-parabola bow of the feature grid's centre "
                      "w_x, w_y mm, and its y axis stretched against x, %; ± 1σ): " + "; ".join(
                          f"{m} " + ", ".join(
                              f"{v:.3f} ± {log['param_std'].get(n, float('nan')):.3f}"
                              for v, n in zip([*log["board_warp_mm"],
                                               log.get("board_aspect_error_pct", 0.0)],
                                              ("warp_x_mm", "warp_y_mm", "aspect_error_pct")))
                          for m, log in warps) + ".", ""]
        flagged = [(m, v) for m in results["methods"]
                   for v in results["calibration"][m].get(cam, {}).get("diagnostics", {})
                   .get("views", {}).get("flagged", [])]
        if flagged:
            by_view = {}
            for m, v in flagged:
                by_view.setdefault(v, []).append(m)
            lines += ["Views that fit worse than the others: " + "; ".join(
                f"{results['frame_names'][v]} ({', '.join(ms)})"
                for v, ms in sorted(by_view.items())) + ".", ""]
        lines += ["Agreement between methods (projection difference over the image):", ""]
        lines += _agreement_rows(results["agreement"][cam]) + [""]
    if results["rig"]:
        lines += ["## The rig", "",
                  f"The first camera the rig joins ({names[0]} unless it was left out) is the "
                  "reference. Board shape: the RMS distance "
                  "between the triangulated board and its known layout after the best rigid "
                  "motion, per frame; scale: the triangulated board's size error. OpenCV: "
                  "cv2.calibrateMultiview on the same detections with the same intrinsics "
                  "fixed (full views only).", ""]
        lines += _capture_rig_rows(results) + [""]
    if results.get("recapture"):
        lines += ["## What to recapture", ""] + [f"- {n}" for n in results["recapture"]] + [""]
    notes = results["warnings"] + results["notes"]
    if notes:
        lines += ["## Notes", ""] + [f"- {n}" for n in notes] + [""]
    t = results["timing"]
    lines += [f"Detection {t['detect_s']:.1f} s, calibration {t['calibrate_s']:.1f} s, "
              f"diagnostics {t['diagnostics_s']:.1f} s, rig {t['rig_s']:.1f} s, views to add "
              f"{t['next_views_s']:.1f} s.", ""]
    return "\n".join(lines)


def imported_markdown(report: dict) -> str:
    """report.md of a calibration from another tool scored against a dataset's truth
    (exchange.score_calibration)."""
    lines = [f"# {report['calibration']} ({report['format']}) against the truth of "
             f"{report['dataset']}", "", f"Cameras {report['matched']}.", ""]
    columns = [c for c in CALIBRATION_COLUMNS
               if c[1][0] in ("projection_difference", "validity", "parameter_errors")]
    lines += _header("camera", *_titles(columns))
    for cam, entry in report["cameras"].items():
        lines.append(f"| {cam} | " + " | ".join(_num(_get(entry, path), 4)
                                                for _, path in columns) + " |")
    rig = report.get("rig")
    if rig and "error" in rig:
        lines += ["", "## The rig", "", f"Not scored: {rig['error']}."]
    elif rig:
        geo = rig["board_geometry"]
        lines += ["", "## The rig", "",
                  f"RMSE_cal {_num(rig['rmse_cal_mm'])} mm over {rig['points_triangulated']} "
                  f"triangulated board points (centre {_num(rig['centre_rmse_mm'])} mm, max "
                  f"{_num(rig['max_error_mm'])} mm); the triangulated board keeps its shape to "
                  f"{_num(geo['rmse_mm'])} mm and its size to {_num(geo['scale_error_pct'])} %.",
                  ""]
        lines += _header("camera", "rotation err deg", "centre err mm", "aligned rotation err deg",
                         "aligned centre err mm")
        aligned = (rig.get("aligned") or {}).get("cameras", {})
        for cam, e in rig["camera_errors"].items():
            a = aligned.get(cam, {})
            lines.append(f"| {cam} | {_num(e['rotation_deg'], 4)} | {_num(e['centre_mm'], 4)} | "
                         f"{_num(a.get('rotation_deg'), 4)} | {_num(a.get('centre_mm'), 4)} |")
    return "\n".join(lines + [""])


def twin_markdown(results: dict) -> str:
    """The twin's report: real against twin per camera, whether they match, then (only if they
    do) each method's true errors with 95 % intervals over seeds (run/twin.py)."""

    def iv(s, digits=3):
        if not isinstance(s, dict) or not s.get("n"):
            return "–"
        half = s["ci95"]
        return f"{s['mean']:.{digits}g}" + (f" ± {half:.2g}" if np.isfinite(half) else "")

    def num(x, digits=3):
        return f"{x:.{digits}g}" if isinstance(x, (int, float)) else "–"

    m = results["method"]
    lines = [f"# Twin of {results['capture']}", "",
             f"The capture's {m} cameras and board poses ({results['frames']['twin']} of "
             f"{results['frames']['real']} frames), the imaging measured on its images, rendered "
             f"with exact truth {results['seeds']} times and calibrated as the capture was. Twin "
             f"values: mean ± the 95 % interval over seeds.", "",
             f"## Real and twin ({m})", "",
             "| camera | | detected | RPE px | held-out px | neighbour correlation | residuals "
             "random | projection σ px |", "|---|---|---|---|---|---|---|---|"]
    for cam, s in results["side_by_side"].items():
        r, t = s["real"], s["twin"]
        lines.append(f"| {cam} | real | {r.get('detected')} of {r.get('frames')} | "
                     f"{num(r.get('rpe_px'))} | {num(r.get('heldout_px'))} | "
                     f"{num(r.get('neighbour_correlation'), 2)} | "
                     f"{'yes' if r.get('residuals_random') else 'no'} | "
                     f"{num(r.get('projection_sigma_px'))} |")
        lines.append(f"| {cam} | twin | {iv(t['detected'])} | {iv(t['rpe_px'])} | "
                     f"{iv(t['heldout_px'])} | {iv(t['neighbour_correlation'], 2)} | "
                     f"{100 * t['residuals_random_share']:.0f} % of seeds | "
                     f"{iv(t['projection_sigma_px'])} |")
    lines += ["", "Per-view RPE px (10th, 50th, 90th percentile; the twin's views of every seed "
              "pooled):", ""]
    for cam, s in results["side_by_side"].items():
        real = [v for v in (s["view_rpe_px"]["real"] or []) if v is not None]
        twin = [v for seed in s["view_rpe_px"]["twin"] for v in (seed or []) if v is not None]
        spread = [", ".join(f"{q:.3g}" for q in np.percentile(v, [10, 50, 90])) if v else "–"
                  for v in (real, twin)]
        lines.append(f"- {cam}: real {spread[0]}; twin {spread[1]}")
    img = results["imaging"]
    lines += ["", "Imaging measured on the real images (render/imaging_fit.py) and the twin's "
              "settings:", "", "| camera | black | white | background | gain DN/e | read DN | "
              "corner illumination | edge σ px | JPEG quality |",
              "|---|---|---|---|---|---|---|---|---|"]
    for cam, f in img["measured_on_real"].items():
        lines.append(f"| {cam} | {f['black_level']:.0f} | {f['white_level']:.0f} | "
                     f"{f['background']:.0f} | {num(f['gain_dn_per_e'])} | "
                     f"{f['read_noise_dn']:.2f} | {f['corner_illumination']:.2f} | "
                     f"{f['edge_sigma_px']:.2f} | {f['jpeg_quality'] or '–'} |")
    env = results["rig"]["environment"]
    lines += ["", f"Twin environment: `{json.dumps(env)}` (the lens blur is the real edge "
              f"width {img['edge_sigma_px']['real']:.2f} px less, in quadrature, the "
              f"rendered edge's own {img['edge_sigma_px']['rendered_without_blur']:.2f} px). "
              "Not reproduced: motion blur, the board's scale"
              + (", its warp (not fitted by the capture: --fit-board-warp)"
                 if "board" not in env else "") + ".", ""]
    if not results["matches"]:
        lines += ["## The twin does not match", "",
                  "Its true errors are not an answer for this capture:", ""]
        lines += [f"- {x}" for x in results["mismatch"]]
        return "\n".join(lines) + "\n"
    lines += ["## How far each calibration most likely is from the truth", "",
              "| method | camera | projection diff mean px | max px | fx err px | fy err px | "
              "cx err px | cy err px |", "|---|---|---|---|---|---|---|---|"]
    for meth, e in results["true_errors"].items():
        for cam, c in e["cameras"].items():
            lines.append(f"| {meth} | {cam} | {iv(c['projection_mean_px'])} | "
                         f"{iv(c['projection_max_px'])} | {iv(c['fx_err_px'])} | "
                         f"{iv(c['fy_err_px'])} | {iv(c['cx_err_px'])} | {iv(c['cy_err_px'])} |")
    rigs = {meth: e["rig"] for meth, e in results["true_errors"].items() if "rig" in e}
    if rigs:
        lines += ["", "| method | RMSE_cal mm | rotation err deg | centre err mm | "
                  "baseline err mm |", "|---|---|---|---|---|"]
        lines += [f"| {meth} | {iv(r['rmse_cal_mm'])} | {iv(r['rotation_deg'])} | "
                  f"{iv(r['centre_mm'])} | {iv(r['baseline_mm'])} |" for meth, r in rigs.items()]
    return "\n".join(lines) + "\n"


def _interval(s: dict, digits: int = 3) -> str:
    """mean [95 % interval] of a sweep_stats.t_interval summary; the mean alone for one seed."""
    if not s or s.get("mean") is None or not math.isfinite(s["mean"]):
        return "–"
    if s.get("ci_low") is None or not math.isfinite(s["ci_low"]):
        return _num(s["mean"], digits)
    return f"{_num(s['mean'], digits)} [{_num(s['ci_low'], digits)}, {_num(s['ci_high'], digits)}]"


def _share_cell(s: dict) -> str:
    return (f"{100 * s['share']:.0f} % [{100 * s['ci_low']:.0f}, {100 * s['ci_high']:.0f}] "
            f"of {s['n']}")


def compare_markdown(report: dict) -> str:
    """report.md of ``stereo-bench compare-tools`` (run/compare.py): every tool's figures with
    95 % intervals over the seeds, its pose cost, and whether its uncertainty is honest."""
    seeds = len(report["seeds"])
    table, pose = report["table"], report.get("pose") or {}
    ran = {n: r for n, r in table.items() if not r["skipped"]}
    lines = [f"# Calibration tools against the truth: {report['rig']}", "",
             f"{report['cameras']} camera(s), {report['pattern']} board, `{report['environment']}` "
             f"imaging, {seeds} seed(s). Every tool calibrates the same detections of each seed's "
             f"session as its users run it (a tool that reads only images, multical, detects "
             f"the board itself in the same images); its own file is read back and scored "
             f"against the truth. Cells: mean [95 % Student-t interval over the seeds].", ""]

    def rows(keys: tuple, extra=None) -> list[str]:
        figs = [f for f in COMPARE_FIGURES if f[0] in keys]
        out = _header("tool", *[f"{t} {u}" for _, t, u in figs],
                      *([extra[0]] if extra else []), "seeds")
        for name, row in ran.items():
            cells = [_interval(row["figures"][k], 4 if u == "deg" else 3) for k, _, u in figs]
            if extra:
                cells.append(extra[1](name))
            out.append(f"| {name} | " + " | ".join(cells) + f" | {row['seeds']} |")
        return out

    lines += ["## The cameras", "", "Errors of each camera's intrinsics (mean over the cameras); "
              "the projection difference is how far the tool's lens projects each true ray of "
              "a grid over the whole image from its pixel (mean over the cameras of the mean, "
              "worst camera's max). A lens the suite's camera model cannot hold (mrcal's "
              "splined) is compared through its own projection after turning its camera frame "
              "onto the true one (its frame is a gauge), and has no parameters to compare.", ""]
    lines += rows(("focal_error_px", "principal_point_error_px", "projection_difference_mean_px",
                   "projection_difference_max_px", "time_s"))
    if report["cameras"] > 1:
        pose_cols = "costs" in pose
        lines += ["", "## The rig", "", "RMSE_cal: the board's points triangulated through the "
                  "tool's cameras against their true positions. Camera errors: the other "
                  "cameras' centres and rotations with camera 0 as the reference (mean), and "
                  "the centres after a similarity alignment of all cameras (3+ cameras).", ""]
        lines += rows(("rmse_cal_mm", "centre_error_mm", "rotation_error_deg",
                       "aligned_centre_error_mm"),
                      ("pose cost mm", lambda n: _interval(pose["costs"].get(n, {})))
                      if pose_cols else None)
        if pose_cols:
            lines += ["", f"Pose cost: pose-eval's paired MPJPE of the body triangulated "
                          f"through the tool's cameras minus through the true ones, on the same "
                          f"keypoints (floor, true cameras: {_interval(pose['floor'])} mm); "
                          f"{pose['about']}."]
        elif pose.get("error"):
            lines += ["", f"Pose cost not measured: {pose['error']}."]
    cover = {n: r["coverage"] for n, r in table.items() if r["coverage"]}
    if cover:
        lines += ["", "## Is each tool's own uncertainty honest?", "",
                  "The share of (seed, camera) values whose true error lies inside the tool's "
                  "reported 1-sigma, with its 95 % Wilson interval; an honest uncertainty holds "
                  "68 %. Projection: the true error of the mean-frames projection at 9 pixels "
                  f"inside the 68 % ellipse of the reported covariance (e' S^-1 e <= "
                  f"{report['chi2_2d_68']:.2f}); beside it the median of the error's length over "
                  "the worst-direction sigma.", ""]
        lines += _header("tool", "parameters (all)", "projection", "error / sigma (median)",
                         "worst parameter")
        for name, c in cover.items():
            params = c.get("parameters", {})
            worst = min(params.items(), key=lambda kv: kv[1]["share"], default=None)
            none = c.get("not_computed", [])
            lines.append(
                f"| {name} | {_share_cell(c['parameters_all']) if params else '–'} | "
                f"{_share_cell(c['projection']) if 'projection' in c else '–'}"
                + (f"; not computed for {len(none)}: {none[0]}" if none else "") + " | "
                f"{_num(c.get('projection_error_over_sigma_median'), 2)} | "
                + (f"{worst[0]}: {100 * worst[1]['share']:.0f} %" if worst else "–") + " |")
    lines += ["", "## The tools", ""]
    for name, row in table.items():
        state = (f"not run here: {row['skipped']}" if row["skipped"] else
                 f"failed on {len(row['failed'])} seed(s), e.g. {row['failed'][0]}"
                 if row["failed"] else "ran on every seed")
        lines.append(f"- **{name}**: {report['about'][name]}; {state}.")
    return "\n".join(lines + [""])
