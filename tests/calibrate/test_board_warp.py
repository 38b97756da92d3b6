"""The board's warp fitted in calibration (refine.py's ``board``; zhang's ``board_warp``;
``calibration.fit_board_warp``): on renders of a board bowed by a known amount (mrcal's
two-parabola model, render/imaging's board), the estimate recovers the bow within its own 2
sigma, the RPE falls to a flat board's and so does the projection difference."""

import json
from pathlib import Path

import pytest
import yaml

from stereo_bench.cli import main

RIG = Path(__file__).resolve().parents[2] / "configs" / "paper" / "wide_mono.yaml"


def run(tmp_path, warp, fit):
    rig = yaml.safe_load(RIG.read_text())
    rig["trajectory"]["frames"] = 40
    rig["environment"] = {"kind": "clean", "board": {"warp_mm": [warp, 0.6 * warp]}}
    rig["calibration"] = {"fit_board_warp": fit}
    path = tmp_path / f"rig_{warp}_{fit}.yaml"
    path.write_text(yaml.safe_dump(rig))
    out = tmp_path / f"out_{warp}_{fit}"
    assert main(["run", str(path), "--out", str(out), "--methods", "zhang-brown"]) == 0
    trial = json.loads((out / "results.json").read_text())["trials"][0]
    return trial["calibration"]["zhang-brown"]["wide"]


@pytest.fixture(scope="module")
def flat(tmp_path_factory):
    return run(tmp_path_factory.mktemp("flat"), 0.0, False)


@pytest.mark.parametrize("warp", [0.5, 1.0, 2.0])
def test_a_bowed_board_is_recovered_and_its_cost_removed(tmp_path, flat, warp):
    bowed, fitted = run(tmp_path, warp, False), run(tmp_path, warp, True)
    w = fitted["log"]["board_warp_mm"]
    std = fitted["log"]["param_std"]
    print(warp, w, std["warp_x_mm"], std["warp_y_mm"], flat["rpe_rms_px"], bowed["rpe_rms_px"],
          fitted["rpe_rms_px"], flat["projection_difference"]["mean_px"],
          bowed["projection_difference"]["mean_px"], fitted["projection_difference"]["mean_px"])
    assert abs(w[0] - warp) < 2 * std["warp_x_mm"] + 0.01
    assert abs(w[1] - 0.6 * warp) < 2 * std["warp_y_mm"] + 0.01
    # The bow's cost: the flat fit's RPE and projection difference grow with it; fitted, both
    # are back at the flat board's.
    assert bowed["rpe_rms_px"] > 2 * flat["rpe_rms_px"]
    assert fitted["rpe_rms_px"] < 1.2 * flat["rpe_rms_px"]
    assert (fitted["projection_difference"]["mean_px"]
            < 1.5 * flat["projection_difference"]["mean_px"] + 0.02)
