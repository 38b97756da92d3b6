"""A calibration that leaves the suite for another tool comes back scored exactly as the suite
scores its own, and pose-eval triangulates through it."""

import json
from pathlib import Path

import numpy as np
import pytest

from pose_eval.cli import main as pose_main
from stereo_bench.cli import main
from stereo_bench.config.schema import parse_rig
from stereo_bench.run.pipeline import run
from stereo_bench.io.rundir import RunPaths
from quickstart import quickstart

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def stereo_run(tmp_path_factory):
    d = quickstart(12)
    cfg = parse_rig(d)
    out = tmp_path_factory.mktemp("exchange") / "run"
    trial = run(cfg, out, ["opencv-radtan", "opencv"])[0]
    return out, trial, RunPaths(out).trial(cfg.seed).dataset.root


@pytest.mark.parametrize("fmt", ["opencv", "colmap", "kalibr", "easymocap", "anipose", "mrcal"])
def test_exported_rig_scores_as_the_suites_own(stereo_run, fmt, tmp_path):
    out, trial, dataset = stereo_run
    exported = tmp_path / fmt
    assert main(["export", str(out), "--format", fmt, "--method", "opencv-radtan",
                 "--out", str(exported)]) == 0
    scored = out.parent / "scored"  # shared: the dataset's detections are reused
    assert main(["score", str(dataset), str(exported), "--out", str(scored)]) == 0
    report = json.loads((scored / "results.json").read_text())
    assert report["format"] == fmt
    own = trial["rig"]["opencv-radtan"]
    # The same cameras (through a file) and the same detections: the same RMSE_cal.
    assert report["rig"]["rmse_cal_mm"] == pytest.approx(own["rmse_cal_mm"], rel=1e-6)
    for cam in ("left", "right"):
        ours = report["rig"]["camera_errors"][cam]
        assert ours["rotation_deg"] == pytest.approx(own["camera_errors"][cam]["rotation_deg"],
                                                     abs=1e-6)
    # Per camera: the rig's refined intrinsics, not the single-camera estimate; both close.
    assert report["cameras"]["left"]["projection_difference"]["mean_px"] < 0.5


def test_export_refuses_what_a_format_cannot_hold(stereo_run, tmp_path, capsys):
    out, _, _ = stereo_run
    assert main(["export", str(out), "--format", "kalibr", "--method", "opencv",
                 "--out", str(tmp_path / "k")]) == 2
    assert "k3" in capsys.readouterr().err
    assert main(["export", str(out), "--format", "kalibr", "--method", "tsai",
                 "--out", str(tmp_path / "t")]) == 2
    assert "no estimate of method 'tsai'" in capsys.readouterr().err


def test_pose_eval_takes_a_users_calibration(stereo_run, tmp_path):
    out, _, _ = stereo_run
    exported = tmp_path / "kalibr"
    assert main(["export", str(out), "--format", "kalibr", "--method", "opencv-radtan",
                 "--out", str(exported)]) == 0
    pose = tmp_path / "pose"
    assert pose_main(["--run", str(out), "--calib", "opencv-radtan", "--calibration",
                      str(exported / "camchain.yaml"), "--frames", "10", "--out",
                      str(pose)]) == 0
    res = json.loads((pose / "results.json").read_text())
    mine, theirs = res["methods"]["file:camchain.yaml"], res["methods"]["opencv-radtan"]
    # The same cameras through Kalibr's file: the same pose, to rounding.
    a, b = (m["triangulated"]["mpjpe_mm"]["mean"] for m in (mine, theirs))
    assert np.isclose(a, b, rtol=1e-6)


def test_export_of_a_missing_source_creates_nothing(tmp_path, capsys):
    missing = tmp_path / "no_run"
    assert main(["export", str(missing), "--format", "kalibr"]) == 2
    assert "neither a run directory" in capsys.readouterr().err
    assert not missing.exists()


def test_a_pose_no_rotation_keeps_finite_is_refused_naming_the_file():
    """A rotation vector a file may hold (finite) but whose rotation overflows: the refusal
    names the file, as every other refusal of an imported calibration does."""
    from stereo_bench.core.camera import Camera
    from stereo_bench.run.exchange import as_rig_of

    left = Camera("left", 100, 80, 100.0, 100.0, 50.0, 40.0, rvec=np.array([0.0, -1e308, 0.0]))
    right = Camera("right", 100, 80, 100.0, 100.0, 50.0, 40.0)
    with pytest.raises(ValueError, match=r"^/calib/camera-0-left\.cameramodel: camera 'left'"), \
            np.errstate(all="ignore"):
        as_rig_of([left, right], ["left", "right"], "/calib/camera-0-left.cameramodel")
