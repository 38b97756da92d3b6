"""Motion-capture studios: rig layouts, the calibration session, and the multi-camera
calibration (covisibility graph, then bundle adjustment) against exact ground truth."""

from pathlib import Path

import numpy as np
import pytest

from stereo_bench.calibrate import get_calibrator
from stereo_bench.calibrate.base import Observations
from stereo_bench.core.poses import matrix_to_rodrigues
from stereo_bench.config.bounds import ConfigError
from stereo_bench.config.schema import load_rig, parse_rig
from stereo_bench.scene.rig import Rig, volume_centre
from stereo_bench.multiview.bundle import (aligned_rig_errors, calibrate_rig, rig_errors,
                                           similarity_transform, unreachable)
from stereo_bench.core.poses import cam_from_cam0
from stereo_bench.calibrate.pose import planar_pose

STUDIOS = sorted((Path(__file__).resolve().parents[2] / "configs" / "studios").glob("*.yaml"))
LENS = {"width": 640, "height": 480, "fx": 500.0, "fy": 500.0, "cx": 319.5, "cy": 239.5,
        "dist": [-0.1, 0.05, 0.0, 0.0]}


def studio_dict(**studio):
    return {"name": "s", "pattern": {"kind": "charuco", "squares_x": 7, "squares_y": 5,
                                     "square_mm": 80.0, "marker_mm": 60.0,
                                     "dictionary": "DICT_4X4_50"},
            "studio": {"layout": "ring", "count": 4, "radius_mm": 3000.0, "lenses": [LENS],
                       **studio},
            "trajectory": {"kind": "session", "frames": 60, "turns": 2, "closeups": 12}}


def test_ring_layout_places_cameras_on_the_circle_looking_at_the_target():
    cfg = parse_rig(studio_dict(count=6, height_mm=[1500.0, 2500.0], start_deg=30.0))
    cams = cfg.cameras_true()
    centres = np.stack([c.center for c in cams])
    assert np.allclose(np.hypot(centres[:, 0], centres[:, 1]), 3000.0)
    assert np.allclose(centres[:, 2], [1500, 2500] * 3)
    angles = np.degrees(np.arctan2(centres[:, 1], centres[:, 0])) % 360
    assert np.allclose(angles, (30 + 60 * np.arange(6)) % 360)
    target = np.array([0.0, 0.0, 1000.0])
    for c in cams:  # the optical axis passes through the target, the image is upright
        v = (target - c.center) / np.linalg.norm(target - c.center)
        assert np.allclose(c.R[2], v, atol=1e-12)
        assert c.R[1] @ np.array([0.0, 0.0, 1.0]) < 0  # image y points down the world
    assert np.allclose(volume_centre(cams), target, atol=1e-9)
    assert [c.name for c in cams] == [f"cam{i}" for i in range(1, 7)]


def test_half_ring_and_rectangle_layouts():
    half = parse_rig(studio_dict(count=5, arc_deg=180.0)).cameras_true()
    angles = [np.degrees(np.arctan2(c.center[1], c.center[0])) for c in half]
    assert np.allclose(angles, [0, 45, 90, 135, 180])
    rect = parse_rig(studio_dict(layout="rectangle", size_mm=[3600.0, 8400.0],
                                 radius_mm=None)).cameras
    centres = np.array([c.position_mm for c in rect])[:, :2]
    assert sorted(map(tuple, centres.tolist())) == [(-1800, -4200), (-1800, 4200),
                                                    (1800, -4200), (1800, 4200)]
    # Consecutive cameras go round the rectangle: pairs on the long sides (x = -1800, +1800).
    assert centres[0, 0] == centres[1, 0] and centres[2, 0] == centres[3, 0]


def test_mixed_lenses_are_taken_in_turn_and_the_expansion_round_trips():
    wide = {**LENS, "fx": 300.0, "fy": 300.0}
    cfg = parse_rig(studio_dict(count=4, lenses=[LENS, wide], names=["a", "b", "c", "d"]))
    assert [c.fx for c in cfg.cameras] == [500, 300, 500, 300]
    assert [c.name for c in cfg.cameras] == ["a", "b", "c", "d"]
    # The resolved configuration lists the cameras; read back, it is the same rig.
    again = parse_rig(cfg.model_dump(mode="json"))
    assert again == cfg and again.studio is None


