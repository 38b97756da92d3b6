"""The end-to-end commands on small rigs: results, reuse of complete stages, recorded failures."""

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from stereo_bench.cli import main
from stereo_bench.config.schema import parse_rig
from stereo_bench.run.pipeline import load_run, run
from quickstart import quickstart

ROOT = Path(__file__).resolve().parents[2]


def small_rig(frames=8, **changes):
    d = quickstart(frames)
    d.update(changes)
    return d


def test_run_scores_rig_and_reuses_complete_stages(tmp_path):
    cfg = parse_rig(small_rig())
    out = tmp_path / "run"
    first = run(cfg, out, ["bouguet", "opencv"])[0]
    rig = first["rig"]["bouguet"]
    # Clean renders of a camera inside Bouguet's model: sub-millimetre triangulation.
    assert rig["rmse_cal_mm"] < 0.5
    assert rig["rig_errors"]["rotation_deg"][0] < 0.05
    assert first["calibration"]["bouguet"]["left"]["projection_difference"]["mean_px"] < 0.5
    stamp = (out / "trials" / "seed_7" / "metrics.json").stat().st_mtime_ns
    second = run(cfg, out, ["bouguet", "opencv"])[0]
    assert (out / "trials" / "seed_7" / "metrics.json").stat().st_mtime_ns == stamp
    assert second["rig"]["bouguet"]["rmse_cal_mm"] == rig["rmse_cal_mm"]
    trial = load_run(out)[0]
    assert trial.seed == 7 and set(trial.rigs) == {"bouguet", "opencv"}
    assert np.allclose(trial.rigs["bouguet"][0].tvec, 0)  # camera 0 is the estimate's world


def test_a_camera_that_never_finds_the_board_is_recorded(tmp_path):
    d = small_rig(frames=4)
    tiny = dict(d["cameras"][1], name="tiny", width=40, height=30, fx=37.5, fy=28.0, cx=20.0,
                cy=15.0)
    d["cameras"][1] = tiny
    result = run(parse_rig(d), tmp_path / "run", ["opencv"])[0]
    assert "error" in result["calibration"]["opencv"]["tiny"]
    assert "projection_difference" in result["calibration"]["opencv"]["left"]
    assert "error" in result["rig"]["opencv"]


def test_cameras_calibrated_side_by_side_are_calibrated_as_one_by_one(tmp_path):
    """With worker processes the cameras are calibrated side by side: the same entries (a
    camera that fails included) and the same rigs as in this process, one camera after the
    other."""
    d = small_rig(frames=4)
    d["cameras"].append(dict(d["cameras"][1], name="tiny", width=40, height=30, fx=37.5,
                             fy=28.0, cx=20.0, cy=15.0))
    cfg = parse_rig(d)

    def timeless(x):
        if isinstance(x, dict):
            return {k: timeless(v) for k, v in x.items() if not k.endswith("time_s")}
        return [timeless(v) for v in x] if isinstance(x, list) else x
    one, two = (run(cfg, tmp_path / f"w{w}", ["zhang", "opencv"], workers=w)[0] for w in (1, 2))
    assert "error" in one["calibration"]["opencv"]["tiny"]
    assert timeless(one["calibration"]) == timeless(two["calibration"])
    assert timeless(one["rig"]) == timeless(two["rig"])


def test_cli_run_writes_report_and_plots(tmp_path):
    rig = tmp_path / "rig.yaml"
    rig.write_text(yaml.safe_dump(small_rig(frames=6)))
    out = tmp_path / "out"
    assert main([str(rig), "--out", str(out), "--methods", "zhang,bouguet"]) == 0
    results = json.loads((out / "results.json").read_text())
    assert set(results["aggregate"]["rig"]) == {"zhang", "bouguet"}
    assert "Table 4" in (out / "report.md").read_text()
    assert {p.name for p in (out / "plots").glob("*.png")} >= {
        "metrics.png", "residuals.png", "trajectory.png", "projection_difference_left.png"}


def test_cli_errors_name_the_problem(tmp_path, capsys):
    assert main(["configs/quickstart.yaml", "--methods", "zhang,magic"]) == 2
    assert "magic" in capsys.readouterr().err
    assert main(["calibrate", str(tmp_path)]) == 2
    assert "manifest.json" in capsys.readouterr().err


def test_sweep_writes_one_table(tmp_path):
    grid = tmp_path / "grid.yaml"
    grid.write_text(yaml.safe_dump({
        "name": "g", "rigs": [str(ROOT / "configs" / "quickstart.yaml")],
        "patterns": ["checkerboard", "asymmetric_circles"], "environments": ["clean"],
        "methods": ["opencv"], "frames": 5}))
    assert main(["sweep", str(grid), "--out", str(tmp_path / "s"), "--workers", "1"]) == 0
    table = (tmp_path / "s" / "sweep.md").read_text()
    assert "quickstart_checkerboard_clean" in table and "quickstart_asymmetric_circles_clean" in table
    result = json.loads((tmp_path / "s" / "sweep.json").read_text())
    assert set(result["stage_time_s"]) == {"render_s", "detect_s", "calibrate_s", "rig_s"}


@pytest.mark.parametrize("bad", [{"rigs": []}, {"rigs": ["missing.yaml"]}, {"colour": 1}])
def test_bad_grid_is_an_error(tmp_path, capsys, bad):
    grid = tmp_path / "grid.yaml"
    grid.write_text(yaml.safe_dump({"rigs": ["x.yaml"], "patterns": ["checkerboard"], **bad}))
    assert main(["sweep", str(grid)]) == 2
    assert str(grid) in capsys.readouterr().err


@pytest.mark.parametrize("option", [["--workers", "0"], ["--trials", "0"], ["--workers", "65"]])
def test_a_refused_option_leaves_no_folder(tmp_path, capsys, option):
    out = tmp_path / "run"
    assert main([str(Path(__file__).parents[2] / "configs" / "quickstart.yaml"), "--out",
                 str(out), *option]) == 2
    assert "--workers: expected 1..64" in capsys.readouterr().err
    assert not out.exists()


def test_views_with_too_few_or_collinear_points_are_left_out_and_said():
    from stereo_bench.core.camera import Camera
    from stereo_bench.detect.dataset import CameraDetections
    from stereo_bench.evaluate.stage import observations
    from stereo_bench.core.patterns import Checkerboard

    obj = Checkerboard().object_points()  # 8 x 11 corners, row by row
    pts = np.full((3, len(obj), 2), np.nan)
    pts[0] = obj[:, :2] * 2 + 100  # a whole board
    pts[1, :8] = obj[:8, :2] * 2 + 100  # one row of 8 corners: collinear
    pts[2, :5] = obj[:5, :2] * 2 + 100  # five corners
    det = CameraDetections("c", "checkerboard", "classic", pts, np.ones(3, bool),
                           np.arange(len(obj)))
    obs, dropped = observations(det, obj, Camera("c", 640, 480, 500, 500, 320, 240))
    assert obs.view_ids == [0]
    assert "collinear" in dropped[1] and "5 points" in dropped[2]
