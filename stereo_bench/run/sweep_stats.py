"""A sweep's statistics: per-trial figures, curves with Student-t intervals, paired comparisons.

Every trial of a configuration is one seed (the rig's seed + the trial's index, see
``pipeline.run``); the seed drives the images' noise and, for a session trajectory, the walk.
Two configurations of one rig file therefore see the same seeds, and within a configuration
every method calibrates the same detections. So a difference between two methods, or between
two patterns, is taken per seed (a paired design), and its mean gets a 95 % Student-t interval
over the seeds: mean ± t(0.975, n-1) · s / sqrt(n), s the sample standard deviation (ddof 1).
A verdict "A beats B" is written only where that interval excludes zero.

Figures per trial (``trial_values``):

* ``projection_difference_mean_px``: per method, the mean over the rig's cameras of each
  camera's mean projection difference against the truth (px); undefined in a trial where a
  camera's calibration failed;
* ``rmse_cal_mm``: per method, RMSE_cal of the rig (mm; rigs of 2+ cameras);
* ``detection_rate``: frames where the board was found over frames, all cameras together;
* ``detection_error_px``: mean distance of the detected points from the true ones (px), over
  all cameras' points.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from itertools import combinations

import numpy as np
from scipy import stats

from .grid import value_key, value_token

CONFIDENCE = 0.95


@dataclass(frozen=True)
class Metric:
    key: str
    title: str
    unit: str
    better: str        # "lower" or "higher"
    per_method: bool   # calibration figures are per method; detection ones are the pattern's


METRICS = [
    Metric("projection_difference_mean_px", "projection difference mean", "px", "lower", True),
    Metric("rmse_cal_mm", "RMSE_cal", "mm", "lower", True),
    Metric("detection_rate", "detection rate", "share of frames", "higher", False),
    Metric("detection_error_px", "detection error", "px", "lower", False),
]


def _num(x) -> float:
    return float(x) if isinstance(x, (int, float)) and not isinstance(x, bool) else math.nan


def t_interval(values, confidence: float = CONFIDENCE) -> dict:
    """Mean, sample std and the two-sided Student-t interval of the mean over the finite
    ``values``; the interval is NaN (with a reason) below two values."""
    v = np.array([x for x in map(_num, values) if math.isfinite(x)])
    n = len(v)
    out = {"n": n, "mean": float(v.mean()) if n else math.nan,
           "std": float(v.std(ddof=1)) if n > 1 else math.nan,
           "ci_low": math.nan, "ci_high": math.nan}
    if n > 1:
        half = stats.t.ppf(0.5 + confidence / 2, n - 1) * out["std"] / math.sqrt(n)
        out["ci_low"], out["ci_high"] = out["mean"] - half, out["mean"] + half
    else:
        out["ci_reason"] = f"{n} value(s): no interval"
    return out


def trial_values(trial: dict) -> dict:
    """The sweep's figures of one trial (a trial report of ``pipeline.run``; module docstring)."""
    det = trial["detection"].values()
    frames = sum(e["frames"] for e in det)
    weighted = [(_num(e["mean_px"]), e["points"]) for e in det
                if e.get("points") and math.isfinite(_num(e["mean_px"]))]
    points = sum(p for _, p in weighted)
    methods = {}
    for m, cams in trial["calibration"].items():
        failed = [f"{cam}: {e['error']}" for cam, e in cams.items() if "error" in e]
        means = [_num(e["projection_difference"]["mean_px"]) for e in cams.values()
                 if "error" not in e]
        entry = {"projection_difference_mean_px": math.nan if failed else float(np.mean(means))}
        if failed:
            entry["error"] = "; ".join(failed)
        rig = (trial.get("rig") or {}).get(m)
        if rig is not None:
            entry["rmse_cal_mm"] = _num(rig.get("rmse_cal_mm"))
            entry["rig_rpe_px"] = _num(rig.get("rms_px"))
            if "error" in rig:
                entry["rig_error"] = rig["error"]
        methods[m] = entry
    return {"seed": trial["seed"],
            "detection_rate": sum(e["found"] for e in det) / frames if frames else math.nan,
            "detection_error_px": (sum(v * p for v, p in weighted) / points if points
                                   else math.nan),
            "methods": methods}


