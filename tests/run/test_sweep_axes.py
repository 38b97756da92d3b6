"""Sweeps over any rig-file field: axis expansion, refusals, intervals, curves and pairing."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy import stats

from stereo_bench.cli import main
from stereo_bench.config.bounds import ConfigError
from stereo_bench.core.files import is_safe_name
from stereo_bench.run.grid import load_grid
from stereo_bench.run.sweep_stats import t_interval

ROOT = Path(__file__).resolve().parents[2]
QUICKSTART = ROOT / "configs" / "quickstart.yaml"
NOISE = "environment.sensor.noise_sigma"  # the additive noise's field


def tiny_rig(tmp_path: Path, name: str = "tiny", frames: int = 8, noisy: bool = False) -> Path:
    d = yaml.safe_load(QUICKSTART.read_text())
    d["trajectory"]["frames"] = frames
    if noisy:
        d["environment"] = {"kind": "noisy"}
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(d))
    return path


def grid_file(tmp_path: Path, **grid) -> Path:
    path = tmp_path / "grid.yaml"
    path.write_text(yaml.safe_dump({"name": "g", "methods": ["opencv", "zhang"], **grid},
                                  sort_keys=False))
    return path


# ------------------------------------------------------------------------------------------
# Intervals
# ------------------------------------------------------------------------------------------

def test_t_interval_matches_scipy_and_hand_values():
    data = [0.31, 0.42, 0.29, 0.55, 0.38, 0.47, 0.33]
    ci = t_interval(data)
    low, high = stats.t.interval(0.95, len(data) - 1, loc=np.mean(data),
                                 scale=stats.sem(data))
    assert ci["n"] == 7 and ci["mean"] == pytest.approx(np.mean(data), abs=1e-15)
    assert ci["std"] == pytest.approx(np.std(data, ddof=1), rel=1e-12)
    assert (ci["ci_low"], ci["ci_high"]) == pytest.approx((low, high), rel=1e-12)
    # 1..5: mean 3, s = sqrt(2.5), t(0.975, 4) = 2.776445: 3 -+ 1.963243.
    ci = t_interval([1, 2, 3, 4, 5])
    assert (ci["ci_low"], ci["ci_high"]) == pytest.approx((1.036757, 4.963243), abs=1e-6)
    # Non-finite values are left out; one value has no interval.
    ci = t_interval([2.0, float("nan"), None])
    assert ci["n"] == 1 and ci["mean"] == 2.0 and math.isnan(ci["ci_low"])


# ------------------------------------------------------------------------------------------
# Expansion
# ------------------------------------------------------------------------------------------

def test_axes_are_crossed_named_and_set_at_their_paths(tmp_path):
    rig = tiny_rig(tmp_path)
    sweep = load_grid(grid_file(tmp_path, rigs=[rig.name], patterns=["checkerboard", "charuco"],
                                axes={"trajectory.frames": [8, 12],
                                      "cameras.*.dist.0": [0.3, 0.45],
                                      "cameras.1.fx": [610.0]}))
    configs = sweep.configurations
    assert len(configs) == 2 * 2 * 2
    assert configs[0].name == "tiny_checkerboard_clean_frames-8_dist.0-0.3"
    assert configs[-1].name == "tiny_charuco_clean_frames-12_dist.0-0.45"
    assert len({c.name for c in configs}) == 8 and all(is_safe_name(c.name) for c in configs)
    for c in configs:
        cfg = c.config
        assert cfg.name == c.name
        assert cfg.pattern.kind == c.axes["pattern.kind"]
        assert cfg.trajectory.frames == c.axes["trajectory.frames"]
        assert [cam.dist[0] for cam in cfg.cameras] == [c.axes["cameras.*.dist.0"]] * 2
        assert [cam.fx for cam in cfg.cameras] == [600.0, 610.0]  # one camera only
        assert cfg.cameras[0].dist[1] == 0.1  # the rest of the list stays the rig file's
    assert sweep.trials == 1 and "clean" in sweep.trials_reason


def test_the_paper_grid_keeps_its_names_and_meaning():
    sweep = load_grid(ROOT / "configs" / "grids" / "paper.yaml")
    names = [c.name for c in sweep.configurations]
    rigs = ["rectilinear_mono", "wide_mono", "rectilinear_pair", "wide_pair", "mixed_pair"]
    assert names == [f"{r}_{p}_{e}" for r in rigs
                     for p in ("checkerboard", "symmetric_circles", "asymmetric_circles",
                               "charuco") for e in ("clean", "noisy")]
    assert sweep.trials == 1
    noisy = sweep.configurations[1].config
    assert noisy.environment.kind == "noisy" and noisy.pattern.kind == "checkerboard"
    assert noisy.trajectory.frames == 127


def test_default_trials_ten_when_noisy_and_an_explicit_count_wins(tmp_path):
    rig = tiny_rig(tmp_path)
    assert load_grid(grid_file(tmp_path, rigs=[rig.name], axes={NOISE: [1, 2]})).trials == 10
    assert load_grid(grid_file(tmp_path, rigs=[rig.name],
                               environments=["clean", "noisy"])).trials == 10
    assert load_grid(grid_file(tmp_path, rigs=[rig.name], axes={NOISE: [1, 2]},
                               trials=3)).trials == 3
    assert load_grid(grid_file(tmp_path, rigs=[rig.name],
                               axes={"trajectory.tilt_deg": [10, 30]})).trials == 1
    # A bowed board without sensor noise renders the same images for every seed.
    assert load_grid(grid_file(tmp_path, rigs=[rig.name],
                               axes={"environment.board.warp_mm": [[0, 0], [1, 1]]})).trials == 1


def test_a_name_too_long_for_a_folder_is_shortened_and_stays_unique(tmp_path):
    rig = tiny_rig(tmp_path, name="a_rig_file_whose_name_alone_takes_most_of_a_folder_name")
    configs = load_grid(grid_file(tmp_path, rigs=[rig.name],
                                  axes={"trajectory.tilt_deg": [10.5, 10.25]})).configurations
    assert all(is_safe_name(c.name) and len(c.name) == 64 for c in configs)
    assert configs[0].name != configs[1].name


@pytest.mark.parametrize("axes, message", [
    ({"environment.nois_sigma": [1]},
     r"axes\.environment\.nois_sigma: no such field in rig file tiny\.yaml \(fields of "
     r"environment: kind, "),
    ({"trajectori.frames": [8]}, r"axes\.trajectori\.frames: no such field .*top-level fields"),
    ({"cameras.2.fx": [500.0]}, r"axes\.cameras\.2\.fx: cameras is a list of 2"),
    ({"trajectory.frames": [8, 0]}, r"axes\.trajectory\.frames: value 0 in rig file tiny\.yaml"
                                    r".*\n  trajectory\.frames: Input should be greater than 0"),
    ({"cameras.*.dist.0": ["wide"]}, r"axes\.cameras\.\*\.dist\.0: value \"wide\""),
    ({"trajectory.tilt_deg": [10, 10]}, r"axes\.trajectory\.tilt_deg: listed twice"),
    ({"trajectory.tilt_deg": [10, 10.0]}, r"configurations \[.*tilt_deg-10.\] would run twice"),
])
def test_bad_axes_are_refused_through_the_cli_before_anything_runs(tmp_path, capsys, axes,
                                                                   message):
    import re

    rig = tiny_rig(tmp_path)
    grid = grid_file(tmp_path, rigs=[rig.name], axes=axes)
    out = tmp_path / "out"
    assert main(["sweep", str(grid), "--out", str(out), "--workers", "1"]) == 2
    err = capsys.readouterr().err
    assert str(grid) in err.replace("\n", "") and "Traceback" not in err
    assert re.search(message, err), err
    assert not out.exists()


def test_a_legacy_list_and_its_axis_together_are_refused(tmp_path):
    rig = tiny_rig(tmp_path)
    with pytest.raises(ConfigError, match="patterns and axes.pattern.kind say the same"):
        load_grid(grid_file(tmp_path, rigs=[rig.name], patterns=["charuco"],
                            axes={"pattern.kind": ["checkerboard"]}))


# ------------------------------------------------------------------------------------------
# A real sweep
# ------------------------------------------------------------------------------------------

def _per_trial(run_dir: Path) -> dict[int, dict]:
    """Per seed, per method: (mean projection difference over cameras, RMSE_cal), read back
    from the configuration's own results.json."""
    trials = json.loads((run_dir / "results.json").read_text())["trials"]
    out = {}
    for t in trials:
        out[t["seed"]] = {m: (np.mean([e["projection_difference"]["mean_px"]
                                       for e in cams.values()]), t["rig"][m]["rmse_cal_mm"])
                          for m, cams in t["calibration"].items()}
    return out


