"""Write our Tables 2, 3 and 4 beside the paper's, and whether the suite confirms the paper's
claims, with intervals.

    python scripts/paper_comparison.py out/paper_grid [--out docs/paper_comparison.md]
    python scripts/paper_comparison.py out/paper_realistic_mono out/paper_realistic_pairs \
        --out docs/paper_realistic.md --discussion ''

Reads the sweep.json of one or more `stereo-bench sweep` runs (configs/grids/paper.yaml, or
paper_realistic_mono.yaml and paper_realistic_pairs.yaml). Every environment other than
`clean` is set beside the paper's noisy column. The paper's numbers below are typed from its
tables (reference/synthcal-paper.tex) for side-by-side reading only; every number in our
columns is read from the sweeps' results. The claims are tested on paired per-seed differences
(each seed renders the same trajectory and noise for every method and pattern) with 95 %
Student-t intervals (stereo_bench.run.sweep_stats): a claim is confirmed where every interval it
rests on excludes zero in its favour, refuted where one excludes zero against it.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from stereo_bench.run.sweep_stats import METRICS, t_interval, value

METHODS = {"zhang": "Zhang", "tsai": "Tsai", "bouguet": "Bouguet"}
PATTERNS = {"checkerboard": "9x12 Ch", "symmetric_circles": "10x10 Sc",
            "asymmetric_circles": "9x10 Ac", "charuco": "9x12 Cu"}
# The paper's Table 2: (RPE_RMS, RMSE) per camera and method, 9x12 Ch.
PAPER_T2 = {"rectilinear": {"zhang": (0.510, 1.221), "tsai": (0.551, 1.880),
                            "bouguet": (0.373, 1.127)},
            "wide": {"zhang": (1.316, 2.219), "tsai": (1.433, 2.344),
                     "bouguet": (0.811, 1.861)}}
# The paper's Table 3: (RPE_RMS, RMSE) per environment, pattern and method.
PAPER_T3 = {
    "clean": {"checkerboard": [(0.510, 1.221), (0.561, 1.233), (0.483, 1.166)],
              "symmetric_circles": [(0.508, 1.206), (0.559, 1.216), (0.490, 1.214)],
              "asymmetric_circles": [(0.506, 1.205), (0.554, 1.198), (0.497, 1.193)],
              "charuco": [(0.493, 1.093), (0.542, 1.139), (0.476, 1.012)]},
    "noisy": {"checkerboard": [(1.116, 2.219), (1.227, 2.290), (1.062, 2.252)],
              "symmetric_circles": [(1.20, 2.263), (1.320, 2.347), (1.140, 2.373)],
              "asymmetric_circles": [(1.118, 2.261), (1.234, 2.224), (1.155, 2.319)],
              "charuco": [(0.898, 1.916), (0.987, 1.868), (0.853, 2.020)]}}
# The paper's Table 4: RMSE_cal (mm) per rig and environment, 9x12 Ch.
PAPER_T4 = {"rectilinear_pair": {"clean": (2.365, 2.456, 2.143), "noisy": (4.604, 4.812, 4.746)},
            "wide_pair": {"clean": (3.780, 3.998, 3.612), "noisy": (5.611, 5.742, 5.798)},
            "mixed_pair": {"clean": (4.118, 4.236, 4.052), "noisy": (6.401, 6.552, 6.577)}}


def cell(summary: dict | None) -> str:
    if not summary or summary["n"] == 0:
        return "failed"
    if summary["n"] == 1:
        return f"{summary['mean']:.3f}"
    return f"{summary['mean']:.3f} ± {summary['std']:.3f}"


def mono(configs: dict, rig: str, pattern: str, env: str, method: str, column: str):
    row = configs.get(f"{rig}_mono_{pattern}_{env}")
    if not row or "aggregate" not in row:
        return None
    (cam_row,) = row["aggregate"]["calibration"][method].values()
    return cam_row[column]


def rig_cell(configs: dict, rig: str, env: str, method: str):
    row = configs.get(f"{rig}_checkerboard_{env}")
    if not row or "aggregate" not in row or "rig" not in row["aggregate"]:
        return None
    return row["aggregate"]["rig"][method]["RMSE_cal mm"]


def load(sweep_dirs: list[Path]) -> tuple[dict, list[str]]:
    """The configurations of every sweep by name, and the sweeps' names."""
    configs, names = {}, []
    for sweep_dir in sweep_dirs:
        sweep = json.loads((sweep_dir / "sweep.json").read_text())
        names.append(sweep["name"])
        for row in sweep["configurations"]:
            # A configuration rerun with more trials (stereo-bench RIG --out DIR/name --trials
            # N) has a newer results.json than the sweep's summary.
            results = sweep_dir / row["name"] / "results.json"
            if "aggregate" in row and results.is_file():
                row["aggregate"] = json.loads(results.read_text())["aggregate"]
            configs[row["name"]] = row
    return configs, names


