"""calibrate-images refuses evidence that cannot determine a camera (one view, one orientation
repeated, boards facing the camera, a wrong --inner-corners found in one image), says why in
words and with the exit code of the README; a camera's image size is the most common one; a
fold is reported only when it covers a reportable share of the image, each fact once.

Images are rendered by the project's analytic renderer (clean, a 640 x 480 camera with barrel
distortion) at poses chosen per case, written as a user's folder of PNGs."""

import json

import cv2
import numpy as np
import pytest

from stereo_bench.core.camera import Camera
from stereo_bench.core.poses import rodrigues_to_matrix
from stereo_bench.run.capture import calibrate_capture, flags
from stereo_bench.cli import main
from stereo_bench.scene.image_folders import ImageFolders
from stereo_bench.core.patterns import Checkerboard
from stereo_bench.render import AnalyticRenderer, RenderSettings

CAM = Camera("cam", 640, 480, 550, 550, 320, 240, 0, np.array([-0.2, 0.05, 0, 0, 0, 0, 0, 0]))
BOARD = Checkerboard(squares_x=10, squares_y=7, square_mm=25.0)  # 9 x 6 inner corners
BOARD_ARGS = ["--board", "checkerboard", "--inner-corners", "9x6", "--square-mm", "25"]
CENTRE = 0.5 * (BOARD.object_points().min(0) + BOARD.object_points().max(0))
Z0 = BOARD.size_mm[1] * CAM.fy / (0.7 * CAM.height)  # the board fills 70 % of the height


def pose(axis_deg, tilt_deg, roll_deg=0.0, shift=(0.0, 0.0), z=1.0):
    """cam_from_board: the board tilted by tilt_deg about an in-image axis at axis_deg, rolled
    in its plane, its centre at (shift * Z0, z * Z0)."""
    a = np.radians(axis_deg)
    R = (rodrigues_to_matrix(np.radians(tilt_deg) * np.array([np.cos(a), np.sin(a), 0.0]))
         @ rodrigues_to_matrix([0.0, 0.0, np.radians(roll_deg)]))
    return R, np.array([shift[0] * Z0, shift[1] * Z0, z * Z0]) - R @ CENTRE


# Six well-spread views: tilted 30 degrees in six directions.
GOOD = [pose(a, 30, r, s, z) for a, r, s, z in [
    (0, 0, (-0.1, -0.1), 1.0), (60, 10, (0.1, -0.1), 1.1), (120, -10, (0.0, 0.0), 1.3),
    (180, 20, (-0.1, 0.1), 1.2), (240, -20, (0.1, 0.1), 1.25), (300, 0, (0.0, 0.05), 1.4)]]
SAME = [pose(30, 30)] * 6
# Boards facing the camera: rolled in their plane and moved, never tilted.
FRONTO = [pose(0, 0, r, s, z) for r, s, z in [
    (0, (-0.1, -0.1), 1.0), (20, (0.1, -0.1), 1.1), (-20, (0.0, 0.0), 1.3),
    (40, (-0.1, 0.1), 1.2), (-40, (0.1, 0.1), 1.25), (90, (0.0, 0.05), 1.4)]]


@pytest.fixture(scope="module")
def renderer():
    return AnalyticRenderer(CAM, BOARD, RenderSettings())


@pytest.fixture(scope="module")
def images(renderer):
    """name -> rendered images of that pose set (rendered once per module)."""
    return {name: [renderer.render(R, t) for R, t in poses]
            for name, poses in (("good", GOOD), ("same", SAME), ("fronto", FRONTO))}


def folder(path, imgs, prefix="img"):
    path.mkdir(parents=True)
    for i, img in enumerate(imgs):
        cv2.imwrite(str(path / f"{prefix}{i + 1:02d}.png"), img)
    return path


def command(tmp_path, capsys, *cameras):
    out = tmp_path / "out"
    code = main(["calibrate-images", *cameras, *BOARD_ARGS, "--folds", "2", "--out", str(out)])
    err = capsys.readouterr().err
    assert "Traceback" not in err
    results = json.loads((out / "results.json").read_text())
    return code, err, results, out


