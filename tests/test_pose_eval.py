"""pose-eval against exact ground truth: placement, detections, triangulation, fit, metrics, CLI.

Rigs are the paper's (configs/paper/*.yaml); estimated rigs are the true ones with known errors.
"""

import json
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

from pose_eval import cli
from pose_eval.body import forward, load_body_model
from pose_eval.fit import fit_smpl
from pose_eval.metrics import mpjpe, pa_mpjpe, paper_mpjpe, pose_metrics, similarity_align
from pose_eval.motion import JOINT, make_motion
from pose_eval.observe import (DetectorModel, observe, read_openpose, scene_occlusion,
                               write_openpose)
from pose_eval.reconstruct import triangulate_joints
from pose_eval.scene import in_true_world, in_view, make_scene, place_body, rig_axes
from stereo_bench.camera import compose, invert, matrix_to_rodrigues, rodrigues_to_matrix
from stereo_bench.config import load_rig
from stereo_bench.pipeline import load_run, rig_fingerprint
from stereo_bench.rundir import RunPaths, write_json

ROOT = Path(__file__).resolve().parents[1]
WIDE, MIXED = ROOT / "configs/paper/wide_pair.yaml", ROOT / "configs/paper/mixed_pair.yaml"


@pytest.fixture(scope="module")
def model():
    return load_body_model()


def cameras(path):
    return load_rig(path).cameras_true()


def turn_second_camera(cams, deg):
    """The rig with camera 1 turned by ``deg`` about the world's vertical (a vergence error)."""
    R = rodrigues_to_matrix(np.array([0.0, np.radians(deg), 0.0])) @ cams[1].R
    return [cams[0], cams[1].with_params(rvec=matrix_to_rodrigues(R))]


def standing(model, cams, yaw=0.0):
    """arm_raise's first frame (arms down) turned by ``yaw`` about SMPL's up, placed in the rig."""
    m = make_motion("arm_raise", 1)
    joints, vertices = forward(model, m.body_pose, [[0.0, yaw, 0.0]], m.transl)
    return place_body(cams, joints, vertices, model.faces)


# --- scene -----------------------------------------------------------------------------------

def test_body_stands_upright_in_view_and_faces_the_rig(model):
    cams = cameras(WIDE)
    scene = make_scene(cams, "walk_circle", 30, model=model)
    for cam in cams:  # every vertex of every frame is seen
        assert in_view(cam, scene.vertices).all()
    centre, axis, up = rig_axes(cams)
    J = scene.joints
    assert ((J[:, JOINT["head"]] - J[:, JOINT["pelvis"]]) @ up > 1000 * 0.5).all()
    # Facing the rig: the body's left is on the image's right, as in a mirror.
    front = standing(model, cams)
    u = cams[0].project(front.joints[0])[:, 0]
    assert u[JOINT["left_hip"]] > u[JOINT["right_hip"]]
    # The body fills the view: 10 % nearer and some vertex leaves an image.
    with pytest.warns(UserWarning, match="leaves the view of"):
        nearer = make_scene(cams, "walk_circle", 30, model=model,
                            distance_mm=0.9 * scene.distance_mm)
    assert not all(in_view(cam, nearer.vertices).all() for cam in cams)


def test_estimated_rig_is_placed_at_the_true_reference_pose():
    truth = cameras(MIXED)
    R0i, t0i = invert(truth[0].R, truth[0].tvec)  # world_from_cam0
    estimate = []
    for cam in truth:  # exactly what stereo-bench writes: cam_from_cam0
        R, t = compose(cam.R, cam.tvec, R0i, t0i)
        estimate.append(cam.with_params(rvec=matrix_to_rodrigues(R), tvec=t))
    assert np.allclose(estimate[0].tvec, 0) and np.allclose(estimate[0].rvec, 0)
    for placed, cam in zip(in_true_world(estimate, truth), truth):
        np.testing.assert_allclose(placed.R, cam.R, atol=1e-12)
        np.testing.assert_allclose(placed.tvec, cam.tvec, atol=1e-9)
    with pytest.raises(ValueError, match="do not match"):
        in_true_world(estimate[::-1], truth)


