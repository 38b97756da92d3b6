"""The board's shape fitted in calibration (refine.py's ``board``; zhang's and bouguet's
``board_warp``; ``calibration.fit_board_warp``): on renders of a board bowed and stretched by a
known amount (mrcal's two-parabola warp and an aspect error, render/imaging's board), the
estimate recovers both within its own 2 sigma, the RPE falls to a flat board's and so does the
projection difference."""

import json
from pathlib import Path

import pytest
import yaml

from stereo_bench.cli import main

RIG = Path(__file__).resolve().parents[2] / "configs" / "paper" / "wide_mono.yaml"


def run(tmp_path, warp, fit, method="zhang-brown"):
    rig = yaml.safe_load(RIG.read_text())
    rig["trajectory"]["frames"] = 40
    rig["environment"] = {"kind": "clean", "board": {"warp_mm": [warp, 0.6 * warp],
                                                     "aspect_error_pct": 0.2 * warp}}
    rig["calibration"] = {"fit_board_warp": fit}
    path = tmp_path / f"rig_{warp}_{fit}.yaml"
    path.write_text(yaml.safe_dump(rig))
    out = tmp_path / f"out_{warp}_{fit}"
    assert main(["run", str(path), "--out", str(out), "--methods", method]) == 0
    trial = json.loads((out / "results.json").read_text())["trials"][0]
    return trial["calibration"][method]["wide"]


@pytest.fixture(scope="module")
def flat(tmp_path_factory):
    return run(tmp_path_factory.mktemp("flat"), 0.0, False)


# 1 mm by default; 0.5 and 2 mm (the closing figures) with -m slow.
@pytest.mark.parametrize("warp", [pytest.param(0.5, marks=pytest.mark.slow), 1.0,
                                  pytest.param(2.0, marks=pytest.mark.slow)])
def test_a_bowed_board_is_recovered_and_its_cost_removed(tmp_path, flat, warp):
    bowed, fitted = run(tmp_path, warp, False), run(tmp_path, warp, True)
    w = fitted["log"]["board_warp_mm"]
    std = fitted["log"]["param_std"]
    print(warp, w, std["warp_x_mm"], std["warp_y_mm"], flat["rpe_rms_px"], bowed["rpe_rms_px"],
          fitted["rpe_rms_px"], flat["projection_difference"]["mean_px"],
          bowed["projection_difference"]["mean_px"], fitted["projection_difference"]["mean_px"])
    assert abs(w[0] - warp) < 2 * std["warp_x_mm"] + 0.01
    assert abs(w[1] - 0.6 * warp) < 2 * std["warp_y_mm"] + 0.01
    aspect = fitted["log"]["board_aspect_error_pct"]
    print("aspect", aspect, std["aspect_error_pct"])
    assert abs(aspect - 0.2 * warp) < 2 * std["aspect_error_pct"] + 0.005
    # The bow's cost: the flat fit's RPE and projection difference grow with it; fitted, both
    # are back at the flat board's.
    assert bowed["rpe_rms_px"] > 2 * flat["rpe_rms_px"]
    assert fitted["rpe_rms_px"] < 1.2 * flat["rpe_rms_px"]
    assert (fitted["projection_difference"]["mean_px"]
            < 1.5 * flat["projection_difference"]["mean_px"] + 0.02)


def test_bouguet_fits_the_warp_too(tmp_path):
    """bouguet-brown: its recomputed extrinsics hold the warp fitted so far."""
    fitted = run(tmp_path, 1.0, True, "bouguet-brown")
    w, std = fitted["log"]["board_warp_mm"], fitted["log"]["param_std"]
    assert abs(w[0] - 1.0) < 2 * std["warp_x_mm"] + 0.01
    assert abs(w[1] - 0.6) < 2 * std["warp_y_mm"] + 0.01
    assert fitted["projection_difference"]["mean_px"] < 0.3  # flat: 10 px


def test_the_warps_jacobian_matches_finite_differences():
    """d residuals / d (w_x, w_y, aspect) of refine's problem against central differences."""
    import numpy as np

    from stereo_bench.calibrate.refine import CameraModel, _Problem
    from stereo_bench.core.board_shape import BoardShape
    from stereo_bench.core.camera import Camera
    from stereo_bench.core.patterns import Checkerboard

    cam = Camera("c", 640, 480, 600, 450, 320, 240, 0.5, [0.5, 0.1, 0.03, 0, 0, 0, 0, 0])
    obj = Checkerboard().object_points()
    rng = np.random.default_rng(2)
    rv = rng.normal(0, 0.3, (3, 3))
    tv = np.array([[-60.0, -80.0, 400.0], [-40.0, -60.0, 350.0], [-70.0, -90.0, 450.0]])
    model = CameraModel("opencv")
    free = np.r_[np.zeros(len(model.param_names), bool), True, True, True]
    problem = _Problem(model, free, [obj] * 3, [np.zeros((len(obj), 2))] * 3,
                       BoardShape.of_points(obj))
    x = np.r_[model.params_of(cam), 0.7, -0.4, 0.3]
    J = problem.residuals(x, rv, tv, jacobians=True)[1]
    for k in range(3):
        dx = np.zeros_like(x)
        dx[-3 + k] = 1e-6
        fd = (problem.residuals(x + dx, rv, tv) - problem.residuals(x - dx, rv, tv)) / 2e-6
        assert np.abs(J[:, :, k] - fd).max() < 1e-6 * np.abs(fd).max()


def test_a_rig_on_a_bowed_board_triangulates_the_physical_board(tmp_path):
    """The quick-start pair with its board bowed by (1.5, 0.9) mm: fitting the warp, each
    camera's calibration and the rig's adjustment (its board bowed by the cameras' mean fit)
    triangulate the board to a tenth of a millimetre of its physical points (the truth
    RMSE_cal is scored against); without, 26 mm."""
    rig = yaml.safe_load((RIG.parents[1] / "quickstart.yaml").read_text())
    rig["environment"] = {"kind": "clean", "board": {"warp_mm": [1.5, 0.9]}}
    out = {}
    for fit in (False, True):
        rig["calibration"] = {"fit_board_warp": fit}
        path = tmp_path / f"rig_{fit}.yaml"
        path.write_text(yaml.safe_dump(rig))
        assert main(["run", str(path), "--out", str(tmp_path / str(fit)), "--methods",
                     "zhang-brown"]) == 0
        out[fit] = json.loads((tmp_path / str(fit) / "results.json").read_text())[
            "aggregate"]["rig"]["zhang-brown"]["RMSE_cal mm"]["mean"]
    assert out[True] < 0.2 and out[False] > 10  # measured 0.088 and 25.8 mm
