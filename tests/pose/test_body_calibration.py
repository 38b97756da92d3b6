"""Calibration from the body: its spline and bundle adjustment's Jacobian against finite
differences, clocks that shift the truth exactly, the studio recovered from people walking
against the truth (poses, clocks, scale, vertical), and bad input refused by name."""

import warnings

import numpy as np
import pytest

from stereo_bench.config.schema import load_rig, parse_rig
from stereo_bench.config.yaml_reader import load_yaml
from stereo_bench.scene.dataset import UnusableRigError, write_dataset
from pose_eval import cli
from pose_eval.body import load_body_model
from pose_eval.body_calibration import (Scale, _Bundle, calibrate_from_body, cubic_bspline,
                                        on_frames)
from pose_eval.body_session import Session, calibrate_session, session_keypoints
from pose_eval.motion import make_motion
from pose_eval.observe import DetectorModel, observe
from pose_eval.scene import Person, seen_by_clocks

from tests.quickstart import ROOT

H36M = ROOT / "configs/studios/h36m_rectangle.yaml"
FPS = 30.0


@pytest.fixture(scope="module")
def studio():
    return load_rig(H36M).cameras_true(), load_body_model()


def _gaussian(noise_px):
    detector = DetectorModel(noise_px=noise_px)
    return lambda cams, scene, rng: observe(cams, scene, detector, rng)


def test_bspline_weights_partition_unity_and_their_derivatives_are_exact():
    u = np.linspace(-0.4, 1.4, 37)
    w, dw = cubic_bspline(u)
    assert np.allclose(w.sum(1), 1, atol=1e-14) and np.allclose(dw.sum(1), 0, atol=1e-14)
    h = 1e-6
    fd = (cubic_bspline(u + h)[0] - cubic_bspline(u - h)[0]) / (2 * h)
    assert np.abs(fd - dw).max() < 1e-8
    # Nearly the same noise at every fraction of a frame: no pull towards half frames.
    ss = (cubic_bspline(np.linspace(0, 1, 11))[0] ** 2).sum(1)
    assert ss.min() > 0.45 and ss.max() <= 0.5 + 1e-12
    control = np.random.default_rng(0).normal(size=(6, 2, 3))
    frames = on_frames(control, np.zeros(6, int))
    assert np.isnan(frames[0]).all() and np.isnan(frames[-1]).all()
    assert np.allclose(frames[2], (control[1] + 4 * control[2] + control[3]) / 6, atol=1e-14)


def test_bundle_jacobian_matches_finite_differences(studio):
    cams, _ = studio
    rng = np.random.default_rng(3)
    T, N = 12, 5
    track = rng.normal(scale=300, size=(1, N, 3)) + np.array([0, 0, 1000.0])
    points = track + np.cumsum(rng.normal(scale=20, size=(T, N, 3)), axis=0)
    offsets = np.array([0.0, 0.3, -0.6, 1.2])
    pixels = np.stack([cam.project(points.reshape(-1, 3)).reshape(T, N, 2) for cam in cams])
    pixels += rng.normal(scale=2, size=pixels.shape)
    weights = rng.uniform(0.3, 1, size=(4, T, N))
    # A moved start, so that the Jacobian is taken away from the solution.
    moved = [cams[0]] + [c.with_params(rvec=c.rvec + 0.01, tvec=c.tvec + 20) for c in cams[1:]]
    problem = _Bundle(moved, pixels, weights, points, offsets, True, np.zeros(T, int))
    assert problem.n_obs > 0 and len(problem.triples) > 0
    x = problem.pack(moved, offsets, points)
    J = problem.jacobian(x).toarray()
    fd = np.empty_like(J)
    for k in range(len(x)):
        h = 1e-6 * max(1.0, abs(x[k]))
        up, down = x.copy(), x.copy()
        up[k] += h
        down[k] -= h
        fd[:, k] = (problem.residuals(up) - problem.residuals(down)) / (2 * h)
    assert np.abs(J - fd).max() < 1e-5 * np.abs(fd).max()


