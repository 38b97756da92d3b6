"""OpenCV's cv2.calibrateMultiview (multiview_ref) against ground truth, bundle.calibrate_rig and
pycolmap's bundle adjuster, on the synthetic studio of studio_scene.py (5 cameras on a 3.5 m
ring, 640 x 480, a checkerboard of 9 x 6 inner corners at 60 mm through a 60-frame calibration
session, each camera seeing its front in about half of the frames).
"""

import cv2
import numpy as np
import pytest

if not hasattr(cv2, "calibrateMultiviewExtended"):
    pytest.skip(f"OpenCV {cv2.__version__} has no calibrateMultiview (OpenCV >= 5)",
                allow_module_level=True)

from stereo_bench.multiview import opencv_ref as multiview_ref  # noqa: E402
from stereo_bench.core.camera import project_points  # noqa: E402
from stereo_bench.multiview.opencv_ref import board_unit_mm, opencv_multiview  # noqa: E402
from stereo_bench.multiview.bundle import calibrate_rig, rig_errors, rig_start  # noqa: E402
from studio_scene import LENSES, exact_views, intrinsics_only, noisy_views, studio  # noqa: E402


@pytest.fixture(scope="module")
def noisy(rig):
    """0.3 px noise; OpenCV's rig and calibrate_rig's (from each camera's own planar_pose)."""
    cams, obj, img, found, rv, tv = noisy_views(rig)
    intr = intrinsics_only(cams)
    ours = calibrate_rig(intr, obj, img, rv, tv, found)
    return cams, obj, img, found, rv, tv, ours, opencv_multiview(intr, obj, img, found)


def test_noise_free_gives_the_true_rig_to_float32_precision(exact):
    cams, obj, img, seen, (R, t, rv, tv) = exact
    intr = intrinsics_only(cams)
    res = opencv_multiview(intr, obj, img, seen)
    err = rig_errors(res.cameras, cams)
    # Measured 2.3e-4 mm and 2.5e-7 deg. OpenCV takes float32 points: rounding a pixel
    # coordinate of 256-512 px to float32 is an error of up to 3e-5 px (RMS ~1.8e-5), 1/15000
    # of 0.3 px noise, which moves these cameras by ~1 mm: ~1e-4 mm. (In float64 pycolmap gets
    # ~3e-12.)
    assert err["translation_mm"].max() < 2e-3 and err["centre_mm"].max() < 2e-3
    assert err["rotation_deg"].max() < 5e-5
    assert res.rms_px < 1e-4 and res.log["opencv_rms_px"] < 1e-4  # measured 2e-6, 7e-6
    # Rs, Ts are cam_from_cam0 with camera 0 the reference; rvecs0, tvecs0 cam0_from_board.
    assert np.all(res.cameras[0].rvec == 0) and np.all(res.cameras[0].tvec == 0)
    used = res.frames_used
    assert np.array_equal(used, seen.sum(0) >= 2)
    assert np.abs(res.board_tvecs[used] - tv[used]).max() < 2e-3
    assert np.abs(res.board_rvecs[used] - rv[used]).max() < 1e-6
    assert np.isnan(res.board_tvecs[~used]).all()
    # Intrinsics held (CALIB_USE_INTRINSIC_GUESS), the views in the problem all accounted for.
    for est, cam in zip(res.cameras, intr):
        assert np.array_equal(est.intrinsics, cam.intrinsics) and np.array_equal(est.dist, cam.dist)
    assert res.log["n_views"] == int(seen[:, used].sum())
    assert res.log["n_observations"] == res.log["n_views"] * len(obj)
    assert res.log["left_out"] == {"partial_views": 0,
                                   "views_in_frames_seen_by_fewer": int(seen[:, ~used].sum()),
                                   "views_dropped_by_opencv": 0}
    assert np.array_equal(np.isfinite(res.log["per_view_rms_px"]), seen & used)
    assert len(res.log["initialization_pairs"]) == len(cams) - 1
    assert res.log["board_unit_mm"] == pytest.approx(np.hypot(480, 300))


