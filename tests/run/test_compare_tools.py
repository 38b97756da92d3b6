"""stereo-bench compare-tools: other calibrators run as their users run them, read back from
their own files and scored against the truth (stereo_bench/tools, run/compare.py)."""

import json
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from quickstart import quickstart
from stereo_bench.cli import main
from stereo_bench.config.schema import parse_rig
from stereo_bench.run.compare import CHI2_2D_68, check_uncertainty, projection_errors, wilson
from stereo_bench.run.exchange import score_cameras
from stereo_bench.scene.dataset import write_dataset
from stereo_bench.tools import Session, ToolError, ToolResult, module, parse_tools


@pytest.fixture(scope="module")
def exact(tmp_path_factory):
    """The quick-start pair (16 frames) with its exact image points as the detections."""
    ds = write_dataset(parse_rig(quickstart(16)), tmp_path_factory.mktemp("exact") / "ds")
    gt = ds.ground_truth
    points = np.where(gt.visible[..., None], gt.points, np.nan)
    session = Session([c.name for c in ds.cameras], [c.size for c in ds.cameras],
                      ds.object_points, points, gt.visible.all(-1), ds.pattern)
    return ds, session


# Noise-free detections: the suite's own solver and pycolmap's (float64 throughout) find the
# truth to rounding; OpenCV rounds its inputs to float32 (1e-4 px measured); mrcal's defaults
# regularize the distortion and fit the board's warp, and its OPENCV8 rational terms are not
# identified by planar views: 0.01 px mean, 0.18 px at the image's corners (measured).
TOLERANCE_PX = {"synthcal": 1e-9, "synthcal-warp": 1e-9, "pycolmap": 1e-9, "opencv-stereo": 5e-4,
                "opencv-multiview": 5e-4, "mrcal": 0.05}


@pytest.mark.parametrize("name", list(TOLERANCE_PX))
def test_every_tool_finds_the_truth_from_exact_detections(exact, tmp_path, name):
    ds, session = exact
    mod = module(name)
    if (why := mod.missing()) is not None:
        pytest.skip(why)
    result = mod.calibrate(session, tmp_path / name, name)
    assert [c.name for c in result.cameras] == session.names
    assert result.path.is_dir() and any(result.path.iterdir())  # the tool's own file
    scored = score_cameras(ds, result.cameras, session.image_points, name)
    for cam in scored["cameras"].values():
        assert cam["projection_difference"]["mean_px"] < TOLERANCE_PX[name]
    assert scored["rig"]["rmse_cal_mm"] < 100 * TOLERANCE_PX[name]


def test_mrcal_splined_is_scored_through_its_own_projection(exact, tmp_path):
    """A lens the camera model cannot hold: its frame (a gauge, ~10 degrees off at mrcal's seed)
    is turned onto the truth before the rig is scored. From exact detections the rig comes out
    within 0.011 mm and 0.004 deg (measured; mrcal's regularization and outlier rejection on
    noise-free points keep it from zero), while the lens's frame as written is degrees off."""
    from stereo_bench.run.compare import _score_proxy

    ds, session = exact
    mod = module("mrcal-splined")
    if (why := mod.missing()) is not None:
        pytest.skip(why)
    result = mod.calibrate(session, tmp_path, "mrcal-splined")
    assert result.cameras == [] and result.proxy is not None
    scored = _score_proxy(ds, result, session)
    for name, cam in scored["cameras"].items():
        proj = cam["projection_difference"]
        assert proj["rotation_deg"] > 1 and proj["direct_mean_px"] > 10 * proj["mean_px"]
        assert cam["parameter_errors"] is None
    other = scored["rig"]["camera_errors"][session.names[1]]
    assert other["centre_mm"] < 0.05 and other["rotation_deg"] < 0.02


@pytest.fixture(scope="module")
def square_pixels(tmp_path_factory):
    """The quick-start pair with a lens anipose's and caliscope's cameras hold (one focal
    length, the principal point at the image centre, k1 only), exact detections."""
    rig = quickstart(16)
    for cam in rig["cameras"]:
        cam.update(fx=600.0, fy=600.0, cx=319.5, cy=239.5, dist=[-0.2, 0, 0, 0, 0, 0, 0, 0])
    ds = write_dataset(parse_rig(rig), tmp_path_factory.mktemp("square") / "ds")
    gt = ds.ground_truth
    points = np.where(gt.visible[..., None], gt.points, np.nan)
    return ds, Session([c.name for c in ds.cameras], [c.size for c in ds.cameras],
                       ds.object_points, points, gt.visible.all(-1), ds.pattern)