def value(values: dict, metric: Metric, method: str | None) -> tuple[float, str | None]:
    """One trial's figure and, when it has none, why."""
    if not metric.per_method:
        v = _num(values[metric.key])
        return v, None if math.isfinite(v) else "no board point detected"
    entry = values["methods"].get(method)
    if entry is None:
        return math.nan, f"{method} not run"
    v = _num(entry.get(metric.key))
    if math.isfinite(v):
        return v, None
    if metric.key == "rmse_cal_mm":
        return v, f"{method}: {entry.get('rig_error') or entry.get('error') or 'no point triangulated'}"
    return v, f"{method}: {entry.get('error', 'estimate invalid over the whole image')}"


def _multi(result: dict) -> list[dict]:
    return [a for a in result["axes"] if len(a["values"]) >= 2]


def _point(row: dict, metric: Metric, method: str | None, x) -> dict:
    if "error" in row:
        return {"x": x, "configuration": row["name"], "n": 0, "failed": row["error"]}
    vals, excluded = [], []
    for t in row["per_trial"]:
        v, why = value(t, metric, method)
        if why:
            excluded.append({"seed": t["seed"], "reason": why})
        else:
            vals.append(v)
    return {"x": x, "configuration": row["name"], **t_interval(vals), "excluded": excluded}


def _groups(rows: list[dict], held: list[dict]) -> dict[tuple, list[dict]]:
    """Configurations by rig and the values of the ``held`` axes, in the grid's order."""
    out: dict[tuple, list[dict]] = {}
    for row in rows:
        key = (row["rig"], *(value_key(row["axes"][a["path"]]) for a in held))
        out.setdefault(key, []).append(row)
    return out


def curves(result: dict) -> list[dict]:
    """Per axis of 2+ values and per combination of the other axes' values (and rig file): each
    metric against the axis, one line per method (detection metrics: per pattern). When the
    grid also varies the pattern, the pattern is a line of its own (method / pattern) rather
    than another figure, so that patterns are compared in one picture."""
    multi = _multi(result)
    rows = result["configurations"]
    out, ids = [], set()
    for axis in multi:
        by_pattern = axis["path"] != "pattern.kind" and any(
            a["path"] == "pattern.kind" for a in multi)
        held = [a for a in multi if a is not axis and not (by_pattern
                                                           and a["path"] == "pattern.kind")]
        for group in _groups(rows, held).values():
            first = group[0]
            patterns = (next(a for a in multi if a["path"] == "pattern.kind")["values"]
                        if by_pattern else [None])

            def row_at(x, p):
                return next(r for r in group if value_key(r["axes"][axis["path"]]) == value_key(x)
                            and (p is None or r["axes"]["pattern.kind"] == p))

            metrics = {}
            for metric in METRICS:
                if metric.key == "rmse_cal_mm" and len(first["cameras"]) < 2:
                    continue
                series = ([(m, p) for m in result["methods"] for p in patterns]
                          if metric.per_method else [(None, p) for p in patterns])
                lines = []
                for m, p in series:
                    label = " / ".join(s for s in (m, p) if s) or (
                        first["pattern"] if axis["path"] != "pattern.kind" else "detection")
                    lines.append({"label": label, "method": m, "pattern": p,
                                  "points": [_point(row_at(x, p), metric, m, x)
                                             for x in axis["values"]]})
                metrics[metric.key] = {"title": metric.title, "unit": metric.unit,
                                       "better": metric.better, "lines": lines}
            held_values = {"rig": first["rig"],
                           **{a["path"]: first["axes"][a["path"]] for a in held}}
            cid = "__".join([axis["label"], first["rig"]] + [
                f"{a['label']}-{value_token(first['axes'][a['path']])}" for a in held])
            while cid in ids:
                cid += "_"
            ids.add(cid)
            out.append({"id": cid, "axis": axis["path"], "axis_label": axis["label"],
                        "scale": axis["scale"], "values": axis["values"], "held": held_values,
                        "figure": f"curves/{cid}.png", "metrics": metrics})
    return out