@pytest.mark.parametrize("change, message", [
    ({"radius_mm": None}, "radius_mm: required for a ring"),
    ({"layout": "rectangle", "size_mm": [3000.0, 4000.0], "count": 5}, "expected an even count"),
    ({"names": ["a"]}, "names: expected 4 names"),
    ({"count": 1}, "studio.count"),
    ({"lenses": []}, "studio.lenses"),
    ({"lenses": [{**LENS, "cx": 5.0}]}, "cx: 5.0 lies outside the central 90 %"),
])
def test_bad_studios_are_refused_naming_the_field(change, message):
    d = studio_dict()
    d["studio"].update(change)
    with pytest.raises(ConfigError, match=message):
        parse_rig(d, "studio.yaml")


def test_cameras_and_studio_together_are_refused():
    d = studio_dict()
    d["cameras"] = [{**LENS, "name": "x"}]
    with pytest.raises(ConfigError, match="either a list of cameras or a studio"):
        parse_rig(d, "studio.yaml")


def test_spring_around_a_studio_is_refused_with_the_way_out():
    d = studio_dict()
    d["trajectory"] = {"kind": "spring", "frames": 10}
    with pytest.raises(ValueError, match="trajectory.kind: session"):
        Rig.from_config(parse_rig(d))
    d["trajectory"] = {"kind": "spring", "closeups": 3}
    with pytest.raises(ConfigError, match="closeups: only a session trajectory"):
        parse_rig(d)


@pytest.mark.parametrize("path", STUDIOS, ids=[p.stem for p in STUDIOS])
def test_session_shows_each_camera_the_board_part_of_the_time(path):
    cfg = load_rig(path)
    rig = Rig.from_config(cfg)
    tr = cfg.trajectory
    C = len(rig.cameras)
    assert len(rig.trajectory) == tr.frames + C * tr.closeups
    assert np.array_equal(rig.closeup_of,
                          np.repeat(np.arange(-1, C), [tr.frames] + [tr.closeups] * C))
    gt = rig.ground_truth()
    seen = gt.visible.sum(axis=2) >= 8  # (C, F)
    walk = rig.closeup_of < 0
    for c in range(C):
        # Part of the time, not always: the board's front faces each camera in turn.
        assert 0.2 * tr.frames <= seen[c, walk].sum() <= 0.8 * tr.frames
        # Its own close-ups show it the whole board in nearly every frame.
        own = rig.closeup_of == c
        assert gt.visible[c, own].all(axis=1).mean() >= 0.9
    # The walk joins every camera to every other through frames two cameras share, seen
    # within 60 degrees of the board's normal (beyond, ArUco markers are rarely read), for
    # every seed tried: the session's path is drawn from the seed.
    for seed in range(4):
        rig = Rig.from_config(cfg.model_copy(update={"seed": seed}))
        ok = rig.ground_truth().visible.sum(axis=2) >= 8
        for c, cam in enumerate(rig.cameras):
            R, t = rig.cam_from_board(cam)
            cos = np.abs(np.einsum("fi,fi->f", R[:, :, 2], t)) / np.linalg.norm(t, axis=1)
            ok[c] &= cos > np.cos(np.radians(60))
        assert unreachable(ok & (rig.closeup_of < 0)) == [], seed


def exact_studio(closeups=12):
    """A 4-camera ring, its exact board observations (C, F, N, 2; NaN where unseen) and
    the board points."""
    d = studio_dict()
    d["trajectory"]["closeups"] = closeups
    rig = Rig.from_config(parse_rig(d))
    gt = rig.ground_truth()
    return rig, np.where(gt.visible[..., None], gt.points, np.nan), rig.pattern.object_points()


def per_camera(rig, img, obj, method, frames=None):
    """Each camera calibrated alone by ``method`` on its views with 8+ points; its estimate and
    per-frame cam_from_board (planar poses for frames its calibration did not use)."""
    C, F = img.shape[:2]
    cams, rv, tv = [], np.full((C, F, 3), np.nan), np.full((C, F, 3), np.nan)
    for c, cam in enumerate(rig.cameras):
        ok = np.isfinite(img[c]).all(-1)
        views = np.flatnonzero((ok.sum(1) >= 8) & (frames[c] if frames is not None else True))
        obs = Observations([obj[ok[f]] for f in views], [img[c, f][ok[f]] for f in views],
                           cam.size, views, cam.name)
        res = get_calibrator(method).calibrate(obs)
        cams.append(res.camera)
        rv[c, views], tv[c, views] = res.rvecs, res.tvecs
        for f in np.flatnonzero(ok.sum(1) >= 8):
            if f not in views:
                rv[c, f], tv[c, f] = planar_pose(res.camera, obj[ok[f]], img[c, f][ok[f]])
    return cams, rv, tv