# aniposelib takes float32 corners (3e-6 px measured); caliscope stops at its least-squares
# tolerance with the board's points free (1e-4 px mean, 8e-4 px max measured).
@pytest.mark.parametrize("name,tolerance_px", [("anipose", 1e-4), ("caliscope", 1e-3)])
def test_anipose_and_caliscope_find_a_lens_their_cameras_hold(square_pixels, tmp_path, name,
                                                               tolerance_px):
    from stereo_bench.run.exchange import rebased

    ds, session = square_pixels
    mod = module(name)
    if (why := mod.missing()) is not None:
        pytest.skip(why)
    result = mod.calibrate(session, tmp_path / name, name)
    scored = score_cameras(ds, rebased(result.cameras), session.image_points, name)
    for cam in scored["cameras"].values():
        assert cam["projection_difference"]["mean_px"] < tolerance_px
    assert scored["rig"]["rmse_cal_mm"] < 0.01


def test_mean_frames_error_is_zero_for_the_truth_and_follows_a_shifted_lens(exact):
    """The true error of a projection uncertainty (module notes of run/compare.py): zero for
    the true camera with the true board poses; a principal point moved by (2, -1) px, the poses
    kept, moves the projection of every pixel by that much."""
    ds, _ = exact
    truth = ds.cameras[0].with_params(rvec=np.zeros(3), tvec=np.zeros(3))
    frames = np.arange(6)
    from stereo_bench.run.compare import _true_cam_from_board
    from stereo_bench.core.poses import matrix_to_rodrigues
    R, t = _true_cam_from_board(ds, 0, frames)
    poses = {int(f): (matrix_to_rodrigues(R[i]), t[i]) for i, f in enumerate(frames)}
    projection = {"pixels": np.array([[100.0, 80.0], [320.0, 240.0], [600.0, 400.0]]),
                  "distance_mm": 700.0, "board_poses": poses}
    assert np.abs(projection_errors(ds, 0, truth, projection)).max() < 1e-9
    shifted = truth.with_params(cx=truth.cx + 2.0, cy=truth.cy - 1.0)
    e = projection_errors(ds, 0, shifted, projection)
    np.testing.assert_allclose(e, np.tile([-2.0, 1.0], (3, 1)), atol=1e-9)


def test_uncertainty_check_counts_a_parameter_inside_its_sigma(exact):
    ds, _ = exact
    truth = ds.cameras[0].with_params(rvec=np.zeros(3), tvec=np.zeros(3))
    est = truth.with_params(fx=truth.fx + 0.5, fy=truth.fy - 2.0)
    result = ToolResult([est], Path("."), "opencv", 0.0,
                        uncertainty={truth.name: {"parameters": {"fx": 1.0, "fy": 1.0}}})
    z = check_uncertainty(ds, result)[truth.name]["parameter_z"]
    assert z == pytest.approx({"fx": 0.5, "fy": -2.0})


def test_wilson_interval_and_the_2d_one_sigma_quantile():
    lo, hi = wilson(7, 10)
    assert (lo, hi) == pytest.approx((0.3968, 0.8922), abs=1e-4)
    # 68.27 % of a 2-D standard Gaussian lies within radius sqrt(2.2957...).
    assert 1 - math.exp(-CHI2_2D_68 / 2) == pytest.approx(0.6827, abs=1e-9)


def test_grid_tools_refuse_a_board_that_is_not_a_square_grid(exact):
    _, session = exact
    for obj in (session.object_points * [1.0, 1.5, 1.0],  # rectangular cells
                session.object_points[::-1]):  # numbered from the other end
        with pytest.raises(ToolError, match="square grid"):
            Session(session.names, session.sizes, obj, session.image_points, session.found,
                    session.pattern).grid()
    assert session.grid() == (8, 11, 15.0)


def test_a_pair_tool_refuses_a_studio_by_name(exact, tmp_path):
    _, s = exact
    three = Session(s.names + ["third"], s.sizes * 2, s.object_points,
                    np.concatenate([s.image_points, s.image_points[:1]]),
                    np.concatenate([s.found, s.found[:1]]), s.pattern)
    with pytest.raises(ToolError, match=r"opencv-stereo: .*3 camera\(s\)"):
        module("opencv-stereo").calibrate(three, tmp_path, "opencv-stereo")
    with pytest.raises(ValueError, match="tool 'kalibr'"):
        parse_tools("opencv-stereo,kalibr")


