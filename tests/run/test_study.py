"""stereo-bench study: the cost model and its threshold, the study file's refusals, and a small
study end to end (calibration sessions, then the pose costs, then the report)."""

import json
import math

import numpy as np
import pytest
import yaml

from stereo_bench.cli import main
from stereo_bench.config.schema import ConfigError
from stereo_bench.run.study import cost_curve, load_study

from tests.quickstart import ROOT

STUDIO = {
    "name": "studio3", "seed": 0,
    "studio": {"layout": "ring", "count": 3, "radius_mm": 3000.0, "height_mm": [1600.0],
               "look_at_mm": [0.0, 0.0, 1000.0],
               "lenses": [{"width": 640, "height": 480, "fx": 520.0, "fy": 520.0, "cx": 319.5,
                           "cy": 239.5, "dist": [-0.1, 0.05, 0.0, 0.0, 0.0]}]},
    "pattern": {"kind": "checkerboard", "squares_x": 8, "squares_y": 6, "square_mm": 100.0},
    "trajectory": {"kind": "session", "frames": 40, "turns": 3, "closeups": 8},
}


def _study(tmp_path, **pose) -> str:
    (tmp_path / "studio3.yaml").write_text(yaml.safe_dump(STUDIO))
    study = {"name": "tiny", "rigs": ["studio3.yaml"], "environments": ["clean"],
             "methods": ["zhang", "tsai"], "trials": 2,
             "pose": {"motions": ["walk_circle"], "frames": 8,
                      "detectors": ["gaussian", "blazepose_fit"], **pose}}
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(study))
    return str(path)


def test_cost_curve_recovers_the_slope_and_the_threshold():
    k, share = 0.8, 0.1
    points = []
    for floor in (5.0, 6.0):
        for r in (0.5, 2.0, 8.0, 30.0):
            points.append({"rmse_cal_mm": r, "floor_mm": floor,
                           "cost_mm": math.sqrt(floor ** 2 + (k * r) ** 2) - floor})
    c = cost_curve(points, share)
    assert c["k"] == pytest.approx(k, rel=1e-6)
    assert c["residual_rms_mm"] < 1e-6
    # At the threshold the model's cost is the share of the (median) floor.
    F, R = c["floor_mm"], c["threshold_rmse_cal_mm"]
    assert math.sqrt(F ** 2 + (k * R) ** 2) - F == pytest.approx(share * F, rel=1e-6)
    assert "reason" in cost_curve(points[:1], share)
    flat = [dict(p, cost_mm=0.0) for p in points]
    assert "threshold_rmse_cal_mm" not in cost_curve(flat, share)


@pytest.mark.parametrize("pose, message", [
    ({"motions": ["moonwalk"]}, r"pose.motions: .*moonwalk"),
    ({"detectors": ["openpose"]}, r"pose.detectors.0"),
    ({"frames": 1}, r"pose.frames"),
    ({"detectors": ["gaussian", "blazepose"], "rendered_studios": ["elsewhere"]},
     r"pose.rendered_studios: \['elsewhere'\] are none of the study's rig files"),
    ({"rendered_studios": ["studio3"]}, r"blazepose detector renders; it is not in"),
    ({"detector_model": "missing.json"}, r"pose.detector_model: .*missing.json is not a file"),
    ({"colour": "red"}, r"pose.colour: unknown key"),
    ({"detector_model": "bad.json"}, r"pose.detector_model: .*bad.json: expected a mapping"),
])
def test_study_file_refusals_name_the_field(tmp_path, pose, message):
    (tmp_path / "bad.json").write_text("[1, 2]")
    with pytest.raises(ConfigError, match=message):
        load_study(_study(tmp_path, **pose))


@pytest.mark.parametrize("path", sorted((ROOT / "configs" / "studies").glob("*.yaml")),
                         ids=lambda p: p.stem)
def test_shipped_studies_load(path):
    study = load_study(path)
    assert study.sweep.configurations and study.pose.motions


def test_small_study_end_to_end(tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["study", _study(tmp_path), "--out", str(out), "--workers", "2"]) == 0
    result = json.loads((out / "study.json").read_text())
    for name in ("study.md", "study.html", "study_studio3.png", "calibration/sweep.json"):
        assert (out / name).is_file(), name
    (config,) = result["configurations"]
    assert config["name"] == "studio3_checkerboard_clean"
    for d in ("gaussian", "blazepose_fit"):
        pose = config["pose"][d]
        assert pose["floor_mm"]["n"] == 2 and pose["floor_mm"]["mean"] > 0
        assert {p["method"] for p in pose["points"]} == {"zhang", "tsai"}
    # Each point pairs a calibration's cost with its own RMSE_cal, as the sweep scored it.
    sweep = json.loads((out / "calibration" / "sweep.json").read_text())
    (row,) = sweep["configurations"]
    rmse = {(t["seed"], m): t["methods"][m]["rmse_cal_mm"] for t in row["per_trial"]
            for m in ("zhang", "tsai")}
    points = config["pose"]["gaussian"]["points"]
    assert len(points) == 4
    for p in points:
        assert p["rmse_cal_mm"] == pytest.approx(rmse[p["seed"], p["method"]])
    curve = next(c for c in result["curves"] if c["detector"] == "gaussian")
    assert curve["n"] == 4 and curve["k"] > 0
    # The fitted BlazePose detector's floor is BlazePose's (tens of mm), the Gaussian's a few.
    floors = {d: config["pose"][d]["floor_mm"]["mean"] for d in ("gaussian", "blazepose_fit")}
    assert floors["blazepose_fit"] > 3 * floors["gaussian"]
    text = (out / "study.md").read_text()
    assert "## The answer" in text and "## Pose cost (mm), synthetic, Gaussian" in text
    assert np.isfinite(result["wall_time_s"]["total"])
