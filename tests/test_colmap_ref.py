"""pycolmap's bundle adjuster (colmap_ref) against ground truth and against stereo.calibrate_rig.

The synthetic studio of studio_scene.py: 5 cameras (640 x 480, fx ~ 500, distortion; cameras 1
and 3 with k3, so COLMAP's FULL_OPENCV, the others OPENCV) on a 3.5 m ring looking at the centre,
and a 9 x 6 board at 60 mm that moves through the volume facing a random horizontal direction; a
camera sees a frame when it faces the board's front and every point is inside its image.
"""

import numpy as np
import pytest

pycolmap = pytest.importorskip("pycolmap", reason="pycolmap not installed (pip install pycolmap)")

from stereo_bench import colmap_ref  # noqa: E402
from stereo_bench.colmap_ref import (colmap_rig_bundle, rig_reconstruction,  # noqa: E402
                                     to_colmap_camera)
from stereo_bench.stereo import calibrate_rig, rig_errors, rig_start  # noqa: E402
from studio_scene import (board, intrinsics_only, observe, perturbed,  # noqa: E402
                          pnp_board_poses, ring, true_start)


@pytest.fixture(scope="module")
def exact():
    cams, obj = ring(), board()
    R_wb, t_wb, img = observe(cams, obj, 0.0)
    seen = np.all(np.isfinite(img), axis=(-1, -2))
    return cams, obj, img, seen, true_start(cams, R_wb, t_wb)


@pytest.fixture(scope="module")
def noisy():
    """0.3 px noise; per-camera cam_from_board by cv2.solvePnP, as a calibration would give."""
    cams, obj = ring(), board()
    R_wb, t_wb, img = observe(cams, obj, 0.3, seed=1)
    rv, tv, found = pnp_board_poses(cams, obj, img)
    return cams, obj, img, found, rv, tv


def test_studio_is_a_real_studio(exact):
    cams, obj, img, seen, _ = exact
    per_frame = seen.sum(0)
    # Each camera sees about a third of the frames, most frames are seen by two or three.
    assert np.all((seen.sum(1) > 15) & (seen.sum(1) < 35))
    assert (per_frame >= 2).sum() > 45 and per_frame.max() <= 3
    assert [colmap_ref.colmap_model(c)[0] for c in cams] == ["OPENCV", "FULL_OPENCV"] * 2 + [
        "OPENCV"]


def test_noise_free_from_a_perturbed_start_gives_the_true_rig(exact):
    cams, obj, img, seen, truth = exact
    R, t, rv, tv = perturbed(*truth)
    res = colmap_rig_bundle(intrinsics_only(cams), obj, img, R, t, rv, tv, seen)
    err = rig_errors(res.cameras, cams)
    # Measured ~1e-11 mm and ~1e-15 rad (Ceres in double precision, tolerances 1e-15).
    assert err["translation_mm"].max() < 1e-6
    assert np.radians(err["rotation_deg"]).max() < 1e-8
    assert res.rms_px < 1e-9 and res.rms_px_per_camera.max() < 1e-9
    used = res.frames_used
    assert np.array_equal(used, seen.sum(0) >= 2)
    assert np.abs(res.board_tvecs[used] - truth[3][used]).max() < 1e-6
    assert np.isnan(res.board_tvecs[~used]).all()
    assert res.log["initial_rms_px"] > 5  # the start was genuinely off
    assert res.log["termination"] == "CONVERGENCE" and res.log["usable"]
    assert res.log["final_cost"] < 1e-12 < res.log["initial_cost"]
    assert res.log["dropped_observations"] == 0
    assert res.log["n_observations"] == int(np.isfinite(img[..., 0])[:, used].sum())