def _verdict(ci: dict, better: str, a: str, b: str) -> str:
    n = ci["n"]
    low, high = ci["ci_low"], ci["ci_high"]
    if n < 2 or not (low > 0 or high < 0):  # NaN compares False: no interval, no verdict
        return f"no difference shown at n={n}"
    a_wins = (high < 0) == (better == "lower")
    said = f"{a} beats {b}" if a_wins else f"{b} beats {a}"
    if ci["std"] == 0:
        said += f" (all {n} differences equal: the seed changes nothing here)"
    return said


def _paired(metric: Metric, rows: tuple[dict, dict], methods: tuple, names: tuple,
            extra: dict) -> dict:
    """Per seed, figure of A minus figure of B; its mean, interval and verdict."""
    entry = {**extra, "metric": metric.key, "unit": metric.unit, "better": metric.better,
             "a": names[0], "b": names[1],
             "configurations": sorted({r["name"] for r in rows}, key=[r["name"]
                                                                      for r in rows].index)}
    failed = {r["name"]: r["error"] for r in rows if "error" in r}
    if failed:
        entry.update(n=0, verdict="not compared: " + "; ".join(
            f"configuration {k} failed ({v})" for k, v in failed.items()), differences=[],
            excluded=[])
        return entry
    trials = [{t["seed"]: t for t in r["per_trial"]} for r in rows]
    diffs, excluded = [], []
    for seed in sorted(set(trials[0]) | set(trials[1])):
        if seed not in trials[0] or seed not in trials[1]:
            excluded.append({"seed": seed, "reason": "not run in both configurations"})
            continue
        (va, wa), (vb, wb) = (value(t[seed], metric, m) for t, m in zip(trials, methods))
        if wa or wb:
            excluded.append({"seed": seed, "reason": "; ".join(
                f"{n}: {w}" for n, w in zip(names, (wa, wb)) if w)})
            continue
        diffs.append({"seed": seed, "a": va, "b": vb, "difference": va - vb})
    ci = t_interval([d["difference"] for d in diffs])
    entry.update(n=ci["n"], mean_difference=ci["mean"], std=ci["std"], ci_low=ci["ci_low"],
                 ci_high=ci["ci_high"], verdict=_verdict(ci, metric.better, *names),
                 differences=diffs, excluded=excluded)
    return entry


def comparisons(result: dict) -> list[dict]:
    """Paired comparisons: every pair of methods within each configuration (calibration
    metrics), and, when the grid varies the pattern, every pair of patterns between the
    configurations that differ in the pattern alone (each method's calibration metrics and the
    detection metrics)."""
    out = []
    rows = result["configurations"]
    for row in rows:
        for a, b in combinations(result["methods"], 2):
            for metric in METRICS:
                if metric.per_method and (metric.key != "rmse_cal_mm" or len(row["cameras"]) > 1):
                    out.append(_paired(metric, (row, row), (a, b), (a, b),
                                       {"kind": "methods", "axes": row["axes"]}))
    pattern = next((a for a in _multi(result) if a["path"] == "pattern.kind"), None)
    if pattern is None:
        return out
    others = [a for a in result["axes"] if a is not pattern]
    for group in _groups(rows, others).values():
        by = {r["axes"]["pattern.kind"]: r for r in group}
        held = {k: v for k, v in group[0]["axes"].items() if k != "pattern.kind"}
        for pa, pb in combinations(pattern["values"], 2):
            pair = (by[pa], by[pb])
            for metric in METRICS:
                if metric.key == "rmse_cal_mm" and len(pair[0]["cameras"]) < 2:
                    continue
                for m in (result["methods"] if metric.per_method else [None]):
                    out.append(_paired(metric, pair, (m, m), (pa, pb),
                                       {"kind": "patterns", "method": m, "axes": held}))
    return out


