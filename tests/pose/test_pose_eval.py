"""pose-eval against exact ground truth: placement, detections, triangulation, fit, metrics, CLI.

Rigs are the paper's (configs/paper/*.yaml) and two studio presets (configs/studios: a
Human3.6M-like rectangle of 4 cameras, a TotalCapture-like ring of 8); estimated rigs are the
true ones with known errors.
"""

import json
import shutil
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from pose_eval import cli
from pose_eval.body import forward, load_body_model, to_mm
from pose_eval.fit import fit_smpl
from pose_eval.metrics import mpjpe, pa_mpjpe, paper_mpjpe, pose_metrics, similarity_align
from pose_eval.motion import JOINT, make_motion
from pose_eval.observe import DetectorModel, observe, read_openpose, scene_occlusion, write_openpose
from pose_eval.reconstruct import triangulate_joints
from pose_eval.scene import in_true_world, in_view, make_scene, place_body, rig_axes
from stereo_bench.core.poses import compose, invert, matrix_to_rodrigues, rodrigues_to_matrix
from stereo_bench.config.schema import load_rig, parse_rig
from stereo_bench.run.pipeline import load_run, rig_fingerprint
from stereo_bench.io.rundir import RunPaths
from stereo_bench.core.files import write_json

ROOT = Path(__file__).resolve().parents[2]
WIDE, MIXED = ROOT / "configs/paper/wide_pair.yaml", ROOT / "configs/paper/mixed_pair.yaml"
# h36m: 4 cameras at 1500 mm on the corners of a 3600 x 8400 mm rectangle, 4.57 m from its
# centre, cam1 and cam2 on one long side; ring: 8 cameras on a 3500 mm circle at heights
# alternating 1500 / 2500 mm. All look at [0, 0, 1000] in a z-up world (floor z = 0).
STUDIOS = {"h36m": ROOT / "configs/studios/h36m_rectangle.yaml",
           "ring": ROOT / "configs/studios/ring8.yaml"}


@pytest.fixture(scope="module")
def model():
    return load_body_model()


def cameras(path):
    return load_rig(path).cameras_true()


def turn_camera(cams, deg, index=1, about_centre=False):
    """The rig with camera ``index`` turned by ``deg`` about its image's vertical axis (for the
    paper's pairs, the world's vertical: a vergence error). about_centre keeps the camera
    centre (an orientation error alone); otherwise the translation t is kept, as the pairs'
    numbers were measured, and the centre of a camera away from the origin moves a little."""
    cam = cams[index]
    turn = rodrigues_to_matrix(np.array([0.0, np.radians(deg), 0.0]))
    tvec = turn @ cam.tvec if about_centre else cam.tvec
    out = list(cams)
    out[index] = cam.with_params(rvec=matrix_to_rodrigues(turn @ cam.R), tvec=tvec)
    return out


def standing(model, cams, yaw=0.0):
    """arm_raise's first frame (arms down) turned by ``yaw`` about SMPL's up, placed in the rig."""
    m = make_motion("arm_raise", 1)
    joints, vertices = forward(model, m.body_pose, [[0.0, yaw, 0.0]], m.transl)
    return place_body(cams, joints, vertices, model.faces)


def studio(kind: str) -> dict:
    """A studio preset's rig file data (STUDIOS) with its cameras listed one by one, as the
    resolved configuration lists them, to edit."""
    return load_rig(STUDIOS[kind]).model_dump(mode="json")


def outward_ring() -> dict:
    """The ring's cameras turned to look outwards, away from its centre: no place for a body."""
    rig = studio("ring")
    for cam in rig["cameras"]:
        cam["look_at_mm"] = [2 * v for v in cam["position_mm"][:2]] + [1000.0]
    return rig


def studio_cameras(kind: str):
    return cameras(STUDIOS[kind])


# --- scene -----------------------------------------------------------------------------------

def test_body_stands_upright_in_view_and_faces_the_rig(model):
    cams = cameras(WIDE)
    scene = make_scene(cams, "walk_circle", 30, model=model)
    for cam in cams:  # every vertex of every frame is seen
        assert in_view(cam, scene.vertices).all()
    centre, axis, up, surrounds = rig_axes(cams)
    assert not surrounds  # a pair looks the same way
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

@pytest.mark.parametrize("rig", [WIDE, MIXED, "h36m", "ring"],
                         ids=["wide_pair", "mixed_pair", "h36m", "ring"])