def test_a_small_sweep_gives_curves_and_paired_differences_of_its_trials(tmp_path, capsys):
    rig = tiny_rig(tmp_path, noisy=True)
    grid = grid_file(tmp_path, rigs=[rig.name], axes={NOISE: [1, 2, 4]}, trials=2)
    out = tmp_path / "out"
    # A configuration that cannot write its folder fails; the others must complete.
    out.mkdir()
    (out / "tiny_checkerboard_noisy_noise_sigma-2").write_text("in the way")
    assert main(["sweep", str(grid), "--out", str(out), "--workers", "2"]) == 0
    assert "tiny_checkerboard_noisy_noise_sigma-2" in capsys.readouterr().err
    result = json.loads((out / "sweep.json").read_text())
    assert result["failed"] == ["tiny_checkerboard_noisy_noise_sigma-2"]
    assert result["trials_per_configuration"] == 2
    ok = ["tiny_checkerboard_noisy_noise_sigma-1", "tiny_checkerboard_noisy_noise_sigma-4"]
    read = {name: _per_trial(out / name) for name in ok}
    assert all(sorted(r) == [7, 8] for r in read.values())  # seeds: the rig's 7, then 8

    [curve] = result["curves"]
    assert curve["axis"] == NOISE and curve["values"] == [1, 2, 4]
    assert set(curve["metrics"]) == {"projection_difference_mean_px", "rmse_cal_mm",
                                     "detection_rate", "detection_error_px"}
    assert (out / curve["figure"]).stat().st_size > 10_000
    proj = curve["metrics"]["projection_difference_mean_px"]["lines"]
    assert [ln["label"] for ln in proj] == ["opencv", "zhang"]
    assert len(curve["metrics"]["detection_rate"]["lines"]) == 1
    for k, line in enumerate(proj):
        failed, *_ = [p for p in line["points"] if p["n"] == 0]
        assert failed["x"] == 2 and "failed" in failed
        for p in line["points"]:
            if p["n"] == 0:
                continue
            vals = [read[p["configuration"]][s][line["method"]][0] for s in (7, 8)]
            assert p["n"] == 2 and p["mean"] == pytest.approx(np.mean(vals), rel=1e-12)
            low, high = stats.t.interval(0.95, 1, loc=np.mean(vals), scale=stats.sem(vals))
            assert (p["ci_low"], p["ci_high"]) == pytest.approx((low, high), rel=1e-9)

    methods = [c for c in result["comparisons"] if c["kind"] == "methods"]
    assert len(methods) == 3 * 2  # per configuration: projection difference and RMSE_cal
    for c in methods:
        [name] = c["configurations"]
        if name in result["failed"]:
            assert c["n"] == 0 and c["verdict"].startswith("not compared: configuration")
            continue
        column = 0 if c["metric"] == "projection_difference_mean_px" else 1
        expected = [read[name][s]["opencv"][column] - read[name][s]["zhang"][column]
                    for s in (7, 8)]
        assert [d["difference"] for d in c["differences"]] == pytest.approx(expected,
                                                                            rel=1e-12)
        assert c["mean_difference"] == pytest.approx(np.mean(expected), rel=1e-12)
        beats = c["ci_high"] < 0 or c["ci_low"] > 0
        assert ("beats" in c["verdict"]) == beats
        if not beats:
            assert c["verdict"] == "no difference shown at n=2"
    md = (out / "sweep.md").read_text()
    assert "## Curves" in md and "## Paired comparisons" in md
    assert "tiny_checkerboard_noisy_noise_sigma-2: configuration failed" in md
    # The configurations that ran have their own complete run directories.
    assert all((out / name / "report.md").is_file() for name in ok)


def test_the_curves_are_drawn_here_when_the_cluster_cannot_draw_them(tmp_path, monkeypatch):
    """The curves' figures go to the cluster's workers once every configuration is done; a
    cluster lost by then must not cost the sweep its tables and figures: they are drawn in the
    command's own process instead."""
    from distributed import Client

    mapped = Client.map

    def lost_on_curves(self, func, *args, **kwargs):
        if getattr(func, "__name__", "") == "plot_sweep_curve":
            raise OSError("the cluster went away")
        return mapped(self, func, *args, **kwargs)

    monkeypatch.setattr(Client, "map", lost_on_curves)
    rig = tiny_rig(tmp_path, noisy=True)
    grid = grid_file(tmp_path, rigs=[rig.name], axes={NOISE: [1, 2]}, trials=1)
    out = tmp_path / "out"
    assert main(["sweep", str(grid), "--out", str(out), "--workers", "1"]) == 0
    result = json.loads((out / "sweep.json").read_text())
    assert result["failed"] == []
    [curve] = result["curves"]
    assert (out / curve["figure"]).stat().st_size > 10_000