# --- triangulation through true and estimated cameras ----------------------------------------

@pytest.mark.parametrize("rig", [WIDE, MIXED], ids=["wide_pair", "mixed_pair"])
def test_noise_free_keypoints_through_true_cameras_are_exact(model, rig):
    cams = cameras(rig)
    scene = make_scene(cams, "walk_circle", 10, model=model)
    kp = observe(cams, scene, DetectorModel(), np.random.default_rng(0))
    joints, dropped = triangulate_joints(cams, kp)
    m = pose_metrics(joints, scene.joints)
    assert dropped == 0 and m["missing_joints"] == 0
    # measured 2e-12 mm (wide, k1 = 0.5) and 2e-11 mm (mixed)
    assert m["mpjpe_mm"] < 1e-6 and m["paper_mpjpe_mm"] < 1e-6 and m["pa_mpjpe_mm"] < 1e-6


def test_calibration_error_gives_growing_mpjpe(model):
    cams = cameras(WIDE)
    scene = make_scene(cams, "walk_circle", 10, model=model)
    kp = observe(cams, scene, DetectorModel(), np.random.default_rng(0))
    errors = [mpjpe(triangulate_joints(turn_second_camera(cams, d), kp)[0], scene.joints)
              for d in (0.03, 0.1, 0.3)]
    # measured 18, 59, 167 mm: a 150 mm baseline at 2-4 m turns vergence errors into depth
    assert 10 < errors[1] and errors[0] < errors[1] < errors[2]
    assert errors[2] == pytest.approx(3 * errors[1], rel=0.1)  # linear for small errors


def test_unprojectable_detections_are_dropped_not_fatal(model):
    cams = cameras(WIDE)
    scene = make_scene(cams, "arm_raise", 2, model=model)
    kp = observe(cams, scene, DetectorModel(), np.random.default_rng(0))
    kp.pixels[1, 0, 5] = [635.0, 475.0]  # an image corner
    folding = [cams[0], cams[1].with_params(dist=[-0.6, 0, 0, 0, 0, 0, 0, 0])]  # folds at r 0.75
    joints, dropped = triangulate_joints(folding, kp)
    assert dropped >= 1 and np.isnan(joints[0, 5]).all() and np.isfinite(joints[1]).all()


def test_robust_triangulation_rejects_an_outlier_view(model):
    cams = cameras(WIDE) + [cameras(MIXED)[0].with_params(name="rect_top")]
    R = rodrigues_to_matrix(np.array([np.radians(-10), 0, 0])) @ cams[2].R
    cams[2] = cams[2].with_params(rvec=matrix_to_rodrigues(R), tvec=R @ np.array([0, 400.0, 0]))
    scene = make_scene(cams, "arm_raise", 2, model=model)
    kp = observe(cams, scene, DetectorModel(), np.random.default_rng(0))
    kp.pixels[1, :, 3] += 40.0  # one view of spine1 is 57 px off
    plain = triangulate_joints(cams, kp)[0]
    robust = triangulate_joints(cams, kp, robust=True)[0]
    assert np.linalg.norm(plain[:, 3] - scene.joints[:, 3], axis=-1).min() > 5
    np.testing.assert_allclose(robust, scene.joints, atol=1e-6)


# --- detections --------------------------------------------------------------------------------

def test_occlusion_from_the_side_but_not_from_the_front(model):
    cams = cameras(WIDE)
    front = scene_occlusion(cams, standing(model, cams))
    torso = [JOINT[n] for n in ("pelvis", "left_hip", "right_hip", "spine1", "spine2", "spine3",
                                "neck", "left_collar", "right_collar", "head")]
    assert not front[:, :, torso].any()
    assert not front.any()  # measured: nothing hidden, arms down, from the front
    side = scene_occlusion(cams, standing(model, cams, yaw=np.pi / 2))  # right side to the rig
    far = [JOINT[n] for n in ("left_knee", "left_ankle", "left_elbow", "left_wrist")]
    near = [JOINT[n] for n in ("right_knee", "right_ankle", "right_elbow", "right_wrist", "head")]
    assert side[:, :, far].all() and not side[:, :, near].any()