def test_fisheye_cameras_go_in_as_opencv_fisheye():
    """Kannala-Brandt cameras (three of five) are OpenCV's CALIB_MODEL_FISHEYE: the noise-free
    studio gives the true rig as the pinhole one does; a fisheye's skew (which OpenCV does not
    honour) and the omnidirectional lenses (which it has not) are refused by name."""
    fisheye = {"lens": "kannala_brandt", "dist": [0.05, -0.02, 0.004, -0.001]}
    lenses = [{**lens, **fisheye} if c % 2 == 0 else lens
              for c, lens in enumerate(LENSES)]
    cams, obj, img, seen, _ = exact_views(studio(lenses))
    assert [c.model for c in cams].count("kannala_brandt") == 3
    res = opencv_multiview(intrinsics_only(cams), obj, img, seen)
    err = rig_errors(res.cameras, cams)
    # The pinhole studio's float32 bound (above; measured here 3e-4 mm, 7e-6 px).
    assert err["centre_mm"].max() < 2e-3 and err["rotation_deg"].max() < 5e-5
    assert res.rms_px < 1e-4
    with pytest.raises(ValueError, match=r"cameras\[2\] \('cam3'\): skew 0.8 is not 0"):
        opencv_multiview(intrinsics_only(cams[:2] + [cams[2].with_params(skew=0.8)] + cams[3:]),
                         obj, img, seen)
    mei = cams[1].with_params(model="mei", dist=np.array([0.9, 0.0, 0.0, 0.0, 0.0]))
    with pytest.raises(ValueError, match=r"cameras\[1\] \('cam2'\): a mei lens; "
                                         "calibrateMultiview has opencv and kannala_brandt"):
        opencv_multiview(intrinsics_only([cams[0], mei] + list(cams[2:])), obj, img, seen)


def test_noisy_rig_agrees_with_calibrate_rig(noisy):
    cams, obj, img, found, rv, tv, ours, res = noisy
    # The same observations (every view is full) ...
    assert np.array_equal(res.frames_used, ours.frames_used)
    assert res.log["n_observations"] == ours.log["n_observations"]
    # ... and nearly the same rig: OpenCV minimizes a robust cost (weight exp(-|e|^2/30) per
    # point), whose minimum sits a few percent of the error against the truth away from the
    # least-squares minimum (measured up to 1.2 % in translation, 3.1 % in rotation, 2.1 % in
    # the centre), where pycolmap sits 2e-6 of it away.
    truth = rig_errors(ours.cameras, cams)
    between = rig_errors(res.cameras, ours.cameras)
    for key in ("translation_mm", "rotation_deg", "centre_mm"):
        assert np.all(between[key][1:] < 0.1 * truth[key][1:]), key
    # Least squares is the minimum of the RMS: OpenCV's is just above it (measured 8e-7).
    assert ours.rms_px <= res.rms_px < ours.rms_px * (1 + 1e-5)
    # Near the truth as least squares is (measured 0.012 deg, 1.2 mm; boards 0.014 mm apart).
    opencv_truth = rig_errors(res.cameras, cams)
    assert opencv_truth["rotation_deg"].max() < 0.04 and opencv_truth["translation_mm"].max() < 3
    assert np.nanmax(np.abs(res.board_tvecs - ours.board_tvecs)) < 0.1  # mm


def test_noisy_rig_agrees_with_pycolmap(noisy):
    pytest.importorskip("pycolmap", reason="pycolmap not installed (pip install pycolmap)")
    from stereo_bench.multiview.colmap_ref import colmap_rig_bundle

    cams, obj, img, found, rv, tv, ours, res = noisy
    intr = intrinsics_only(cams)
    s = rig_start(intr, img, rv, tv, found)
    ref = colmap_rig_bundle(intr, obj, img, s.R, s.t, s.board_rvecs, s.board_tvecs, s.seen)
    truth = rig_errors(ref.cameras, cams)
    colmap_ours = rig_errors(ref.cameras, ours.cameras)
    colmap_opencv = rig_errors(ref.cameras, res.cameras)
    for key in ("translation_mm", "rotation_deg"):
        # Measured 2e-6 and up to 3 % of the error against the truth.
        assert np.all(colmap_ours[key][1:] < 1e-4 * truth[key][1:]), key
        assert np.all(colmap_opencv[key][1:] < 0.1 * truth[key][1:]), key


def test_opencv_reaches_its_minimum_on_this_studio(noisy):
    # With intrinsics fixed, a frame only one camera saw touches only its own board pose: at a
    # minimum adding it cannot move the rig. On this studio OpenCV's rig moves by 2e-5 of its
    # error against the truth (measured; a Gauss-Newton step of its own robust cost from its
    # solution moves it by 1e-4 of it). If this fails, OpenCV stops short of its minimum here,
    # as multiview_ref's notes (limit a) measured on a poorly conditioned studio.
    cams, obj, img, found, rv, tv, ours, res = noisy
    every = opencv_multiview(intrinsics_only(cams), obj, img, found, min_views=1)
    assert every.frames_used.sum() > res.frames_used.sum()
    moved = rig_errors(every.cameras, res.cameras)["translation_mm"][1:]
    truth = rig_errors(ours.cameras, cams)["translation_mm"][1:]
    assert np.all(moved < 1e-3 * truth)