def test_noise_free_keypoints_through_true_cameras_are_exact(model, rig):
    cams = studio_cameras(rig) if isinstance(rig, str) else cameras(rig)
    scene = make_scene(cams, "walk_circle", 10, model=model)
    kp = observe(cams, scene, DetectorModel(), np.random.default_rng(0))
    joints, dropped = triangulate_joints(cams, kp)
    m = pose_metrics(joints, scene.joints)
    assert dropped == 0 and m["missing_joints"] == 0
    # measured 2e-12 mm (wide, k1 = 0.5) and 2e-11 mm (mixed), 2e-13 mm on the studios
    assert m["mpjpe_mm"] < 1e-6 and m["paper_mpjpe_mm"] < 1e-6 and m["pa_mpjpe_mm"] < 1e-6


def test_calibration_error_gives_growing_mpjpe(model):
    cams = cameras(WIDE)
    scene = make_scene(cams, "walk_circle", 10, model=model)
    kp = observe(cams, scene, DetectorModel(), np.random.default_rng(0))
    errors = [mpjpe(triangulate_joints(turn_camera(cams, d), kp)[0], scene.joints)
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


# --- studios: cameras that surround the subject -------------------------------------------------

def test_rigs_that_surround_are_told_apart_by_geometry():
    for rig in (WIDE, MIXED):
        assert not rig_axes(cameras(rig)).surrounds
    for kind in ("h36m", "ring"):
        centre, axis, up, surrounds = rig_axes(studio_cameras(kind))
        assert surrounds
        np.testing.assert_allclose(centre, [0, 0, 1000], atol=1e-6)  # where they all look
        np.testing.assert_allclose(up, [0, 0, 1], atol=1e-12)
        assert abs(axis @ up) < 1e-12  # camera 0's view direction, horizontal
    # Ceiling cameras looking 45 deg down: the mean optical axis is 0.7 long (it points at the
    # floor), yet they surround the point they look at.
    ceiling = studio("ring")
    for cam in ceiling["cameras"]:
        x, y, _ = cam["position_mm"]
        cam["position_mm"] = [x * 2000 / 3500, y * 2000 / 3500, 3000.0]
    cams = parse_rig(ceiling).cameras_true()
    assert np.linalg.norm(np.mean([c.R[2] for c in cams], axis=0)) > 0.7
    assert rig_axes(cams).surrounds
    # Two cameras 150 deg apart have no hull, nor a front (mean axis 0.26), but one target.
    wide = studio("ring")
    wide["cameras"] = [wide["cameras"][0], wide["cameras"][0] | {"name": "far", "position_mm": [
        3500 * np.cos(np.radians(150)), 3500 * np.sin(np.radians(150)), 1500.0]}]
    two = parse_rig(wide).cameras_true()
    assert np.linalg.norm(np.mean([c.R[2] for c in two], axis=0)) < 0.5
    centre, axis, up, surrounds = rig_axes(two)
    assert surrounds
    np.testing.assert_allclose(centre, [0, 0, 1000], atol=1e-6)
    # Cameras looking outwards neither share a front nor look at a point before them all.
    outwards = outward_ring()
    with pytest.raises(ValueError, match="neither look the same way .* nor look at a point"):
        rig_axes(parse_rig(outwards).cameras_true())


@pytest.mark.parametrize("kind", ["h36m", "ring"])
def test_studio_body_stands_at_the_centre_on_its_floor_facing_camera_0(model, kind):
    cams = studio_cameras(kind)
    scene = make_scene(cams, "walk_circle", 15, model=model)
    assert scene.surrounded
    for cam in cams:  # every vertex of every frame, in every camera
        assert in_view(cam, scene.vertices).all()
    # Half the stature above its floor sits at the centre the cameras look at: the stand-in
    # is 1710 mm tall, so its soles are at z = 145 mm whatever the motion, arms raised or not.
    rest = forward(model, np.zeros((1, 69)), np.zeros((1, 3)))[1][0]
    stature = to_mm(np.ptp(rest[:, 1]))
    raised = make_scene(cams, "arm_raise", 60, model=model)  # overhead at the end
    assert raised.vertices[..., 2].max() > scene.vertices[..., 2].max() + 300
    for s in (scene, raised):
        assert s.vertices[..., 2].min() == pytest.approx(1000 - stature / 2, abs=3)
    # The walk goes through the volume around its centre.
    pelvis = scene.joints[:, JOINT["pelvis"], :2]
    assert np.linalg.norm(0.5 * (pelvis.min(0) + pelvis.max(0))) < 300
    # Facing camera 0: its image shows the body's left on the right, as in a mirror.
    u = cams[0].project(standing(model, cams).joints[0])[:, 0]
    assert u[JOINT["left_hip"]] > u[JOINT["right_hip"]]
    with pytest.raises(ValueError, match="--distance-mm"):
        make_scene(cams, "walk_circle", 2, model=model, distance_mm=3000.0)


def test_occlusion_in_a_ring_of_eight_hides_the_far_side(model):
    cams = studio_cameras("ring")  # cam3 (+y) sees the body's left side, cam7 its right
    hidden = scene_occlusion(cams, standing(model, cams))
    assert hidden.shape == (8, 1, 24)
    assert not hidden[0].any()  # measured: from the front, arms down, nothing is hidden
    for cam, near, far in ((2, "left", "right"), (6, "right", "left")):
        for limb in ("knee", "ankle", "elbow", "wrist"):
            assert hidden[cam, 0, JOINT[f"{far}_{limb}"]]
            assert not hidden[cam, 0, JOINT[f"{near}_{limb}"]]
        assert not hidden[cam, 0, JOINT["head"]]


def test_joints_seen_by_fewer_than_two_cameras_are_missing_and_counted(model):
    cams = studio_cameras("h36m")
    scene = make_scene(cams, "walk_circle", 2, model=model)
    kp = observe(cams, scene, DetectorModel(), np.random.default_rng(0))
    kp.confidence[1:, 0, 5] = 0  # frame 0, right_knee: camera 0 alone
    kp.confidence[2:, 1, 6] = 0  # frame 1, spine2: cameras 0 and 1, enough
    kp.pixels[kp.confidence == 0] = np.nan
    assert np.argwhere(kp.under_two_views()).tolist() == [[0, 5]]
    assert kp.counts()["under_two_views"] == 1
    joints, dropped = triangulate_joints(cams, kp)
    m = pose_metrics(joints, scene.joints)
    assert dropped == 0 and m["missing_joints"] == 1 and np.isnan(joints[0, 5]).all()
    assert m["mpjpe_mm"] < 1e-6


@pytest.mark.parametrize("kind, floor_mm", [("h36m", (4.0, 8.0)), ("ring", (1.5, 3.5))])
def test_studio_gt_floor_and_the_cost_of_a_turned_camera(model, kind, floor_mm):
    cams = studio_cameras(kind)
    scene = make_scene(cams, "walk_circle", 15, model=model)
    occluded = scene_occlusion(cams, scene)
    turns = (0.1, 0.3, 1.0)
    rigs = {"truth": list(cams)} | {f"{d} deg": turn_camera(cams, d, about_centre=True)
                                     for d in turns}
    for trial in range(3):
        kp = observe(cams, scene, DetectorModel(1.0), np.random.default_rng([0, trial]), occluded)
        entries, _ = cli.evaluate_trial(cams, rigs, kp, scene)
        gt = entries["gt"]["triangulated"]
        assert gt["missing_joints"] == 0
        # Measured over 10 trials of 15 frames at 1 px: 5.98 ± 0.20 mm (5.65-6.21) on the
        # 4-camera rectangle, 2.49 ± 0.06 mm (2.41-2.56) on the 8-camera ring; at 4.6 and 3.7 m
        # a pixel spans 4.0 and 3.3 mm, which more views and wider angles average down. The
        # bounds leave ten standard deviations either way and stay under the aims of 15 and 10.
        assert floor_mm[0] < gt["mpjpe_mm"] < floor_mm[1]
        # The true cameras passed as an estimate cost exactly nothing: the same numbers.
        assert entries["truth"]["triangulated"]["excess_mpjpe_mm"] == 0.0
        # Camera 1 turned about its centre (measured at 0.1 / 0.3 / 1 deg: +1.9 / +10.8 / +47 mm
        # on the rectangle, +0.39 / +2.5 / +12 mm on the ring, whose 8 views outvote one).
        costs = [entries[f"{d} deg"]["triangulated"]["excess_mpjpe_mm"] for d in turns]
        assert 0 < costs[0] < costs[1] < costs[2]
        assert costs[2] > 5 * costs[0]


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
    run = write_run(tmp_path / "run", WIDE, {"zhang": turn_camera(truth, 0.1),
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


def test_cli_gt_on_a_studio_rig_file(tmp_path, capsys):
    rig, out = STUDIOS["h36m"], tmp_path / "out"
    assert cli.main(["--calib", "gt", "--rig", str(rig), "--frames", "10", "--out", str(out)]) == 0
    res = json.loads((out / "results.json").read_text())
    assert res["settings"]["surrounded"] and res["settings"]["distance_mm"] == pytest.approx(
        np.linalg.norm([1800, 4200, 500]))  # the cameras' mean distance from the centre
    gt = res["methods"]["gt"]["triangulated"]
    assert gt["mpjpe_mm"]["n"] == 1 and 4.0 < gt["mpjpe_mm"]["mean"] < 8.0  # 1 px, as above
    assert gt["excess_mpjpe_mm"]["mean"] == 0 and gt["missing_joints"] == 0
    assert res["under_two_views"] == {} and res["detections"]["under_two_views"] == 0
    report = (out / "report.md").read_text()
    assert "Table 5 redone" in report and "| gt | " in report and "0 (the floor)" in report
    assert (out / "mpjpe.png").is_file() and (out / "skeleton.png").is_file()
    # Most detections missed: joints seen by fewer than two cameras are reported, per joint.
    assert cli.main(["--calib", "gt", "--rig", str(rig), "--frames", "10", "--miss-rate", "0.6",
                     "--out", str(out)]) == 0
    res = json.loads((out / "results.json").read_text())
    under = sum(res["under_two_views"].values())
    assert under == res["detections"]["under_two_views"] > 0
    assert under == res["methods"]["gt"]["triangulated"]["missing_joints"]
    assert any("fewer than two cameras" in w for w in res["warnings"])
    # A studio has no distance to choose; cameras looking outwards have no place for a body.
    assert cli.main(["--calib", "gt", "--rig", str(rig), "--distance-mm", "3000",
                     "--out", str(out)]) == 2
    assert "--distance-mm" in capsys.readouterr().err
    (tmp_path / "outwards.yaml").write_text(yaml.safe_dump(outward_ring()))
    assert cli.main(["--calib", "gt", "--rig", str(tmp_path / "outwards.yaml"),
                     "--out", str(out)]) == 2
    err = capsys.readouterr().err.replace("\n", "")
    assert "outwards.yaml" in err and "neither look the same way" in err


def test_cli_costs_of_a_studio_run_with_their_spread(tmp_path):
    rig = STUDIOS["h36m"]
    truth = cameras(rig)
    run = write_run(tmp_path / "run", rig, {"zhang": turn_camera(truth, 0.3, about_centre=True),
                                            "bouguet": truth})
    out = tmp_path / "out"
    args = ["--calib", "all", "--run", str(run), "--frames", "10", "--out", str(out)]
    assert cli.main(args + ["--trials", "3"]) == 0
    res = json.loads((out / "results.json").read_text())
    m = {k: v["triangulated"] for k, v in res["methods"].items()}
    cost = m["zhang"]["excess_mpjpe_mm"]
    assert cost["n"] == 3 and cost["std"] > 0 and 5 < cost["min"] <= cost["mean"] <= cost["max"]
    # Paired in each trial: the method's MPJPE minus gt's on the same keypoints (no joint is
    # missing here, so the paired mean and the difference of the means agree).
    for t in res["trials"]:
        e = t["methods"]
        assert e["zhang"]["triangulated"]["excess_mpjpe_mm"] == pytest.approx(
            e["zhang"]["triangulated"]["mpjpe_mm"] - e["gt"]["triangulated"]["mpjpe_mm"],
            abs=1e-9)
    assert m["zhang"]["gt_mpjpe_mm"] == m["gt"]["mpjpe_mm"]  # the floor of the same trials
    # The exact rig, through the run's cam_from_cam0 and back: no cost but rounding.
    assert abs(m["bouguet"]["excess_mpjpe_mm"]["max"]) < 1e-6
    assert "| zhang | " in (out / "report.md").read_text()
    assert "no spread" not in (out / "report.md").read_text()
    assert cli.main(args + ["--trials", "1"]) == 0
    assert "no spread: 1 trial" in (out / "report.md").read_text()
