"""pycolmap's bundle adjuster (colmap_ref) against ground truth and against bundle.calibrate_rig.

The synthetic studio of studio_scene.py, built by the package: 5 cameras (640 x 480, fx ~ 500,
distortion; cameras 1 and 3 with k3, so COLMAP's FULL_OPENCV, the others OPENCV) on a 3.5 m ring
looking at the centre, and a checkerboard of 9 x 6 inner corners at 60 mm carried through a
60-frame calibration session; a camera sees a frame when the board's front faces it and every
point is inside its image.
"""

import numpy as np
import pytest

pycolmap = pytest.importorskip("pycolmap", reason="pycolmap not installed (pip install pycolmap)")

from stereo_bench.multiview import colmap_ref  # noqa: E402
from stereo_bench.multiview.colmap_ref import (colmap_rig_bundle, rig_reconstruction,  # noqa: E402
                                               to_colmap_camera)
from stereo_bench.multiview.bundle import calibrate_rig, rig_errors, rig_start  # noqa: E402
from studio_scene import intrinsics_only, noisy_views, perturbed  # noqa: E402


@pytest.fixture(scope="module")
def noisy(rig):
    """0.3 px noise; each camera's own cam_from_board (planar_pose), as a calibration starts."""
    return noisy_views(rig)


def test_studio_is_a_real_studio(exact):
    cams, obj, img, seen, _ = exact
    per_frame = seen.sum(0)
    # Each camera sees about half of the 60 frames (measured 30-32), most frames are seen by two
    # or three (measured 23 and 30 frames), a few by one (3) or four (4), none by all five.
    assert np.all((seen.sum(1) > 20) & (seen.sum(1) < 40))
    assert (per_frame >= 2).sum() > 50 and (per_frame == 1).any() and per_frame.max() <= 4
    assert [colmap_ref.colmap_model(c)[0] for c in cams] == ["OPENCV", "FULL_OPENCV"] * 2 + [
        "OPENCV"]


def test_noise_free_from_a_perturbed_start_gives_the_true_rig(exact):
    cams, obj, img, seen, truth = exact
    R, t, rv, tv = perturbed(*truth)
    res = colmap_rig_bundle(intrinsics_only(cams), obj, img, R, t, rv, tv, seen)
    err = rig_errors(res.cameras, cams)
    # Measured ~3e-12 mm and ~6e-16 rad (Ceres in double precision, tolerances 1e-15).
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
    # ... the same minimum: the rms to 1e-9 (measured 1e-15, per camera 2e-10), each camera's
    # pose to a tiny fraction of its error against the truth (measured 2e-6 of it: at its
    # default tolerance scipy stops ~1e-6 mm short of the minimum one Gauss-Newton step
    # predicts, Ceres ~4e-8 mm), the board poses to 1e-4 mm (measured 9e-7).
    assert res.rms_px == pytest.approx(ref.rms_px, rel=1e-9)
    assert np.allclose(res.rms_px_per_camera, ref.rms_px_per_camera, rtol=1e-9)
    truth_err = rig_errors(ref.cameras, cams)
    between = rig_errors(res.cameras, ref.cameras)
    assert np.all(between["translation_mm"][1:] < 1e-4 * truth_err["translation_mm"][1:])
    assert np.all(between["rotation_deg"][1:] < 1e-4 * truth_err["rotation_deg"][1:])
    assert np.nanmax(np.abs(res.board_tvecs - ref.board_tvecs)) < 1e-4  # mm
    # Both near the truth (35-170 px boards, 0.3 px noise: measured 1.2 mm and 0.012 deg).
    assert truth_err["rotation_deg"].max() < 0.04 and truth_err["translation_mm"].max() < 3
    assert rig_errors(res.cameras, cams)["translation_mm"].max() < 3


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
    # COLMAP's own cost absorbs most of it into the poses (measured 0.015 px), which end up
    # millimetres and a tenth of a degree off (measured 9.5 mm, 0.11 deg); through the
    # project's model the shift is plain.
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
    # Measured 7e-9 mm and 3e-11 px. Ceres spends its 200 steps creeping along the directions
    # FULL_OPENCV's coefficients leave undetermined (terminating NO_CONVERGENCE, its cost down
    # to 3e-18): the rig is exact to 3e-8 mm after 20 of them.
    assert err["translation_mm"].max() < 1e-6 and res.rms_px < 1e-9
    for est, true, model in zip(res.cameras, cams, res.log["camera_models"]):
        assert np.abs(est.intrinsics - true.intrinsics).max() < 1e-6  # cx, cy back by -0.5
        if model == "OPENCV":
            assert np.abs(est.dist - true.dist).max() < 1e-9
        # FULL_OPENCV's k3..k6 are not identified by planar views (measured up to 0.005 off at
        # zero residual): the projection is exact, the coefficients need not be.


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
    # Measured 6.7 mm and 0.22 mm: the corners pull least squares by millimetres, Huber's
    # loss by a thirtieth of that.
    assert e_plain > 3 and e_robust < e_plain / 10
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
    with pytest.raises(ValueError, match="'cam2'.*skew"):
        call(cameras=[intr[0], intr[1].with_params(skew=0.5)] + intr[2:])
    with pytest.raises(ValueError, match="image_points: expected shape"):
        call(image_points=img[..., 0])
    with pytest.raises(ValueError, match="object_points: expected shape"):
        call(object_points=obj[:10])
    with pytest.raises(ValueError, match="cam_from_cam0_R: expected rotation"):
        call(cam_from_cam0_R=R * 2)
    with pytest.raises(ValueError, match="identity for camera 'cam1'"):
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
    lonely[4, lonely[:4].sum(0) >= 1] = False  # cam5 keeps only frames no other camera saw
    with pytest.raises(ValueError, match=r"\['cam5'\] see no frame together"):
        call(seen=lonely)
    apart = seen.copy()
    apart[3:, :] &= ~apart[:3].any(0)  # cam4 and cam5 only see frames together
    with pytest.raises(ValueError, match=r"\['cam4', 'cam5'\] share no frame with camera 'cam1'"):
        call(seen=apart)
    with pytest.raises(ValueError, match="loss: expected one of"):
        call(loss="tukey")
    with pytest.raises(ValueError, match="loss_scale_px"):
        call(loss="huber", loss_scale_px=0.0)


def test_missing_pycolmap_is_a_clear_import_error(rig, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "pycolmap", None)
    with pytest.raises(ImportError, match="pip install pycolmap"):
        colmap_ref.to_colmap_camera(rig.cameras[0], 1)