def test_detector_model_noise_outliers_misses_and_confidence(model):
    cams = cameras(WIDE)
    scene = make_scene(cams, "walk_circle", 20, model=model)
    exact = np.stack([c.project(scene.joints) for c in cams])
    kp = observe(cams, scene, DetectorModel(2.0, 0.1, 0.1), np.random.default_rng(1))
    det = kp.confidence > 0
    assert 0.85 < det.mean() < 0.95  # 10 % missed
    assert np.isnan(kp.pixels[~det]).all() and np.isfinite(kp.pixels[det]).all()
    assert set(np.unique(kp.confidence[det])) == {0.3, 1.0}
    assert (kp.confidence[det & kp.occluded] == 0.3).all()
    err = np.linalg.norm(kp.pixels - exact, axis=-1)
    clean = det & ~kp.occluded & ~kp.outlier
    assert np.sqrt(np.mean(err[clean] ** 2) / 2) == pytest.approx(2.0, rel=0.1)
    assert np.median(err[det & kp.outlier]) > 20 and err[det & kp.outlier].max() <= 50 + 1e-9
    # The same seed gives the same detections.
    again = observe(cams, scene, DetectorModel(2.0, 0.1, 0.1), np.random.default_rng(1))
    np.testing.assert_array_equal(again.pixels, kp.pixels)


def test_openpose_round_trip(tmp_path, model):
    cams = cameras(MIXED)
    scene = make_scene(cams, "squat", 4, model=model)
    kp = observe(cams, scene, DetectorModel(1.0, 0.0, 0.2), np.random.default_rng(2))
    write_openpose(tmp_path, cams, kp)
    assert (tmp_path / "wide_right" / "000003_keypoints.json").is_file()
    back = read_openpose(tmp_path, cams)
    np.testing.assert_array_equal(back.pixels, kp.pixels)  # NaN where missed, exact floats
    np.testing.assert_array_equal(back.confidence, kp.confidence)
    # Frames 4 and 5 have no files: not detected. OpenPose's own file names work too.
    assert np.isnan(read_openpose(tmp_path, cams, frames=6).pixels[:, 4:]).all()
    for path in tmp_path.glob("*/*.json"):
        path.rename(path.with_name(f"take1_{int(path.name[:6]):012d}_keypoints.json"))
    np.testing.assert_array_equal(read_openpose(tmp_path, cams).pixels, kp.pixels)
    bad = tmp_path / "rect_left" / "take1_000000000001_keypoints.json"
    bad.write_text(json.dumps({"people": [{"pose_keypoints_2d": [0.0] * 75}]}))  # BODY_25
    with pytest.raises(ValueError, match="000000000001_keypoints.json.*75 values"):
        read_openpose(tmp_path, cams)
    with pytest.raises(FileNotFoundError, match="nobody"):
        read_openpose(tmp_path, [cams[0].with_params(name="nobody")])


# --- metrics -----------------------------------------------------------------------------------

def test_paper_formula_and_standard_mpjpe_by_hand():
    gt = np.zeros((2, 3, 3))
    est = gt.copy()
    est[0, 0] = [3, 4, 0]  # frame 0: errors 5, 0, 12
    est[0, 2] = [0, 0, 12]
    est[1] = [1, 0, 0]  # frame 1: errors 1, 1, 1
    assert mpjpe(est, gt) == pytest.approx((5 + 0 + 12 + 3) / 6)
    assert paper_mpjpe(est, gt) == pytest.approx((13 + np.sqrt(3)) / 2)  # sqrt(25 + 144) = 13
    est[1, 1] = np.nan  # excluded and counted; the paper's sum is rescaled by 3 / 2
    m = pose_metrics(est, gt)
    assert m["missing_joints"] == 1 and m["total_joints"] == 6
    assert m["mpjpe_mm"] == pytest.approx(19 / 5)
    assert m["paper_mpjpe_mm"] == pytest.approx((13 + np.sqrt(2 * 3 / 2)) / 2)