def _cell(p: dict) -> str:
    if "failed" in p:
        return "failed"
    if p["n"] == 0:
        return "-"
    if p["n"] == 1:
        return f"{p['mean']:.4g} (n=1)"
    return f"{p['mean']:.4g} [{p['ci_low']:.4g}, {p['ci_high']:.4g}] (n={p['n']})"


def _said(values: dict) -> str:
    return ", ".join(f"{k} = {v}" for k, v in values.items()) or "-"


def stats_markdown(result: dict) -> str:
    """The curves (one table per figure and metric) and the paired comparisons, in Markdown."""
    pct = f"{CONFIDENCE:.0%}".replace("%", " %")
    lines = ["", "## Curves", "",
             f"Mean over trials [{pct} Student-t interval] (n trials), per axis value; the "
             "figures are in curves/. A failed configuration reads `failed`; trials left out "
             "are listed at the end.", ""]
    for curve in result["curves"]:
        lines += [f"### {curve['axis']} ({_said(curve['held'])})", "",
                  f"Figure: `{curve['figure']}`", ""]
        for metric in curve["metrics"].values():
            labels = [ln["label"] for ln in metric["lines"]]
            lines += [f"{metric['title']} ({metric['unit']}, {metric['better']} is better):", "",
                      "| " + " | ".join([curve["axis_label"], *labels]) + " |",
                      "|" + "---|" * (len(labels) + 1)]
            for i, x in enumerate(curve["values"]):
                lines.append(f"| {x} | " + " | ".join(_cell(ln["points"][i])
                                                      for ln in metric["lines"]) + " |")
            lines.append("")
    lines += ["## Paired comparisons", "",
              f"Per seed, the figure of A minus that of B over the trials both have (same seed: "
              f"same trajectory and noise); mean and {pct} Student-t interval of the "
              f"difference. \"A beats B\" only where the interval excludes zero.", "",
              "| kind | where | metric | A | B | n | mean A-B | interval | verdict |",
              "|---|---|---|---|---|---|---|---|---|"]
    for c in result["comparisons"]:
        where = ", ".join(c["configurations"]) if c["kind"] == "methods" else (
            f"{_said(c['axes'])}" + (f"; method {c['method']}" if c["method"] else ""))
        if c["n"] == 0:
            lines.append(f"| {c['kind']} | {where} | {c['metric']} | {c['a']} | {c['b']} | 0 "
                         f"| | | {c['verdict']} |")
            continue
        interval = (f"[{c['ci_low']:.3g}, {c['ci_high']:.3g}]" if c["n"] > 1 else "")
        lines.append(f"| {c['kind']} | {where} | {c['metric']} ({c['unit']}) | {c['a']} | "
                     f"{c['b']} | {c['n']} | {c['mean_difference']:.3g} | {interval} | "
                     f"{c['verdict']} |")
    left = _left_out(result)
    if left:
        lines += ["", "## Left out of curves and pairing", ""] + left
    return "\n".join(lines) + "\n"


def _left_out(result: dict) -> list[str]:
    out = []
    for row in result["configurations"]:
        if "error" in row:
            out.append(f"- {row['name']}: configuration failed: {row['error']}")
            continue
        for t in row["per_trial"]:
            for metric in METRICS:
                for m in (result["methods"] if metric.per_method else [None]):
                    if metric.key == "rmse_cal_mm" and len(row["cameras"]) < 2:
                        continue
                    _, why = value(t, metric, m)
                    if why:
                        out.append(f"- {row['name']}, seed {t['seed']}, {metric.key}: {why}")
    return out