def test_compare_tools_command_writes_the_table_and_the_pose_cost(tmp_path, capsys):
    rig = quickstart(12)
    rig["environment"] = {"kind": "noisy"}
    path = tmp_path / "pair.yaml"
    path.write_text(yaml.safe_dump(rig))
    out = tmp_path / "out"
    assert main(["compare-tools", str(path), "--tools", "opencv-stereo,synthcal", "--seeds",
                 "2", "--out", str(out)]) == 0
    results = json.loads((out / "results.json").read_text())
    assert [s["seed"] for s in results["seeds"]] == [7, 8]
    for name in ("opencv-stereo", "synthcal"):
        row = results["table"][name]
        assert row["seeds"] == 2 and not row["failed"]
        rmse = row["figures"]["rmse_cal_mm"]
        assert rmse["ci_low"] < rmse["mean"] < rmse["ci_high"] and 0 < rmse["mean"] < 5
        assert row["coverage"]["parameters_all"]["n"] == 2 * 2 * (10 if name == "synthcal"
                                                                   else 9)
        # The tool's own file, read back, is what was scored.
        assert (out / "trials" / "seed_7" / "tools" / name).is_dir()
    pose = results["pose"]
    assert set(pose["costs"]) == {"opencv-stereo", "synthcal"}
    assert pose["floor"]["mean"] > 0
    text = (out / "report.md").read_text()
    assert "| opencv-stereo |" in text and "pose cost mm" in text
    assert (out / "compare-tools.png").stat().st_size > 1000 and (out / "report.html").is_file()


def test_compare_tools_refuses_an_unknown_tool_before_rendering(tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["compare-tools", str(Path(__file__).resolve().parents[2] / "configs" /
                                      "quickstart.yaml"), "--tools", "nosuch", "--out",
                 str(out)]) == 2
    assert "tool 'nosuch': expected one of" in capsys.readouterr().err
    assert not out.exists()


def test_pose_eval_reads_a_tool_that_failed_in_one_trial(exact, tmp_path):
    """A tool whose calibration failed in one seed leaves a rig entry saying why, and pose-eval
    counts that trial as the tool's failure instead of stopping (a trial without the tool's rig
    at all is read the same way)."""
    from pose_eval.cli import run_rigs
    from stereo_bench.io.rundir import RunPaths
    from stereo_bench.run.compare import _pose_ready
    from stereo_bench.run.pipeline import Trial

    ds, _ = exact
    trial = RunPaths(tmp_path).trial(7)
    _pose_ready(trial, "fp", {"good": {"cameras_estimated": [c.to_dict() for c in ds.cameras]},
                              "bad": {"error": "ToolError: bad: refused"},
                              "absent": {"skipped": "not installed"}})
    assert json.loads(trial.rig("bad").read_text())["error"] == "ToolError: bad: refused"
    assert not trial.rig("absent").exists()
    rigs = run_rigs(["gt", "good", "bad", "gone"],
                     Trial(7, ds.cameras, {"good": ds.cameras, "bad": "ToolError: bad: refused"}))
    assert "refused" in rigs["bad"] and "no rig of gone" in rigs["gone"]
    assert not isinstance(rigs["good"], str)


def test_mrcal_board_poses_are_moved_to_the_session_board_frame():
    """mrcal's board has its first point at its origin; a ChArUco board's first corner is one
    square in: the same physical point must land at the same place through both poses."""
    import cv2

    from stereo_bench.tools.mrcal import _board_frame

    rvec, tvec = np.array([0.1, -0.2, 0.3]), np.array([10.0, -5.0, 900.0])
    origin = np.array([110.0, 110.0, 0.0])
    (r, t), = _board_frame({"0": [*rvec, *tvec]}, origin).values()
    R = cv2.Rodrigues(rvec)[0]
    p = np.array([330.0, 220.0, 0.0])  # a corner in the session's frame
    np.testing.assert_allclose(R @ p + t, R @ (p - origin) + tvec, atol=1e-12)


def test_one_camera_session_is_calibrated_and_read_back(exact, tmp_path):
    """A one-camera session: the suite's own writes that camera's YAML and reads it back."""
    ds, s = exact
    mono = Session(s.names[:1], s.sizes[:1], s.object_points, s.image_points[:1], s.found[:1],
                   s.pattern)
    result = module("synthcal").calibrate(mono, tmp_path, "synthcal")
    assert [c.name for c in result.cameras] == s.names[:1]
    truth = ds.cameras[0].with_params(rvec=np.zeros(3), tvec=np.zeros(3))
    assert abs(result.cameras[0].fx - truth.fx) < 1e-6
