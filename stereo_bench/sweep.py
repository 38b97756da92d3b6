"""`stereo-bench sweep GRID.yaml`: many rig configurations (e.g. the paper's 40), in parallel.

A grid file crosses rig files with patterns and environments::

    name: paper_grid
    rigs: [paper/rectilinear_mono.yaml, paper/wide_pair.yaml]   # relative to the grid file
    patterns: [checkerboard, charuco]
    environments: [clean, noisy]
    methods: [zhang, tsai, bouguet, opencv]
    trials: 1
    frames: 127          # optional: overrides each rig's trajectory.frames

Each configuration runs the whole pipeline into OUT/<rig>_<pattern>_<environment>/ in its own
spawned process; one that fails is recorded with its error and the others go on. OUT/sweep.json
and OUT/sweep.md hold one table for the whole grid, with the wall time and the time per stage.
"""

from __future__ import annotations

import time
import traceback
from concurrent.futures import as_completed
from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from .config import (ConfigError, EnvironmentKind, Int, Name, PatternKind, RigConfig, describe,
                     load_rig, load_yaml, parse_rig)
from .report import fmt, run_title, write_report
from .rundir import locked, write_json, write_text
from .workers import process_pool


class GridConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    name: Name = "grid"
    rigs: list[str] = Field(min_length=1, max_length=100)
    patterns: list[PatternKind] = Field(min_length=1)
    environments: list[EnvironmentKind] = Field(["clean"], min_length=1)
    methods: list[str] = Field(["zhang", "tsai", "bouguet", "opencv"], min_length=1)
    trials: Int = Field(1, ge=1, le=1000)
    frames: Int | None = Field(None, gt=0, le=10_000)

    @field_validator("methods")
    @classmethod
    def _known(cls, v):
        from .calibrate import available_methods

        unknown = [m for m in v if m not in available_methods()]
        if unknown:
            raise ValueError(f"unknown {unknown}; available: {', '.join(available_methods())}")
        if len(set(v)) != len(v):
            raise ValueError(f"listed twice: {sorted({m for m in v if v.count(m) > 1})}")
        return v


def load_grid(path) -> tuple[GridConfig, list[RigConfig]]:
    """The grid and its configurations (each rig file crossed with patterns and environments),
    all validated before anything runs; configuration names must be unique."""
    path = Path(path)
    data = load_yaml(path, "grid file")
    try:
        grid = GridConfig.model_validate(data if isinstance(data, dict) else {"": data})
    except ValidationError as e:
        raise ConfigError(describe(e, str(path), "grid file")) from None
    configs = []
    for i, rig_file in enumerate(grid.rigs):
        try:
            base = load_rig(path.parent / rig_file).model_dump(mode="json")
        except ConfigError as e:
            raise ConfigError(f"{path}: rigs.{i}: {e}") from None
        for pattern in grid.patterns:
            for env in grid.environments:
                d = {**base, "name": f"{Path(rig_file).stem}_{pattern}_{env}",
                     "pattern": {"kind": pattern},
                     "environment": {**base["environment"], "kind": env}}
                if grid.frames:
                    d["trajectory"] = {**base["trajectory"], "frames": grid.frames}
                configs.append(parse_rig(d, f"{path}: configuration {d['name']}"))
    names = [c.name for c in configs]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise ConfigError(f"{path}: rigs: configurations {twice} would run twice into one "
                          f"folder (a rig file listed twice, or two with the same file name)")
    return grid, configs


def _run_config(args) -> dict:
    from .pipeline import run
    from .plots import plot_run

    cfg_json, out, methods, trials = args
    cfg = RigConfig.model_validate(cfg_json)
    t0 = time.perf_counter()
    try:
        with locked(out):
            results = run(cfg, Path(out), methods, trials)
            agg = write_report(Path(out), results, run_title(cfg))
            plot_run(Path(out), results, agg)
        return {"name": cfg.name, "aggregate": agg, "wall_time_s": time.perf_counter() - t0}
    except Exception as e:  # noqa: BLE001 — one configuration must not end the sweep
        return {"name": cfg.name, "error": f"{type(e).__name__}: {e}",
                "traceback": traceback.format_exc(), "wall_time_s": time.perf_counter() - t0}


def run_sweep(grid: GridConfig, configs: list[RigConfig], out: Path, workers: int = 1,
              progress=None) -> dict:
    """Every configuration into OUT/<name>/ (each holding its own run directory's lock), with
    the sweep's lock on OUT; sweep.json and sweep.md last."""
    if not 1 <= workers <= 64:
        raise ValueError(f"--workers: expected 1..64, got {workers}")
    with locked(out) as out:
        jobs = [(c.model_dump(mode="json"), str(out / c.name), grid.methods, grid.trials)
                for c in configs]
        t0 = time.perf_counter()
        rows = {}
        with process_pool(workers) as pool:
            futures = [pool.submit(_run_config, j) for j in jobs]
            for n, fut in enumerate(as_completed(futures), 1):
                row = fut.result()
                rows[row["name"]] = row
                if progress:
                    progress(n, len(jobs))
        result = {"name": grid.name, "workers": workers,
                  "wall_time_s": time.perf_counter() - t0,
                  "configurations": [rows[c.name] for c in configs]}
        result["stage_time_s"] = {
            stage: sum(r["aggregate"]["timing"][stage]["mean"] * r["aggregate"]["trials"]
                       for r in result["configurations"] if "aggregate" in r
                       and r["aggregate"]["timing"][stage]["n"])
            for stage in ("render_s", "detect_s", "calibrate_s", "rig_s")}
        write_json(out / "sweep.json", result)
        write_text(out / "sweep.md", sweep_markdown(result, grid.methods))
    return result


def sweep_markdown(result: dict, methods: list[str]) -> str:
    cols = [("RPE_RMS px", "calibration"), ("proj. diff mean px", "calibration"),
            ("RMSE_cal mm", "rig")]
    lines = [f"# {result['name']}", "",
             f"{len(result['configurations'])} configurations, wall time "
             f"{result['wall_time_s']:.0f} s with {result['workers']} worker(s); summed stage "
             "times (s): " + ", ".join(f"{k[:-2]} {v:.0f}"
                                       for k, v in result["stage_time_s"].items()), "",
             "Per camera for mono columns (camera: value); mean ± std over trials.", "",
             "| configuration | method | " + " | ".join(c for c, _ in cols) + " |",
             "|---|---|" + "---|" * len(cols)]
    for row in result["configurations"]:
        if "error" in row:
            lines.append(f"| {row['name']} | all | failed: {row['error']} |")
            continue
        agg = row["aggregate"]
        for m in methods:
            cells = []
            for col, section in cols:
                if section == "rig":
                    cells.append(fmt(agg["rig"][m][col]) if "rig" in agg else "")
                else:
                    cells.append("; ".join(f"{cam}: {fmt(r[col])}"
                                           for cam, r in agg["calibration"][m].items()))
            lines.append(f"| {row['name']} | {m} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