def pose_errors(estimated, truth):
    e = rig_errors(estimated, truth)
    return e["centre_mm"].max(), np.radians(e["rotation_deg"]).max()


@pytest.mark.parametrize("method", ["zhang", "bouguet", "opencv"])
def test_noise_free_studio_is_recovered_exactly(method):
    """Graph then bundle adjustment, from each method's own intrinsics: every camera's pose to
    1e-6 mm and 1e-8 rad. Zhang's and Bouguet's estimates are exact on exact data, so the rig
    with their intrinsics fixed is too; cv2.calibrateCamera works in float32 image points
    (1e-5 px here), so its intrinsics carry that rounding until the rig's adjustment refines
    them with the parameters it estimates. The refinement runs with the plain loss: from that
    float32 start, scipy's trust region under soft_l1 stops at 8e-6 mm (xtol on a step its
    loss rescaling shrinks), good enough for any user but not for this test's digits."""
    rig, img, obj = exact_studio()
    cams, rv, tv = per_camera(rig, img, obj, method)
    params = get_calibrator(method).model_parameters
    fixed = calibrate_rig(cams, obj, img, rv, tv, loss="soft_l1")
    refined = calibrate_rig(cams, obj, img, rv, tv, refine_intrinsics=[params] * len(cams))
    for result in ([fixed] if method != "opencv" else []) + [refined]:
        centre, rotation = pose_errors(result.cameras, rig.cameras)
        assert centre < 1e-6 and rotation < 1e-8, (method, centre, rotation)
        assert result.rms_px < 1e-6
    for est, true in zip(refined.cameras, rig.cameras):
        assert abs(est.fx - true.fx) < 1e-6 and abs(est.dist[0] - true.dist[0]) < 1e-9
    assert refined.log["refined_intrinsics"]["cam1"] == list(
        n for n in ("fx", "fy", "cx", "cy", "skew", "k1", "k2", "p1", "p2", "k3", "k4", "k5",
                    "k6") if n in params)


def test_intrinsics_from_closeups_only_still_join_the_rig_exactly():
    """Intrinsics from each camera's close-ups alone; the session frames enter the rig through
    planar poses computed with those intrinsics."""
    rig, img, obj = exact_studio()
    frames = np.stack([rig.closeup_of == c for c in range(len(rig.cameras))])
    cams, rv, tv = per_camera(rig, img, obj, "zhang", frames)
    result = calibrate_rig(cams, obj, img, rv, tv)
    centre, rotation = pose_errors(result.cameras, rig.cameras)
    assert centre < 1e-6 and rotation < 1e-8
    # The covisibility the rig reports is the frames each pair saw together.
    seen = np.isfinite(img).all(-1).sum(-1) >= 8
    assert np.array_equal(result.log["covisibility"], (seen[:, None] & seen[None]).sum(-1))


def test_a_camera_no_other_shares_a_frame_with_is_named():
    rig, img, obj = exact_studio()
    cams, rv, tv = per_camera(rig, img, obj, "zhang")
    img = img.copy()
    own = rig.closeup_of == 2
    img[2, ~own] = np.nan  # cam3 keeps only its own close-ups, which no other camera sees
    img[np.ix_([0, 1, 3], own)] = np.nan
    with pytest.raises(ValueError, match=r"cameras \['cam3'\] share no frame"):
        calibrate_rig(cams, obj, img, rv, tv)


def test_robust_loss_resists_wrong_corners():
    rig, img, obj = exact_studio()
    cams, rv, tv = per_camera(rig, img, obj, "zhang")
    rng = np.random.default_rng(1)
    noisy = img + rng.normal(0, 0.3, img.shape)
    bad = rng.random(img.shape[:3]) < 0.01  # 1 % of the corners 5-15 px off
    noisy[bad] += rng.choice([-1, 1], (bad.sum(), 2)) * rng.uniform(5, 15, (bad.sum(), 2))
    plain = calibrate_rig(cams, obj, noisy, rv, tv)
    robust = calibrate_rig(cams, obj, noisy, rv, tv, loss="soft_l1", loss_scale_px=1.0)
    assert pose_errors(robust.cameras, rig.cameras)[0] < 0.5 * pose_errors(
        plain.cameras, rig.cameras)[0]