def test_pa_mpjpe_removes_a_similarity_exactly():
    rng = np.random.default_rng(3)
    gt = rng.normal(0, 300, (5, 24, 3))
    est = np.empty_like(gt)
    for f in range(5):  # a different similarity per frame
        R = rodrigues_to_matrix(rng.normal(0, 1, 3))
        est[f] = rng.uniform(0.5, 2) * gt[f] @ R.T + rng.normal(0, 1000, 3)
    assert mpjpe(est, gt) > 100 and pa_mpjpe(est, gt) < 1e-9
    s, R, t = similarity_align(est[0], gt[0])
    np.testing.assert_allclose(s * est[0] @ R.T + t, gt[0], atol=1e-9)
    bent = gt.copy()
    bent[:, 0] += 10.0  # one joint moved by 17.3 mm: not a similarity
    assert 0.1 < pa_mpjpe(bent, gt) < np.sqrt(300)


# --- SMPL fit ------------------------------------------------------------------------------------

def test_smpl_fit_recovers_noise_free_joints(model):
    cams = cameras(WIDE)
    scene = make_scene(cams, "walk_circle", 10, model=model)
    kp = observe(cams, scene, DetectorModel(), np.random.default_rng(0))
    joints = triangulate_joints(cams, kp)[0]
    start = time.perf_counter()
    fit = fit_smpl(joints, model=model)
    seconds = time.perf_counter() - start
    err = np.linalg.norm(fit.joints - scene.joints, axis=-1)
    # measured: mean 1.4 mm, max 5.1 mm after the 200 L-BFGS iterations (1-2.5 s); converged,
    # 0.7 / 4.3 mm remain: the smoothness prior's bias, as true accelerations reach
    # 38 mm/frame^2 (0.24 / 1.0 mm without it)
    assert err.mean() < 3.0 and err.max() < 8.0, (err.mean(), err.max(), seconds)
    # The fitted parameters through smplx's full forward pass give the same joints.
    J, _ = forward(model, fit.body_pose, fit.global_orient, fit.transl, fit.betas)
    np.testing.assert_allclose(J * 1000, fit.joints, atol=1e-6)


# --- command line ------------------------------------------------------------------------------

def write_run(root: Path, rig: Path, rigs: dict, seeds=(0,)) -> Path:
    """A stereo-bench run directory with the given estimated rigs (true-world cameras, which are
    stored as cam_from_cam0 like stereo-bench does) or error messages."""
    truth = cameras(rig)
    R0i, t0i = invert(truth[0].R, truth[0].tvec)
    for s in seeds:
        trial = RunPaths(root).trial(s)
        trial.dataset.root.mkdir(parents=True)
        shutil.copy(rig, trial.dataset.config)
        write_json(trial.dataset.cameras, [c.to_dict() for c in truth])
        # As stereo-bench does: rig files carry the fingerprint of the calibrations they used.
        write_json(trial.metrics, {"fingerprint": "calibrations"})
        for method, est in rigs.items():
            if isinstance(est, str):
                entry = {"method": method, "error": est}
            else:
                rel = []
                for cam in est:
                    R, t = compose(cam.R, cam.tvec, R0i, t0i)
                    rel.append(cam.with_params(rvec=matrix_to_rodrigues(R), tvec=t).to_dict())
                entry = {"method": method, "reference": truth[0].name, "cameras": rel,
                         "rms_px": 0.1}
            write_json(trial.rig(method),
                       {**entry, "fingerprint": rig_fingerprint("calibrations", method)})
    return root