def environments(configs: dict) -> list[str]:
    envs = {r["axes"].get("environment.kind") for r in configs.values() if "axes" in r}
    envs.discard(None)
    envs = envs or {"clean", "noisy"}
    return ["clean"] * ("clean" in envs) + sorted(envs - {"clean"})


def paper_env(env: str) -> str:
    return "clean" if env == "clean" else "noisy"


def write(configs: dict, grids: list[str]) -> str:
    trials = next((c["aggregate"]["trials"] for c in configs.values() if "aggregate" in c), 0)
    envs = environments(configs)
    out = ["# Our numbers beside the paper's", "",
           f"Generated by `scripts/paper_comparison.py` from `stereo-bench sweep` of "
           f"{', '.join(f'configs/grids/{g}.yaml' for g in grids)} ({len(configs)} "
           f"configurations, {trials} trial(s) each). Ours: mean (± std over trials when there "
           "are several). Paper: its Tables 2-4; every environment but `clean` is set beside "
           "the paper's noisy column.", "",
           "## Table 2: 9x12 checkerboard, clean, mono", "",
           "| camera | method | RPE_RMS ours | RPE_RMS paper | RMSE ours | RMSE paper | "
           "proj. diff mean px (ours) |", "|---|---|---|---|---|---|---|"]
    for cam in ("rectilinear", "wide"):
        for m, label in METHODS.items():
            p = PAPER_T2[cam][m]
            out.append(f"| {cam} | {label} | "
                       f"{cell(mono(configs, cam, 'checkerboard', 'clean', m, 'RPE_RMS px'))} | "
                       f"{p[0]} | {cell(mono(configs, cam, 'checkerboard', 'clean', m, 'paper RMSE'))}"
                       f" | {p[1]} | "
                       f"{cell(mono(configs, cam, 'checkerboard', 'clean', m, 'proj. diff mean px'))} |")
    out += ["", "## Table 3: four patterns, rectilinear mono, every environment", "",
            "| environment | pattern | method | RPE_RMS ours | RPE_RMS paper | RMSE ours | "
            "RMSE paper | proj. diff mean px (ours) |", "|---|---|---|---|---|---|---|---|"]
    for env in envs:
        for pattern, plabel in PATTERNS.items():
            for i, (m, label) in enumerate(METHODS.items()):
                p = PAPER_T3[paper_env(env)][pattern][i]
                get = lambda col: cell(mono(configs, "rectilinear", pattern, env, m, col))  # noqa
                out.append(f"| {env} | {plabel} | {label} | {get('RPE_RMS px')} | {p[0]} | "
                           f"{get('paper RMSE')} | {p[1]} | {get('proj. diff mean px')} |")
    out += ["", "## Table 4: RMSE_cal (mm), 9x12 checkerboard, stereo rigs", "",
            "| rig | environment | " + " | ".join(f"{l} ours | {l} paper" for l in
                                                   METHODS.values()) + " |",
            "|---|---|" + "---|---|" * len(METHODS)]
    for rig in PAPER_T4:
        for env in envs:
            cells = [f"{cell(rig_cell(configs, rig, env, m))} | "
                     f"{PAPER_T4[rig][paper_env(env)][i]}" for i, m in enumerate(METHODS)]
            out.append(f"| {rig} | {env} | " + " | ".join(cells) + " |")
    failed = [c["name"] for c in configs.values() if "error" in c]
    if failed:
        out += ["", f"Failed configurations: {', '.join(failed)}."]
    if any("per_trial" in c for c in configs.values()):
        out += claims(configs, envs)
    return "\n".join(out) + "\n"


PROJ = next(m for m in METRICS if m.key == "projection_difference_mean_px")
RMSE_CAL = next(m for m in METRICS if m.key == "rmse_cal_mm")


def paired(configs: dict, a: tuple, b: tuple, metric) -> dict:
    """Per seed, the figure of (configuration, method) ``a`` minus that of ``b``, with its
    interval (NaN, with the reason, when a configuration is missing or failed)."""
    rows = [configs.get(name) for name, _ in (a, b)]
    if any(r is None or "per_trial" not in r for r in rows):
        return {"n": 0, "why": "not run"}
    by_seed = [{t["seed"]: t for t in r["per_trial"]} for r in rows]
    diffs = []
    for seed in sorted(set(by_seed[0]) & set(by_seed[1])):
        (va, wa), (vb, wb) = (value(t[seed], metric, m)
                              for t, (_, m) in zip(by_seed, (a, b)))
        if not (wa or wb):
            diffs.append(va - vb)
    return {**t_interval(diffs), "deterministic": len(diffs) > 1 and len(set(diffs)) == 1}


def said(ci: dict) -> str:
    if ci["n"] == 0:
        return ci.get("why", "no trial")
    if ci.get("deterministic"):
        return f"{ci['mean']:+.3f} (every seed alike)"
    if ci["n"] < 2:
        return f"{ci['mean']:+.3f} (n=1)"
    return f"{ci['mean']:+.3f} [{ci['ci_low']:+.3f}, {ci['ci_high']:+.3f}]"