def test_a_clock_offset_shows_the_motion_later_exactly(studio):
    cams, model = studio
    shifted = make_motion("walk_circle", 20, FPS, seed=4, start_s=3 / FPS)
    plain = make_motion("walk_circle", 23, FPS, seed=4)
    assert np.allclose(shifted.poses, plain.poses[3:], atol=1e-12)
    assert np.allclose(shifted.transl, plain.transl[3:], atol=1e-12)
    views = seen_by_clocks(cams, [Person("walk_circle", 4)], 20, FPS, model,
                           [0.0, 2000 / FPS, 0.0, 0.0])
    # Camera 1 runs two frames ahead: its frame f is camera 0's frame f + 2, in the same place.
    assert np.allclose(views[1][0].joints[:-2], views[0][0].joints[2:], atol=1e-6)
    assert np.allclose(views[2][0].joints, views[0][0].joints, atol=0)


def test_studio_from_people_walking_against_the_truth(studio):
    """4 cameras 8.4 m apart, 1 px keypoints, clocks up to 1.5 frames apart: poses, clocks,
    scale (from the person's height) and the vertical, each well inside the issue's aims."""
    cams, model = studio
    offsets_ms = np.array([0.0, 23.0, -47.0, 31.0])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the walk leaves some views, as pose-eval warns
        result, errors, placed = calibrate_session(cams, offsets_ms, Session(frames=150),
                                                   model, _gaussian(1.0), [7])
    assert errors["rotation_deg_max"] < 0.05
    assert errors["centre_mm_max"] < 3.0
    assert abs(errors["scale_pct"]) < 0.5
    assert errors["offset_frames"] < 0.05
    assert errors["vertical_deg"] < 0.2
    assert result.vertical == "floor" and errors["rms_px"] < 1.5
    assert np.allclose(placed[0].R, cams[0].R) and np.allclose(placed[0].tvec, cams[0].tvec)


def test_baseline_scale_and_synchronised_cameras(studio):
    cams, model = studio
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _, errors, _ = calibrate_session(cams, np.zeros(4),
                                         Session(frames=100, scale="baseline",
                                                 max_offset_frames=0),
                                         model, _gaussian(1.0), [8])
    assert abs(errors["scale_pct"]) < 0.2 and errors["offset_frames"] == 0.0
    assert errors["rotation_deg_max"] < 0.05


def test_bad_input_is_refused_by_name(studio, tmp_path):
    cams, model = studio
    with pytest.raises(ValueError, match="one known quantity"):
        Scale(baseline_mm=1.0, height_mm=1.0, cameras=("cam1", "cam2"))
    with pytest.raises(ValueError, match="two different cameras"):
        Scale(baseline_mm=1.0, cameras=("cam1", "cam1"))
    with pytest.raises(ValueError, match="people"):
        Session(people=9)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        keypoints, _ = session_keypoints(cams, np.zeros(4), Session(frames=30), model,
                                         _gaussian(1.0), [1])
    pixels = keypoints.pixels.copy()
    pixels[3] = np.nan  # camera 4 sees nobody
    with pytest.raises(ValueError, match=r"\['cam4'\]"):
        calibrate_from_body(cams, pixels, keypoints.confidence, None,
                            Scale(baseline_mm=1.0, cameras=("cam1", "cam2")))
    with pytest.raises(ValueError, match="cam9"):
        calibrate_from_body(cams, keypoints.pixels, keypoints.confidence, None,
                            Scale(baseline_mm=1.0, cameras=("cam1", "cam9")))
    # The rig file's clocks: one per camera of a studio; a board dataset refuses them.
    data = load_yaml(H36M)
    data["studio"]["time_offset_ms"] = [0.0, 5.0]
    with pytest.raises(Exception, match="time_offset_ms: expected 4 offsets"):
        parse_rig(data)
    data["studio"]["time_offset_ms"] = [0.0, 5.0, 0.0, 0.0]
    with pytest.raises(UnusableRigError, match=r"\['cam2'\] have a time_offset_ms"):
        write_dataset(parse_rig(data), tmp_path / "ds")
    assert not (tmp_path / "ds").exists()


def test_pose_eval_refuses_body_calibration_without_a_detector_model(tmp_path, capsys):
    out = tmp_path / "out"
    code = cli.main(["--rig", str(H36M), "--body-calibration", "--keypoints", str(tmp_path),
                     "--out", str(out)])
    assert code == 2 and "--body-calibration" in capsys.readouterr().err
    code = cli.main(["--rig", str(H36M), "--body-calibration", "--body-people", "9",
                     "--out", str(out)])
    assert code == 2 and "--body-people" in capsys.readouterr().err
    assert not out.exists()