def test_noisy_rig_agrees_with_calibrate_rig_from_the_same_start(noisy):
    cams, obj, img, found, rv, tv = noisy
    intr = intrinsics_only(cams)
    ref = calibrate_rig(intr, obj, img, rv, tv, found)
    start = rig_start(intr, img, rv, tv, found)
    R, t, rv0, tv0, seen = start.R, start.t, start.board_rvecs, start.board_tvecs, start.seen
    res = colmap_rig_bundle(intr, obj, img, R, t, rv0, tv0, seen)
    # The same observations and the same start ...
    assert np.array_equal(res.frames_used, ref.frames_used)
    assert res.log["n_observations"] == ref.log["n_observations"]
    assert res.log["initial_rms_px"] == pytest.approx(ref.log["initial_rms_px"], rel=1e-12)
    # ... the same minimum: the rms to 1e-9 (measured ~1e-14), each camera's pose to a tiny
    # fraction of its error against the truth (measured 3e-5 of it: at its default tolerance
    # scipy stops ~5e-5 mm short of the minimum one Gauss-Newton step predicts, Ceres ~1e-8 mm).
    assert res.rms_px == pytest.approx(ref.rms_px, rel=1e-9)
    assert np.allclose(res.rms_px_per_camera, ref.rms_px_per_camera, rtol=1e-9)
    truth_err = rig_errors(ref.cameras, cams)
    between = rig_errors(res.cameras, ref.cameras)
    assert np.all(between["translation_mm"][1:] < 1e-3 * truth_err["translation_mm"][1:])
    assert np.all(between["rotation_deg"][1:] < 1e-3 * truth_err["rotation_deg"][1:])
    assert np.nanmax(np.abs(res.board_tvecs - ref.board_tvecs)) < 1e-2  # mm
    # Both near the truth (a poorly conditioned studio: 70 px boards, 0.3 px noise).
    assert truth_err["rotation_deg"].max() < 0.3 and truth_err["translation_mm"].max() < 20
    assert rig_errors(res.cameras, cams)["translation_mm"].max() < 20


def test_colmap_projects_like_the_project_camera_half_a_pixel_over(exact):
    cams, obj, img, seen, truth = exact
    rng = np.random.default_rng(7)
    P = np.concatenate([rng.uniform(-0.7, 0.7, (200, 2)), np.ones((200, 1))], -1)
    P *= rng.uniform(500, 5000, (200, 1))
    for c, cam in enumerate(cams):
        uv_colmap = to_colmap_camera(cam, c + 1).img_from_cam(P)
        # COLMAP's pixel (0.5, 0.5) is OpenCV's (0, 0): exactly +0.5 in u and v.
        assert np.abs(uv_colmap - cam.project_cam(P) - 0.5).max() < 1e-9
    # The reconstruction at the true poses reproduces every stored observation.
    layout = rig_reconstruction(cams, obj, img, *truth, seen)
    rec = layout.reconstruction
    assert rec.is_valid() and rec.num_points3D() == len(obj)
    worst = 0.0
    for image in rec.images.values():
        for p in image.points2D:
            uv = image.project_point(rec.points3D[p.point3D_id].xyz)
            worst = max(worst, float(np.abs(uv - p.xy).max()))
    assert worst < 1e-9


def test_a_wrong_pixel_convention_would_be_caught(exact, monkeypatch):
    cams, obj, img, seen, truth = exact
    R, t, rv, tv = perturbed(*truth)
    # Convert the principal point but forget the observations: half a pixel off in u and v.
    monkeypatch.setattr(colmap_ref, "opencv_to_colmap_pixels", lambda uv: np.asarray(uv))
    res = colmap_rig_bundle(intrinsics_only(cams), obj, img, R, t, rv, tv, seen)
    err = rig_errors(res.cameras, cams)
    # COLMAP's own cost absorbs most of it into the poses (measured 0.004 px), which end up
    # millimetres and a tenth of a degree off; through the project's model the shift is plain.
    assert res.log["colmap_rms_px"] < 0.05
    assert res.rms_px == pytest.approx(0.5 * np.sqrt(2), rel=0.01)
    assert err["translation_mm"].max() > 1.0 and err["rotation_deg"].max() > 0.01


def test_refined_intrinsics_come_back_in_the_project_convention(exact):
    cams, obj, img, seen, truth = exact
    R, t, rv, tv = perturbed(*truth)
    off = [c.with_params(fx=c.fx * 1.01, fy=c.fy * 0.99, cx=c.cx + 3, cy=c.cy - 2,
                         dist=c.dist + [0.01, -0.005, 1e-4, -1e-4, 0, 0, 0, 0])
           for c in intrinsics_only(cams)]
    res = colmap_rig_bundle(off, obj, img, R, t, rv, tv, seen, refine_intrinsics=True)
    assert res.frames_used.all()  # frames seen by one camera constrain its intrinsics
    err = rig_errors(res.cameras, cams)
    assert err["translation_mm"].max() < 1e-6 and res.rms_px < 1e-9
    for est, true, model in zip(res.cameras, cams, res.log["camera_models"]):
        assert np.abs(est.intrinsics - true.intrinsics).max() < 1e-6  # cx, cy back by -0.5
        if model == "OPENCV":
            assert np.abs(est.dist - true.dist).max() < 1e-9
        # FULL_OPENCV's k3..k6 are not identified by planar views (measured 0.005 off at zero
        # residual): the projection is exact, the coefficients need not be.