def test_well_spread_views_calibrate(images, tmp_path, capsys):
    """The positive control: six tilted views in six directions pass the check (their focal
    length is pinned to a few percent per 0.1 px, the limit is 10 %) and the methods recover
    f."""
    code, err, res, _ = command(tmp_path, capsys, f"cam={folder(tmp_path / 'g', images['good'])}")
    assert code == 0 and res["refused"] == {}
    g = res["view_geometry"]["cam"]
    assert g["views"] == 6 and max(g["focal_ambiguity"].values()) < 0.05
    assert g["normal_spread_deg"] > 50
    for m in ("zhang", "bouguet", "opencv"):
        cam = json.loads((tmp_path / "out" / "calibrations" / m / "cam.json").read_text())
        assert cam["fx"] == pytest.approx(550, rel=0.01), m


def test_one_view_is_refused_in_words(images, tmp_path, capsys):
    """One image: before, exit 0 with fx 571.5 (opencv, bouguet) and 562.4 (tsai) for the
    truth's 550 (918 +- 81 by opencv on OpenCV's real left01.jpg). Now no method runs on it, no
    estimate is written, exit 1, and stderr says why and how many views are needed."""
    code, err, res, out = command(tmp_path, capsys,
                                  f"cam={folder(tmp_path / 'one', images['good'][:1])}")
    assert code == 1
    assert "camera 'cam' not calibrated: 1 usable view" in err
    assert "at least 2 views at different board orientations" in err
    assert "3 for Zhang's closed form with skew" in err
    assert "no camera could be calibrated" in err
    assert set(res["refused"]) == {"cam"}
    for m, cams in res["calibration"].items():
        assert cams["cam"]["error"].startswith("camera 'cam' not calibrated"), m
    assert not (out / "calibrations").exists() or not any((out / "calibrations").rglob("*.json"))
    # The fact once, not once per method (stderr also carries the report, whose notes say it).
    assert err.count("warning: camera 'cam' not calibrated") == 1


def test_one_orientation_is_refused(images, tmp_path, capsys):
    """Six boards facing the camera (rolled and moved only): before, exit 0 with fx 773.5 /
    914.3 / 3942.2 (opencv / bouguet / tsai) for the truth's 550. Now the focal length's
    ambiguity is unbounded (the pinhole Jacobian is singular) and the camera is refused."""
    code, err, res, _ = command(tmp_path, capsys, f"cam={folder(tmp_path / 'f', images['fronto'])}")
    assert code == 1 and set(res["refused"]) == {"cam"}
    g = res["view_geometry"]["cam"]
    assert g["views"] == 6
    assert g["focal_ambiguity"]["fx"] is None  # infinite: nothing fixes it
    assert g["normal_spread_deg"] < 0.5 and g["tilt_deg"][1] < 0.5
    assert "its 6 views do not determine the focal length" in err
    assert "an unbounded amount" in err and "tilted 0 deg from the image plane" in err


def test_one_pose_repeated_is_one_view(images, tmp_path, capsys):
    """Six images of one pose: before, exit 0 with fx 553.0 / 556.4 / 550.5 (opencv / bouguet /
    tsai) for the truth's 550, held only by the distortion terms of noise-free renders. Now the
    five repeats are left out of the intrinsics (view_selection), and one view is refused."""
    code, err, res, _ = command(tmp_path, capsys, f"cam={folder(tmp_path / 's', images['same'])}")
    assert code == 1 and set(res["refused"]) == {"cam"}
    assert len(res["detection"]["cam"]["views_left_out"]) == 5
    assert "5 as repeating a board pose already taken" in err
    assert "camera 'cam' not calibrated: 1 usable view" in err