def verdict(cis: list[dict]) -> str:
    """'confirmed' when every difference (claim's side minus the other) is below zero for
    sure, 'refuted' when one is above zero for sure, else 'not shown'. A deterministic
    difference (every seed renders the same clean images) counts by its sign, said so."""
    def sure(ci, below):
        if ci["n"] == 0 or not math.isfinite(ci["mean"]):
            return False
        if ci.get("deterministic"):
            return ci["mean"] < 0 if below else ci["mean"] > 0
        return ci["n"] > 1 and (ci["ci_high"] < 0 if below else ci["ci_low"] > 0)
    if cis and all(sure(c, True) for c in cis):
        return "confirmed"
    if any(sure(c, False) for c in cis):
        return "refuted"
    return "not shown"


def claims(configs: dict, envs: list[str]) -> list[str]:
    """The paper's four claims, on paired per-seed differences (claim's side minus other)."""
    noisy = [e for e in envs if e != "clean"]
    cams = ("rectilinear", "wide")
    out = ["", "## The paper's claims", "",
           "Each cell: the mean per-seed difference, the claim's side minus the other (negative "
           "favours the claim), with its 95 % interval; `every seed alike` where the images do "
           "not depend on the seed (clean renders of a spring trajectory). Projection "
           "difference (px) for one camera, RMSE_cal (mm) for rigs.", "",
           "### ChArUco is the most robust pattern under noise", "",
           "| camera | environment | method | ChArUco − checkerboard | ChArUco − symmetric "
           "circles | ChArUco − asymmetric circles | verdict |", "|---|---|---|---|---|---|---|"]
    others = [p for p in PATTERNS if p != "charuco"]
    for cam in cams:
        for env in noisy:
            for m in METHODS:
                cis = [paired(configs, (f"{cam}_mono_charuco_{env}", m),
                              (f"{cam}_mono_{p}_{env}", m), PROJ) for p in others]
                out.append(f"| {cam} | {env} | {METHODS[m]} | "
                           + " | ".join(said(c) for c in cis) + f" | {verdict(cis)} |")
    out += ["", "### Bouguet's method is the most accurate on clean images", "",
            "| camera | pattern | Bouguet − Zhang | Bouguet − Tsai | verdict | "
            "Bouguet-brown − Zhang-brown (same lens model) |", "|---|---|---|---|---|---|"]
    for cam in cams:
        for p in PATTERNS:
            name = f"{cam}_mono_{p}_clean"
            cis = [paired(configs, (name, "bouguet"), (name, m), PROJ) for m in ("zhang", "tsai")]
            same = paired(configs, (name, "bouguet-brown"), (name, "zhang-brown"), PROJ)
            out.append(f"| {cam} | {PATTERNS[p]} | " + " | ".join(said(c) for c in cis)
                       + f" | {verdict(cis)} | {said(same)} |")
    out += ["", "### Zhang's method is more robust than Bouguet's under noise", "",
            "| setup | environment | pattern | Zhang − Bouguet | verdict | Zhang-brown − "
            "Bouguet-brown (same lens model) | verdict |", "|---|---|---|---|---|---|---|"]
    for env in noisy:
        rows = [(f"{cam} mono", PATTERNS[p], f"{cam}_mono_{p}_{env}", PROJ)
                for cam in cams for p in PATTERNS]
        rows += [(f"{rig} (RMSE_cal)", PATTERNS["checkerboard"], f"{rig}_checkerboard_{env}",
                  RMSE_CAL) for rig in PAPER_T4]
        for setup, plabel, name, metric in rows:
            ci = paired(configs, (name, "zhang"), (name, "bouguet"), metric)
            same = paired(configs, (name, "zhang-brown"), (name, "bouguet-brown"), metric)
            out.append(f"| {setup} | {env} | {plabel} | {said(ci)} | {verdict([ci])} | "
                       f"{said(same)} | {verdict([same])} |")
    out += ["", "### Identical pairs calibrate better than the mixed pair", "",
            "| environment | method | rectilinear pair − mixed | wide pair − mixed | verdict |",
            "|---|---|---|---|---|"]
    for env in envs:
        for m in METHODS:
            cis = [paired(configs, (f"{rig}_checkerboard_{env}", m),
                          (f"mixed_pair_checkerboard_{env}", m), RMSE_CAL)
                   for rig in ("rectilinear_pair", "wide_pair")]
            out.append(f"| {env} | {METHODS[m]} | " + " | ".join(said(c) for c in cis)
                       + f" | {verdict(cis)} |")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sweep_dirs", nargs="+", type=Path,
                    help="output directories of `stereo-bench sweep`")
    ap.add_argument("--out", default="docs/paper_comparison.md")
    ap.add_argument("--discussion", default="docs/paper_discussion.md",
                    help="hand-written discussion appended after the generated tables")
    args = ap.parse_args()
    text = write(*load(args.sweep_dirs))
    if args.discussion and Path(args.discussion).is_file():
        text += "\n" + Path(args.discussion).read_text()
    Path(args.out).write_text(text)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