def test_similarity_alignment_forgives_reference_and_scale_only():
    rig, _, _ = exact_studio()
    truth = rig.cameras
    # The true rig scaled by 1 % about the reference camera: large centre errors, none aligned.
    R, t = cam_from_cam0(truth)
    scaled = [c.with_params(rvec=matrix_to_rodrigues(R[i]), tvec=1.01 * t[i])
              for i, c in enumerate(truth)]
    errors = rig_errors(scaled, truth)
    aligned = aligned_rig_errors(scaled, truth)
    assert errors["centre_mm"].max() > 10 and errors["rotation_deg"].max() < 1e-9
    assert aligned["centre_mm"].max() < 1e-9 and aligned["rotation_deg"].max() < 1e-9
    assert abs(aligned["scale"] - 1 / 1.01) < 1e-12
    # Umeyama recovers a known similarity.
    src = np.random.default_rng(2).normal(size=(6, 3))
    s, Rq, tq = similarity_transform(src, 2.5 * src @ R[1].T + [1.0, 2.0, 3.0])
    assert abs(s - 2.5) < 1e-12 and np.allclose(Rq, R[1]) and np.allclose(tq, [1, 2, 3])


def test_two_sided_board_is_detected_from_behind_at_the_front_corners():
    """The back of a two-sided ChArUco board: its own marker ids, its corners on the front's
    corners (the board frame stays the front's), detected as accurately as the front."""
    from stereo_bench.scene.dataset import render_settings
    from stereo_bench.detect.boards import detect
    from stereo_bench.render.analytic import AnalyticRenderer

    d = studio_dict()
    d["pattern"]["two_sided"] = True
    cfg = parse_rig(d)
    rig = Rig.from_config(cfg)
    board = rig.pattern
    assert board.back().marker_id_offset == 17 and not board.back().two_sided
    # The back's corner k lies on front corner back_to_front[k]: mirrored about the centre line.
    back_xy = board.back().object_points()[:, :2]
    front_xy = board.object_points()[board.back_to_front, :2]
    assert np.allclose(front_xy[:, 0], board.squares_x * board.square_mm - back_xy[:, 0])
    assert np.allclose(front_xy[:, 1], back_xy[:, 1])
    gt = rig.ground_truth()
    errors = {True: [], False: []}
    for c, cam in enumerate(rig.cameras[:2]):
        renderer = AnalyticRenderer(cam, board, render_settings(cfg, rig, cam))
        R, t = rig.cam_from_board(cam)
        for f in range(0, 60, 2):
            det = detect(renderer.render(R[f], t[f]), board)
            if det.found:
                ok = np.isfinite(det.points).all(axis=1)
                errors[bool(R[f][:, 2] @ t[f] < 0)].append(
                    np.linalg.norm(det.points[ok] - gt.points[c, f][ok], axis=1))
    back, front = np.concatenate(errors[True]), np.concatenate(errors[False])
    assert len(errors[True]) >= 3 and len(errors[False]) >= 3
    # Small far boards (20-40 px squares at 640x480) leave the front a few tenths of a pixel
    # at worst; the back must do as well, not be off by a mirrored corner (a square, ~30 px).
    assert np.median(back) < 0.2
    assert np.percentile(back, 90) < 2 * np.percentile(front, 90) + 0.1
    assert back.max() < 2 * front.max() + 0.5


def test_two_sided_board_lets_opposite_cameras_see_it_together():
    one = Rig.from_config(parse_rig(studio_dict()))
    d = studio_dict()
    d["pattern"]["two_sided"] = True
    two = Rig.from_config(parse_rig(d))
    # cam1 and cam3 face each other across the ring: a one-sided board shows both its front
    # only when it is off centre and nearly edge-on (geometry counts those grazing views;
    # no detector would find them).
    shared = []
    for rig in (one, two):
        seen = rig.ground_truth().visible.sum(axis=2) >= 8
        shared.append(int((seen[0] & seen[2]).sum()))
    assert shared[1] >= 5 * max(shared[0], 2), shared