def test_robust_weight_ignores_wrong_corners(noisy):
    cams, obj, img, found, rv, tv, ours, res = noisy
    bad, gone = img.copy(), img.copy()
    views = np.flatnonzero(found[2])[:3]
    bad[2, views, 0] += [25.0, -20.0]  # three wrong corners
    gone[2, views, 0] = np.nan  # the same corners not detected
    intr = intrinsics_only(cams)

    def moved(a, b):
        return rig_errors(a.cameras, b.cameras)["translation_mm"].max()

    opencv_moved = moved(opencv_multiview(intr, obj, bad, found), res)
    ls_moved = moved(calibrate_rig(intr, obj, bad, rv, tv, found), ours)
    gone_moved = moved(calibrate_rig(intr, obj, gone, rv, tv, found), ours)
    # Weight exp(-32^2/30) ~ 1e-15: OpenCV ignores them, moving as least squares does without
    # those three points (measured 0.0831 and 0.0832 mm); least squares with them is pulled
    # 80 times as far (measured 6.7 mm).
    assert opencv_moved == pytest.approx(gone_moved, rel=0.05)
    assert ls_moved > 20 * gone_moved


def test_partial_views_are_left_out_and_counted(noisy):
    cams, obj, img, found, rv, tv, ours, res = noisy
    rng = np.random.default_rng(3)
    part = img.copy()
    cut = np.zeros_like(found)
    for c, f in zip(*np.nonzero(found)):
        if rng.random() < 0.2:
            part[c, f, rng.choice(len(obj), 5, replace=False)] = np.nan
            cut[c, f] = True
    intr = intrinsics_only(cams)
    out = opencv_multiview(intr, obj, part, found)
    same = opencv_multiview(intr, obj, img, found & ~cut)
    assert out.log["left_out"]["partial_views"] == int(cut.sum()) > 10
    assert out.log["n_views"] == same.log["n_views"]
    for a, b in zip(out.cameras, same.cameras):
        assert np.array_equal(a.rvec, b.rvec) and np.array_equal(a.tvec, b.tvec)
    # A point outside OpenCV's valid range [0, w] x [0, h] makes a view partial too.
    edge = img.copy()
    c, f = np.argwhere(found & (found.sum(0) >= 2))[0]
    edge[c, f, 0] = [-0.2, 100.0]
    assert opencv_multiview(intr, obj, edge, found).log["left_out"]["partial_views"] == 1


def test_opencv_calibrates_each_camera_on_its_own(noisy):
    cams, obj, img, found, rv, tv, ours, res = noisy
    own = opencv_multiview(intrinsics_only(cams), obj, img, found, fix_intrinsics=False)
    assert own.frames_used.sum() == int((found.sum(0) >= 1).sum())
    # Each camera's intrinsics are cv2.calibrateCamera's on its own views (default flags: k1, k2,
    # p1, p2, k3), not refined with the rig: fx agrees to 3e-8, the projections to 1e-4 px
    # (measured; k3 from -1.4 to 0.07, from ~31 views of a board 35-170 px across).
    for c, cam in enumerate(own.cameras):
        views = np.flatnonzero(np.isfinite(own.log["per_view_rms_px"][c]))
        _, K, d, rvecs, tvecs = cv2.calibrateCamera(
            [obj.astype(np.float32)] * len(views), [img[c, f].astype(np.float32) for f in views],
            cam.size, None, None)
        assert cam.fx == pytest.approx(K[0, 0], rel=1e-6)
        assert not np.any(cam.dist[5:])
        for f, r, t in zip(views, rvecs, tvecs):
            uv = cv2.projectPoints(obj, r, t, K, d)[0].reshape(-1, 2)
            assert np.abs(project_points(obj, cam.intrinsics, cam.dist, r.ravel(), t.ravel())
                          - uv).max() < 1e-3
    assert own.log["fix_intrinsics"] is False and own.log["flags"] == 0


def test_millimetres_would_trip_opencv_and_its_error_is_a_runtime_error(noisy, monkeypatch):
    cams, obj, img, found, rv, tv, ours, res = noisy
    assert board_unit_mm(obj) == pytest.approx(566.04, abs=0.01)
    monkeypatch.setattr(multiview_ref, "board_unit_mm", lambda points: 1.0)  # points in mm
    with pytest.raises(RuntimeError, match="calibrateMultiview failed.*Pattern points are "
                                           "collinear"):
        opencv_multiview(intrinsics_only(cams), obj, img, found)