def test_cli_gt_from_a_rig_file(tmp_path, capsys):
    out = tmp_path / "out"
    assert cli.main(["--calib", "gt", "--rig", str(WIDE), "--frames", "5", "--out", str(out)]) == 0
    results = json.loads((out / "results.json").read_text())
    assert list(results["methods"]) == ["gt"]
    gt = results["methods"]["gt"]["triangulated"]
    assert gt["mpjpe_mm"]["n"] == 1 and gt["mpjpe_mm"]["mean"] > 0  # 1 px keypoint noise
    assert "| wide_pair | clean | triangulated |" in (out / "report.md").read_text()
    assert (out / "mpjpe.png").is_file() and (out / "skeleton.png").is_file()
    # Without a run there is no estimate to evaluate.
    assert cli.main(["--calib", "zhang", "--rig", str(WIDE), "--out", str(out)]) == 2
    assert "stereo-bench" in capsys.readouterr().err


def test_cli_all_methods_of_a_run_with_a_failure(tmp_path, capsys):
    truth = cameras(WIDE)
    run = write_run(tmp_path / "run", WIDE, {"zhang": turn_second_camera(truth, 0.1),
                                             "bouguet": truth, "tsai": "too few views"},
                    seeds=(3, 4))
    assert [t.seed for t in load_run(run)] == [3, 4]
    out = tmp_path / "out"
    args = ["--run", str(run), "--frames", "6", "--noise-px", "0", "--out", str(out)]
    assert cli.main(["--calib", "all", "--trials", "3", *args]) == 0
    res = json.loads((out / "results.json").read_text())
    assert list(res["methods"]) == ["gt", "zhang", "tsai", "bouguet"]
    m = res["methods"]
    assert m["gt"]["triangulated"]["mpjpe_mm"]["mean"] < 1e-6
    assert m["bouguet"]["triangulated"]["mpjpe_mm"]["mean"] < 1e-6  # the exact rig
    assert m["zhang"]["triangulated"]["mpjpe_mm"]["mean"] > 10
    assert m["zhang"]["triangulated"]["mpjpe_mm"]["n"] == 3
    assert m["tsai"]["triangulated"]["mpjpe_mm"]["n"] == 0 and len(m["tsai"]["failures"]) == 3
    assert [t["run_seed"] for t in res["trials"]] == [3, 4, 3]
    report = (out / "report.md").read_text()
    assert "tsai: calibration failed in run trial seed 3: too few views" in report
    # A method the run does not have is bad input, named by its path.
    assert cli.main(["--calib", "opencv", *args]) == 2
    assert "seed_3/rig/opencv.json" in capsys.readouterr().err.replace("\n", "")
    assert cli.main(["--calib", "gt", "--run", str(tmp_path / "nowhere")]) == 2
    assert "nowhere" in capsys.readouterr().err


def test_cli_reads_a_detectors_openpose_files(tmp_path, capsys, model):
    cams = cameras(WIDE)
    scene = make_scene(cams, "squat", 5, model=model)  # the scene the CLI places, too
    write_openpose(tmp_path / "kp", cams, observe(cams, scene, DetectorModel(),
                                                  np.random.default_rng(0)))
    out = tmp_path / "out"
    args = ["--calib", "gt", "--rig", str(WIDE), "--motion", "squat", "--frames", "5",
            "--keypoints", str(tmp_path / "kp"), "--out", str(out)]
    assert cli.main(args) == 0
    gt = json.loads((out / "results.json").read_text())["methods"]["gt"]["triangulated"]
    assert gt["mpjpe_mm"]["mean"] < 1e-6
    assert cli.main(args + ["--noise-px", "1"]) == 2  # noise is for synthetic keypoints only
    assert "--keypoints" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_:
        cli.main(["--help"])
    assert exit_.value.code == 0 and "--fit-smpl" in capsys.readouterr().out


def test_cli_fit_smpl_reports_both_stages(tmp_path):
    out = tmp_path / "out"
    assert cli.main(["--calib", "gt", "--rig", str(MIXED), "--frames", "4", "--noise-px", "0",
                     "--fit-smpl", "--out", str(out)]) == 0
    gt = json.loads((out / "results.json").read_text())["methods"]["gt"]
    assert gt["triangulated"]["mpjpe_mm"]["mean"] < 1e-6
    assert gt["fitted"]["mpjpe_mm"]["mean"] < 5
    assert "| mixed_pair | clean | SMPL fit |" in (out / "report.md").read_text()