def test_studio_run_end_to_end(tmp_path):
    """stereo-bench on a small studio: render, detect, calibrate, join the cameras, score;
    the report's studio sections and the studio picture are written."""
    import json

    import yaml

    from stereo_bench.cli import main

    d = studio_dict()
    d["studio"]["lenses"] = [{**LENS, "width": 480, "height": 360, "cx": 239.5, "cy": 179.5,
                              "fx": 420.0, "fy": 420.0}]
    # A studio of 2 m radius and 120 mm squares: ArUco needs about 3 px per marker cell.
    d["studio"].update(radius_mm=2000.0, count=6)
    d["pattern"].update(square_mm=120.0, marker_mm=90.0)
    d["trajectory"].update(frames=50, closeups=5)
    d["environment"] = {"kind": "clean", "supersampling": 1}
    d["calibration"] = {"loss": "soft_l1", "refine_intrinsics": True}
    rig = tmp_path / "studio.yaml"
    rig.write_text(yaml.safe_dump(d))
    out = tmp_path / "run"
    assert main([str(rig), "--out", str(out), "--methods", "zhang,opencv"]) == 0
    report = (out / "report.md").read_text()
    assert "## Per camera of the rig" in report and "RMSE_cal (mm) by distance" in report
    assert "Frames the rig calibration has of each pair of cameras together" in report
    assert "rig bundle adjustment: soft_l1 loss (scale 1 px), intrinsics refined" in report
    assert (out / "plots" / "studio.png").stat().st_size > 10_000
    entry = json.loads((out / "trials" / "seed_0" / "rig" / "zhang.json").read_text())
    assert entry["log"]["refined_intrinsics"]["cam1"][:4] == ["fx", "fy", "cx", "cy"]
    assert entry["log"]["loss"] == "soft_l1"
    aligned = [c["centre_mm"] for c in entry["aligned"]["cameras"].values()]
    fixed = [c["centre_mm"] for c in entry["camera_errors"].values()]
    # Six small cameras whose neighbours share 2-7 detected frames (detection errors ~0.1 px):
    # a weak studio, cm-level (measured: 8-36 mm, 3-7 mm aligned); exactness is tested above
    # on exact observations, this checks the stages join up.
    assert max(aligned) < 15 and max(fixed) < 80 and entry["rms_px"] < 0.2
    cov = np.array(entry["log"]["covisibility"])
    assert cov.shape == (6, 6) and (np.diag(cov) > 0).all()


@pytest.mark.parametrize("path", STUDIOS, ids=[p.stem for p in STUDIOS])
def test_the_vertical_is_found_even_on_a_half_ring(path):
    """Cameras that look down tilt their image up axes towards what they look at; on a half
    ring those tilts do not cancel (their mean is 7 degrees off), the horizontal x axes do."""
    from stereo_bench.scene.rig import world_up

    cams = load_rig(path).cameras_true()
    assert np.allclose(world_up(cams), [0, 0, 1], atol=1e-12)


@pytest.mark.parametrize("change, message", [
    ({"trajectory": {"kind": "spring", "frames": 10}, "calibration": {"intrinsics_views":
                                                                       "closeups"}},
     "intrinsics_views: 'closeups' names frames of a session"),
    ({"calibration": {"intrinsics_views": "closeups"}, "trajectory": {"kind": "session",
                                                                       "closeups": 0}},
     "needs close-up frames"),
])
def test_intrinsics_views_that_cannot_work_are_refused(change, message):
    d = {**studio_dict(), **change}
    with pytest.raises(ConfigError, match=message):
        parse_rig(d, "studio.yaml")


def test_two_cameras_facing_each_other_are_told_what_works():
    d = studio_dict(count=2)
    with pytest.raises(ValueError, match="lie \\(nearly\\) on one line, facing each other"):
        Rig.from_config(parse_rig(d))
    d = studio_dict(count=2, height_mm=[1500.0, 2500.0])
    assert len(Rig.from_config(parse_rig(d)).cameras) == 2