def test_robust_loss_resists_wrong_corners(exact):
    cams, obj, img, seen, truth = exact
    R, t, rv, tv = perturbed(*truth)
    bad = img.copy()
    bad[2, np.flatnonzero(seen[2])[:3], 0] += [25.0, -20.0]  # three wrong corners
    intr = intrinsics_only(cams)
    plain = colmap_rig_bundle(intr, obj, bad, R, t, rv, tv, seen)
    robust = colmap_rig_bundle(intr, obj, bad, R, t, rv, tv, seen, loss="huber")
    e_plain = rig_errors(plain.cameras, cams)["translation_mm"].max()
    e_robust = rig_errors(robust.cameras, cams)["translation_mm"].max()
    assert e_plain > 5 and e_robust < e_plain / 10  # measured 20 mm and 0.6 mm
    assert robust.log["loss"] == "huber" and robust.log["colmap_rms_px"] is None


def test_a_point_observed_once_is_dropped_and_counted(exact):
    cams, obj, img, seen, truth = exact
    img = img.copy()
    once = np.argwhere(np.isfinite(img[:, :, 0, 0]) & (seen.sum(0) >= 2)[None])[0]
    keep = img[once[0], once[1], 0].copy()
    img[:, :, 0] = np.nan
    img[once[0], once[1], 0] = keep  # board point 0 is seen once in the whole capture
    res = colmap_rig_bundle(intrinsics_only(cams), obj, img, *truth, seen)
    assert res.log["dropped_observations"] == 1
    assert rig_errors(res.cameras, cams)["translation_mm"].max() < 1e-6


def test_bad_input_is_named(exact):
    cams, obj, img, seen, truth = exact
    R, t, rv, tv = truth
    intr = intrinsics_only(cams)

    def call(**change):
        args = dict(cameras=intr, object_points=obj, image_points=img, cam_from_cam0_R=R,
                    cam_from_cam0_t=t, board_rvecs=rv, board_tvecs=tv, seen=seen)
        args.update(change)
        return colmap_rig_bundle(**args)

    with pytest.raises(ValueError, match="cameras: expected at least 2"):
        call(cameras=intr[:1])
    with pytest.raises(ValueError, match="'cam1'.*skew"):
        call(cameras=[intr[0], intr[1].with_params(skew=0.5)] + intr[2:])
    with pytest.raises(ValueError, match="image_points: expected shape"):
        call(image_points=img[..., 0])
    with pytest.raises(ValueError, match="object_points: expected shape"):
        call(object_points=obj[:10])
    with pytest.raises(ValueError, match="cam_from_cam0_R: expected rotation"):
        call(cam_from_cam0_R=R * 2)
    with pytest.raises(ValueError, match="identity for camera 'cam0'"):
        call(cam_from_cam0_t=t + 1.0)
    with pytest.raises(ValueError, match=r"board_tvecs: expected shape \(60, 3\)"):
        call(board_tvecs=tv[:5])
    used = np.flatnonzero(seen.sum(0) >= 2)[0]
    nan_pose = tv.copy()
    nan_pose[used] = np.nan
    with pytest.raises(ValueError, match=f"finite initial pose.*frames \\[{used}\\]"):
        call(board_tvecs=nan_pose)
    with pytest.raises(ValueError, match="seen: expected a bool array"):
        call(seen=seen.astype(int))
    lonely = seen.copy()
    lonely[4, lonely[:4].sum(0) >= 1] = False  # cam4 keeps only frames no other camera saw
    with pytest.raises(ValueError, match=r"\['cam4'\] see no frame together"):
        call(seen=lonely)
    with pytest.raises(ValueError, match="loss: expected one of"):
        call(loss="tukey")
    with pytest.raises(ValueError, match="loss_scale_px"):
        call(loss="huber", loss_scale_px=0.0)


def test_missing_pycolmap_is_a_clear_import_error(monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "pycolmap", None)
    with pytest.raises(ImportError, match="pip install pycolmap"):
        colmap_ref.to_colmap_camera(ring()[0], 1)