def test_bad_input_is_named(exact):
    cams, obj, img, seen, _ = exact
    intr = intrinsics_only(cams)

    def call(**change):
        args = dict(cameras=intr, object_points=obj, image_points=img, seen=seen)
        args.update(change)
        return opencv_multiview(**args)

    with pytest.raises(ValueError, match="cameras: expected at least 2"):
        call(cameras=intr[:1])
    with pytest.raises(ValueError, match=r"cameras\[2\]: expected a stereo_bench Camera"):
        call(cameras=intr[:2] + ["cam2"] + intr[3:])
    with pytest.raises(ValueError, match=r"cameras\[1\] \('cam2'\): skew"):
        call(cameras=[intr[0], intr[1].with_params(skew=0.5)] + intr[2:])
    with pytest.raises(ValueError, match="image_points: expected shape"):
        call(image_points=img[..., 0])
    with pytest.raises(ValueError, match="object_points: expected shape"):
        call(object_points=obj[:10])
    with pytest.raises(ValueError, match="object_points: the points are collinear"):
        call(object_points=obj * [1, 0, 0])
    with pytest.raises(ValueError, match="object_points: expected a planar board"):
        call(object_points=obj + [0, 0, 1.0], fix_intrinsics=False)
    with pytest.raises(ValueError, match="seen: expected a bool array"):
        call(seen=seen.astype(int))
    with pytest.raises(ValueError, match="fix_intrinsics: expected True or False"):
        call(fix_intrinsics="yes")
    with pytest.raises(ValueError, match="intrinsics_flags: only used when"):
        call(intrinsics_flags=cv2.CALIB_FIX_K3)
    with pytest.raises(ValueError, match="intrinsics_flags: CALIB_USE_INTRINSIC_GUESS"):
        call(fix_intrinsics=False, intrinsics_flags=cv2.CALIB_USE_INTRINSIC_GUESS)
    with pytest.raises(ValueError, match="intrinsics_flags: expected one non-negative int"):
        call(fix_intrinsics=False, intrinsics_flags=[0, 0])
    with pytest.raises(ValueError, match="min_views: expected an int from 1 to 5"):
        call(min_views=0)
    lonely = seen.copy()
    lonely[4, lonely[:4].sum(0) >= 1] = False  # cam5 keeps only frames no other camera saw
    with pytest.raises(ValueError, match=r"seen: cameras \['cam5'\] have no full view"):
        call(seen=lonely)
    apart = seen.copy()
    apart[3:, :] &= ~apart[:3].any(0)  # cam4 and cam5 only see frames together
    with pytest.raises(ValueError, match=r"seen: cameras \['cam4', 'cam5'\] share no full view"):
        call(seen=apart)


def test_the_rigs_adjustment_fits_a_bowed_boards_shape():
    """The reference studio with its board bowed (1.0, 0.6) mm and stretched 0.2 % in y: from
    each camera's own flat-board poses and a flat start, the rig's adjustment with the board's
    shape free finds the shape and the true rig from exact pixels (the project's solver; OpenCV's
    calibrateMultiview has no such parameter)."""
    import dataclasses

    from stereo_bench.core.board_shape import BoardShape
    from studio_scene import board_poses

    rig = studio()
    bowed = dataclasses.replace(rig, board=BoardShape.for_pattern(
        rig.pattern, aspect_error_pct=0.2, warp_mm=(1.0, 0.6)))
    cams, obj, img, seen, _ = exact_views(bowed)
    rv, tv, found = board_poses(cams, obj, img)
    res = calibrate_rig(intrinsics_only(cams), obj, img, rv, tv, found,
                        board=BoardShape.of_points(obj))
    shape = res.log["board_shape"]
    assert shape["warp_x_mm"] == pytest.approx(1.0, abs=1e-6)
    assert shape["warp_y_mm"] == pytest.approx(0.6, abs=1e-6)
    assert shape["aspect_error_pct"] == pytest.approx(0.2, abs=1e-6)
    err = rig_errors(res.cameras, cams)
    assert err["centre_mm"].max() < 1e-6 and res.rms_px < 1e-8
    flat = calibrate_rig(intrinsics_only(cams), obj, img, rv, tv, found)
    assert flat.rms_px > 0.03  # measured 0.056 px: a flat board cannot explain the bowed one