def test_stereo_with_one_refused_camera(images, tmp_path, capsys):
    """A rig whose right camera has a single view: the left one is calibrated and written, the
    right one is named on stderr once and in the report, the rig says which camera it lacks,
    and the exit status (1) says that a camera asked for is missing."""
    left = folder(tmp_path / "left", images["good"])
    right = folder(tmp_path / "right", images["good"][2:3], prefix="img0")  # frame 3 only
    code, err, res, out = command(tmp_path, capsys, f"left={left}", f"right={right}")
    assert code == 1
    assert "camera(s) 'right' not calibrated by any method" in err
    assert set(res["refused"]) == {"right"}
    assert err.count("warning: camera 'right' not calibrated: 1 usable view;") == 1
    assert "error" not in res["calibration"]["opencv"]["left"]
    for m, rig in res["rig"].items():
        assert "fewer than two cameras calibrated" in rig["error"], m
        assert "'right' not" in rig["error"] and "right" in rig["left_out"], m
    report = (out / "report.md").read_text()
    assert "camera 'right' not calibrated" in report


def test_wrong_inner_corners_on_real_images(opencv_pair, tmp_path, capsys):
    """OpenCV's sample pair (9 x 6 inner corners) described as 5 x 4: the sub-grid is found in
    one right image, which used to calibrate (exit 0, OpenCV's fx from one view). Now the right
    camera is refused, with a word on the board's description; no camera calibrated: exit 1."""
    out = tmp_path / "out"
    code = main(["calibrate-images", f"left={opencv_pair}/left*.jpg",
                 f"right={opencv_pair}/right*.jpg", "--board", "checkerboard", "--inner-corners",
                 "5x4", "--square-mm", "25", "--methods", "opencv,tsai", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 1 and "Traceback" not in err
    # The sub-grid is also found in one more image of each camera in the other polarity (the
    # detector's try for inverted boards): still too few views, and still said why.
    assert "camera 'right' not calibrated: its 2 views do not determine the focal length" in err
    assert "found in only 2 of 13 images: is the board described right? --inner-corners 5x4" \
        in err
    assert "camera 'left' not calibrated: 1 usable view" in err


def test_image_size_is_the_most_common_one(images, tmp_path, capsys):
    """A first image of another size (img00.png, 320 x 240) used to set the camera's size and
    drop the six others as "of another size": a 320 x 240 camera calibrated from that one view,
    exit 0. Now the size is the common 640 x 480, the odd image is named with its size, and the
    camera calibrates from its six views."""
    cams = folder(tmp_path / "mixed", images["good"])
    cv2.imwrite(str(cams / "img00.png"), cv2.resize(images["good"][0], (320, 240)))
    source = ImageFolders.open({"cam": str(cams)}, BOARD)
    assert source.cameras[0].size == (640, 480)
    assert source.warnings == ["camera 'cam': its images are 640x480 px (6 of 7); left out, 1 of "
                               "another size: img00.png (320x240 px)"]
    res = calibrate_capture(source, ["opencv"], tmp_path / "out", folds=2)
    assert res["calibration"]["opencv"]["cam"]["views"] == 6
    assert "320x240 px, expected 640x480 px" in res["detection"]["cam"]["errors"]["frame 0"]
    assert "img00.png (320x240 px)" in res["warnings"][0]


def test_unreadable_images_only_are_named(tmp_path):
    cams = tmp_path / "bad"
    cams.mkdir()
    (cams / "a1.png").write_bytes(b"not a png")
    with pytest.raises(ValueError, match=r"camera 'bad': none of its 1 images is one OpenCV "
                                         r"can read \(e.g. .*a1.png\)"):
        ImageFolders.open({"bad": str(cams)}, BOARD)


def _results(folds: dict[str, float]) -> dict:
    """A capture's results with one camera whose estimates fold over the given shares."""
    ok = {"diagnostics": {"points": {"flagged": [], "threshold_px": 1.0}}, "heldout": {}}
    return {"frame_names": [], "calibration": {
        m: {"cam": {**ok, "validity": {"valid_fraction": 1 - f, "usable": f == 0}}}
        for m, f in folds.items()}}


def test_fold_warning_only_when_reportable_and_once():
    """A fold over one grid point (0.03 % of the image) used to print 'folds over 0% of the
    image'; now no warning says nothing, the figure has one decimal, and methods whose
    estimates fold alike are named in one line."""
    assert flags(_results({"opencv-rational": 1 / 3072})) == []
    assert flags(_results({"opencv-rational": 0.0134, "zhang-rational": 0.0134,
                           "bouguet-rational": 0.02})) == [
        "opencv-rational, zhang-rational, camera cam: the lens model has no unique ray over "
        "1.3 % of the image (it folds there); projections and triangulations there are "
        "meaningless",
        "bouguet-rational, camera cam: the lens model has no unique ray over 2.0 % of the image "
        "(it folds there); projections and triangulations there are meaningless"]


# OpenCV's sample pair, --square-mm 25, before this change (the same numbers after it): RPE px
# and fx px per method and camera.
REAL_BEFORE = {
    ("zhang", "left"): (0.1780249465058392, 533.8943753318082),
    ("zhang", "right"): (0.1757729355229448, 536.3731447870681),
    ("tsai", "left"): (0.3299833861163937, 537.5491611533265),
    ("tsai", "right"): (0.25593785160060356, 540.3244926969502),
    ("bouguet", "left"): (0.17282511583671067, 533.3308994307894),
    ("bouguet", "right"): (0.17294026943524188, 537.1425691495808),
    ("opencv", "left"): (0.17276624524577996, 533.2104498617109),
    ("opencv", "right"): (0.17200398571217324, 537.4077175494144),
}


def test_real_pair_unchanged(opencv_pair, tmp_path):
    """OpenCV's 13 real pairs pass the check by a wide margin (1.3 % of f per 0.1 px) and every
    method's estimate is the one it gave before the check existed."""
    source = ImageFolders.open({"left": f"{opencv_pair}/left*.jpg",
                                "right": f"{opencv_pair}/right*.jpg"},
                               Checkerboard(squares_x=10, squares_y=7, square_mm=25.0))
    assert source.warnings == []
    res = calibrate_capture(source, ["zhang", "tsai", "bouguet", "opencv"], tmp_path, folds=2)
    assert res["refused"] == {}
    for cam in ("left", "right"):
        g = res["view_geometry"][cam]
        assert g["views"] == 13 and max(g["focal_ambiguity"].values()) < 0.02
    for (m, cam), (rpe, fx) in REAL_BEFORE.items():
        e = res["calibration"][m][cam]
        assert e["views"] == 13
        assert e["rpe_rms_px"] == pytest.approx(rpe, rel=1e-9), (m, cam)
        got = json.loads((tmp_path / "calibrations" / m / f"{cam}.json").read_text())["fx"]
        assert got == pytest.approx(fx, rel=1e-9), (m, cam)
    assert not any("0%" in w or "not calibrated" in w for w in res["warnings"])


def test_guidance_names_the_empty_parts_of_the_image_and_a_baseline_apart():
    from stereo_bench.run.capture import baseline_outliers, empty_regions, recapture

    counts = np.zeros((8, 10), int)
    counts[3:6, 4:7] = 5  # the board only ever in the middle of the image
    assert empty_regions(counts) == ["top-left", "top", "top-right", "left", "right",
                                     "bottom-left", "bottom", "bottom-right"]
    counts[:] = 1
    assert empty_regions(counts) == []
    counts[5:, 7:] = 0
    assert empty_regions(counts) == ["bottom-right"]
    results = {"cameras": [{"name": "a"}], "calibration": {"opencv": {"a": {"diagnostics": {
        "coverage": {"counts": counts.tolist(), "cell_fraction": 0.9}}}}}}
    (line,) = recapture(results)
    assert line.startswith("camera a: no board feature reached the bottom-right of the image")
    rig = {m: {"baseline_mm": {"a": 0.0, "b": b}}
           for m, b in (("zhang", 100.0), ("opencv", 100.2), ("tsai", 106.0))}
    (flag,) = baseline_outliers(rig)
    assert flag.startswith("tsai's rig puts camera b 106.0 mm from the reference, +5.8 %")