def test_the_pipeline_recovers_a_studio_exactly_from_exact_detections(tmp_path):
    """The run's own path (intrinsics from the close-ups only, planar poses for the walk, the
    graph, then the bundle adjustment), fed exact detections: every camera to 1e-6 mm."""
    from stereo_bench.scene.dataset import write_dataset
    from stereo_bench.detect.dataset import CameraDetections
    from stereo_bench.detect.boards import resolve_method
    from stereo_bench.evaluate.stage import detections_fingerprint
    from stereo_bench.run.pipeline import run_trial
    from stereo_bench.io.rundir import RunPaths
    from stereo_bench.core.files import write_json

    d = studio_dict()
    d["studio"]["lenses"] = [{**LENS, "width": 320, "height": 240, "cx": 159.5, "cy": 119.5,
                              "fx": 250.0, "fy": 250.0}]
    d["environment"] = {"kind": "clean", "supersampling": 1}
    d["calibration"] = {"intrinsics_views": "closeups"}
    cfg = parse_rig(d)
    trial = RunPaths(tmp_path).trial(cfg.seed)
    ds = write_dataset(cfg, trial.dataset.root)
    gt = ds.ground_truth
    for c, cam in enumerate(ds.cameras):  # the detector replaced by the truth
        points = np.where(gt.visible[c][..., None], gt.points[c], np.nan)
        found = gt.visible[c].sum(axis=1) >= 8
        CameraDetections(cam.name, ds.pattern.kind, resolve_method(ds.pattern, None), points,
                         found, ds.ids, {int(f): "not seen" for f in np.flatnonzero(~found)}
                         ).save(trial.detection(cam.name))
    write_json(trial.detections_done, {"fingerprint": detections_fingerprint(ds),
                                       "detect_s": 0.0})
    report = run_trial(cfg, tmp_path, ["zhang"])
    entry = report["rig"]["zhang"]
    assert "error" not in entry, entry
    errors = entry["camera_errors"]
    assert max(e["centre_mm"] for e in errors.values()) < 1e-6
    assert max(e["rotation_deg"] for e in errors.values()) < np.degrees(1e-8)
    # The intrinsics came from the close-ups alone, the rig from every frame two cameras share.
    assert report["intrinsics_views"] == "closeups"
    own = int((gt.visible[0][ds.closeup_of == 0].sum(axis=1) >= 8).sum())
    assert own > 0 and report["calibration"]["zhang"]["cam1"]["views"] == own
    assert entry["frames_used"] > own


def test_the_vertical_of_a_rolled_pair_stays_near_its_mean_up():
    """Two nearly parallel x axes span a plane any roll tilts; the mean up is kept then."""
    from stereo_bench.scene.rig import world_up

    cfg = load_rig(Path(__file__).resolve().parents[2] / "configs" / "paper" / "wide_pair.yaml")
    roll = np.radians(5.0)
    d = cfg.model_dump(mode="json")
    d["cameras"][1]["up"] = [np.sin(roll), -np.cos(roll), 0.0]
    up = world_up(parse_rig(d).cameras_true())
    assert np.degrees(np.arccos(up @ [0.0, -1.0, 0.0])) < 5.0


def test_calibrate_takes_the_intrinsics_views_of_a_session_dataset(tmp_path, capsys):
    import json

    from stereo_bench.cli import main
    from stereo_bench.scene.dataset import write_dataset

    d = studio_dict()
    d["environment"] = {"kind": "clean", "supersampling": 1}
    d["trajectory"].update(frames=6, closeups=4)
    write_dataset(parse_rig(d), tmp_path / "ds")
    out = tmp_path / "cal"
    rc = main(["calibrate", str(tmp_path / "ds"), "--out", str(out), "--methods", "zhang",
               "--intrinsics-views", "closeups"])
    assert rc in (0, 1)  # a tiny dataset may calibrate nothing; the setting is what counts
    metrics = json.loads((out / "trials" / "seed_0" / "metrics.json").read_text())
    assert metrics["intrinsics_views"] == "closeups"
    assert "intrinsics from closeups views" in (out / "report.md").read_text()
    # A spring dataset has no close-ups: refused, naming the option.
    pair = load_rig(Path(__file__).resolve().parents[2] / "configs" / "quickstart.yaml").model_dump(
        mode="json")
    pair["trajectory"]["frames"] = 2
    write_dataset(parse_rig(pair), tmp_path / "spring")
    capsys.readouterr()
    assert main(["calibrate", str(tmp_path / "spring"), "--intrinsics-views", "closeups"]) == 2
    assert "--intrinsics-views closeups" in capsys.readouterr().err