def test_calibrate_keypoints_from_a_users_files(studio, tmp_path, capsys):
    """Two tracked people in OpenPose files and an EasyMocap intrinsics file in; the studio
    read back from the files it wrote by their own readers, against the truth."""
    from stereo_bench import io
    from stereo_bench.multiview.bundle import aligned_rig_errors
    from pose_eval import calibrate_keypoints
    from pose_eval.body_session import skeleton
    from pose_eval.observe import write_openpose

    cams, model = studio
    offsets_ms = np.array([0.0, -30.0, 12.0, 44.0])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        keypoints, _ = session_keypoints(cams, offsets_ms, Session(people=2, frames=120), model,
                                         _gaussian(1.0), [5])
    write_openpose(tmp_path / "kp", cams, keypoints)
    # A user's intrinsics file holds some poses too, wrong ones here: the method ignores them.
    io.export([c.with_params(rvec=c.rvec + 0.3, tvec=c.tvec + 500) for c in cams],
              tmp_path / "intrinsics", "easymocap")
    stature = skeleton("smpl24", model, 2)[1]
    out = tmp_path / "out"
    code = calibrate_keypoints.main([str(tmp_path / "kp"), "--cameras",
                                     str(tmp_path / "intrinsics"), "--height-mm", str(stature),
                                     "--out", str(out)])
    assert code == 0, capsys.readouterr().err
    for fmt in ("easymocap", "colmap", "anipose"):
        back = io.load(out / fmt, fmt)
        e = aligned_rig_errors(back, cams)
        assert e["rotation_deg"].max() < 0.05 and e["centre_mm"].max() < 3, fmt
        assert abs(1 / e["scale"] - 1) < 0.005, fmt
    report = __import__("json").loads((out / "report.json").read_text())
    assert report["people"] == [0, 1] and report["layout"] == "smpl24"
    est = np.array(list(report["offsets_ms"].values()))
    assert np.abs(est - offsets_ms).max() < 0.05 * 1000 / FPS
    # Refused by name: an unreadable layout, a camera the baseline does not know.
    bad = tmp_path / "bad"
    for cam in cams:
        (bad / cam.name).mkdir(parents=True)
        (bad / cam.name / "000000_keypoints.json").write_text(
            '{"people": [{"pose_keypoints_2d": [1, 2, 1, 3, 4, 1]}]}')
    code = calibrate_keypoints.main([str(bad), "--cameras", str(tmp_path / "intrinsics"),
                                     "--height-mm", "1700", "--out", str(tmp_path / "o2")])
    assert code == 2 and "expected one layout" in capsys.readouterr().err
    code = calibrate_keypoints.main([str(tmp_path / "kp"), "--cameras",
                                     str(tmp_path / "intrinsics"), "--baseline", "cam1", "camX",
                                     "4000", "--out", str(tmp_path / "o3")])
    assert code == 2 and "camX" in capsys.readouterr().err
    assert not (tmp_path / "o2").exists() and not (tmp_path / "o3").exists()


def test_left_and_right_swapped_in_some_views_are_swapped_back(studio):
    """A detector that takes a back for a front swaps left and right (BlazePose does, in a
    quarter of some side views): those views are found and swapped back."""
    from pose_eval.body_calibration import _flip
    from pose_eval.body_session import skeleton

    cams, model = studio
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        keypoints, _ = session_keypoints(cams, np.zeros(4), Session(frames=120), model,
                                         _gaussian(1.0), [11])
    body, stature = skeleton("smpl24", model, 1)
    flips = np.zeros((4, 120, 1), dtype=bool)
    flips[2, ::4] = flips[3, 1::5] = True  # 30 and 24 views
    pixels, confidence = _flip(keypoints.pixels, keypoints.confidence, flips, body)
    result = calibrate_from_body(cams, pixels, confidence, body, Scale(height_mm=stature))
    from stereo_bench.multiview.bundle import aligned_rig_errors
    e = aligned_rig_errors(result.cameras, cams)
    assert e["rotation_deg"].max() < 0.05 and e["centre_mm"].max() < 3
    assert result.mirrored_views == 54
