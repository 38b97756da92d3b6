"""A symmetric board numbered from another corner in some views (orientation.agree), a camera
without views left out of a capture's rig, and a rig its own figures contradict refused."""

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from stereo_bench.core.poses import matrix_to_rodrigues, rodrigues_to_matrix
from stereo_bench.run.capture import rig_doubts
from stereo_bench.cli import main
from stereo_bench.multiview.orientation import agree, symmetries
from stereo_bench.io.rundir import RunPaths
from quickstart import quickstart

ROOT = Path(__file__).resolve().parents[2]


def grid(cols, rows, pitch=25.0):
    return np.array([[x * pitch, y * pitch, 0.0] for y in range(rows) for x in range(cols)])


def test_the_turns_of_a_layout():
    assert [d for d, _ in symmetries(grid(7, 5))] == [180.0]
    assert [d for d, _ in symmetries(grid(4, 4))] == [90.0, 180.0, 270.0]
    (_, perm), = symmetries(grid(7, 5))
    assert list(perm) == list(range(34, -1, -1))  # a 180-degree turn reverses a grid's order
    # An asymmetric circle grid's layout (rows offset by half a pitch) has its own 180 turn.
    asym = np.array([[(2 * x + y % 2) * 10.0, y * 10.0, 0] for y in range(5) for x in range(4)])
    assert [d for d, _ in symmetries(asym)] == []
    assert symmetries(np.array([[0.0, 0, 0], [3, 0, 0], [0, 1, 0]])) == []


def _views(frames=8, seed=1):
    """Two cameras 120 mm apart (the right one turned 10 degrees) and a board moving in front:
    each camera's cam_from_board and the image points of a pinhole camera (f 600 px)."""
    rng = np.random.default_rng(seed)
    obj = grid(7, 5)
    R01 = rodrigues_to_matrix(np.radians([0.0, 10.0, 0.0]))
    t01 = np.array([-120.0, 0.0, 5.0])
    rv, tv, pts = np.zeros((2, frames, 3)), np.zeros((2, frames, 3)), []
    for f in range(frames):
        R0 = rodrigues_to_matrix(rng.normal(0, 0.35, 3) + [np.pi, 0, 0])
        t0 = np.array([rng.uniform(-60, 0), rng.uniform(-60, 0), rng.uniform(500, 800)])
        for c, (R, t) in enumerate([(R0, t0), (R01 @ R0, R01 @ t0 + t01)]):
            rv[c, f], tv[c, f] = matrix_to_rodrigues(R), t
    for c in range(2):
        X = np.einsum("fij,nj->fni", [rodrigues_to_matrix(r) for r in rv[c]], obj) + tv[c][:, None]
        pts.append(600 * X[..., :2] / X[..., 2:] + [320, 240])
    return obj, np.stack(pts), rv, tv


def _turned(obj, pts, rv, tv, cam, frame):
    """The view numbered from the opposite corner, as OpenCV's finder returns a symmetric board
    when it starts there: the points reversed, and the pose planar PnP gives for them."""
    pts, rv, tv = pts.copy(), rv.copy(), tv.copy()
    pts[cam, frame] = pts[cam, frame][::-1]
    centre = obj.mean(axis=0)
    Rz = np.diag([-1.0, -1.0, 1.0])  # the turn p -> Rz (p - c) + c
    R = rodrigues_to_matrix(rv[cam, frame])
    rv[cam, frame] = matrix_to_rodrigues(R @ Rz)
    tv[cam, frame] = tv[cam, frame] + R @ (centre - Rz @ centre)
    return pts, rv, tv


def test_a_view_numbered_from_the_other_corner_is_renumbered_exactly():
    obj, pts, rv, tv = _views()
    found = np.ones((2, 8), bool)
    bad_pts, bad_rv, bad_tv = _turned(obj, pts, rv, tv, cam=1, frame=3)
    # The turned view is the same set of image points of the same board: one camera alone
    # cannot tell, so the view's reprojection is exact.
    R = rodrigues_to_matrix(bad_rv[1, 3])
    X = obj @ R.T + bad_tv[1, 3]
    assert np.abs(600 * X[:, :2] / X[:, 2:] + [320, 240] - bad_pts[1, 3]).max() < 1e-9
    fixed_pts, fixed_rv, fixed_tv, fixed_found, changes = agree(
        obj, bad_pts, bad_rv, bad_tv, found, ["left", "right"])
    assert changes == [{"camera": "right", "frame": 3, "turn_deg": 180.0}]
    assert np.abs(fixed_pts - pts).max() < 1e-9
    assert np.abs(fixed_tv - tv).max() < 1e-9
    assert np.abs(fixed_rv - rv).max() < 1e-9 and fixed_found.all()
    # ChArUco's ids say which point is which: nothing is renumbered.
    assert agree(obj, bad_pts, bad_rv, bad_tv, found, ["left", "right"], identified=True)[4] == []


def test_a_view_that_agrees_under_no_numbering_is_left_out():
    obj, pts, rv, tv = _views()
    rv = rv.copy()
    rv[1, 5] = matrix_to_rodrigues(rodrigues_to_matrix(rv[1, 5])
                                   @ rodrigues_to_matrix(np.radians([50.0, 0, 0])))
    _, _, out_rv, _, found, changes = (None,) + agree(obj, pts, rv, tv, np.ones((2, 8), bool),
                                                      ["left", "right"])
    assert len(changes) == 1 and changes[0]["camera"] == "right" and changes[0]["frame"] == 5
    assert changes[0]["disagreement_deg"] > 40
    assert not found[1, 5] and np.isnan(out_rv[1, 5]).all() and found.sum() == 15


def upside_down_rig(tmp_path, frames=10) -> Path:
    """The quickstart pair with a board whose two ends look alike (8 x 6 squares) and the right
    camera mounted upside down, as studio cameras often are: OpenCV numbers the board from the
    opposite corner in every one of its views."""
    d = yaml.safe_load((ROOT / "configs" / "quickstart.yaml").read_text())
    d["name"] = "upside_down"
    d["trajectory"]["frames"] = frames
    d["pattern"] = {"kind": "checkerboard", "squares_x": 8, "squares_y": 6, "square_mm": 25.0}
    d["cameras"][1]["up"] = [0.0, 1.0, 0.0]
    rig = tmp_path / "rig.yaml"
    rig.write_text(yaml.safe_dump(d, sort_keys=False))
    return rig


def test_an_upside_down_camera_and_a_symmetric_board_give_the_true_rig(tmp_path):
    """Before: rig RMS 46 px, RMSE_cal 229 mm (every right view turned against the left's)."""
    out = tmp_path / "run"
    assert main([str(upside_down_rig(tmp_path)), "--out", str(out), "--methods", "opencv"]) == 0
    rig = json.loads(RunPaths(out).results.read_text())["trials"][0]["rig"]["opencv"]
    assert [c["frame"] for c in rig["log"]["orientation"]] == list(range(10))
    assert rig["rms_px"] < 0.05 and rig["rmse_cal_mm"] < 0.5
    assert rig["camera_errors"]["right"]["rotation_deg"] < 0.05


def test_capture_renumbers_the_turned_views_and_leaves_out_a_blind_camera(tmp_path, capsys):
    """calibrate-images on three cameras: the upside-down pair, and a third camera that sees
    nothing (black images): the rig is the pair's, named as such, and the exit status is 1."""
    out = tmp_path / "run"
    assert main(["render", str(upside_down_rig(tmp_path, frames=8)), "--out", str(out)]) == 0
    folders = {}
    for cam in ("left", "right", "blind"):
        folders[cam] = tmp_path / "user" / cam
        shutil.copytree(out / "images" / ("left" if cam == "blind" else cam), folders[cam])
    for png in folders["blind"].glob("*.png"):
        cv2.imwrite(str(png), np.zeros((480, 640), np.uint8))
    capsys.readouterr()
    code = main(["calibrate-images", *(f"{c}={p}" for c, p in folders.items()), "--board",
                 "checkerboard", "--inner-corners", "7x5", "--square-mm", "25", "--methods",
                 "opencv", "--out", str(tmp_path / "cap")])
    err = capsys.readouterr().err.replace("\n", " ")
    assert code == 1 and "camera(s) 'blind' not calibrated by any method" in err
    res = json.loads((tmp_path / "cap" / "results.json").read_text())
    rig = res["rig"]["opencv"]
    assert "error" not in rig and set(rig["baseline_mm"]) == {"left", "right"}
    assert "blind" in rig["left_out"]
    assert rig["rms_px"] < 0.1 and abs(rig["baseline_mm"]["right"] - 120) < 0.5
    assert "camera blind: left out of the rig" in err
    assert "camera 'right': the board was found numbered from another corner (turned 180 " \
           "degrees" in err
    report = (tmp_path / "cap" / "report.md").read_text()
    assert "| opencv | | blind | left out: no estimate |" in report


def test_a_rig_its_own_figures_contradict_is_not_reported():
    entry = {"board_geometry": {"scale_error_pct": 101.0}, "baseline_mm": {"a": 0.0, "b": 100.0},
             "opencv_multiview": {"cameras": {"b": {"difference_rotation_deg": 7.5,
                                                    "difference_centre_mm": 0.5}}}}
    doubts = rig_doubts(entry)
    assert len(doubts) == 2
    assert "+101.0 % off its known size" in doubts[0] and "7.50 degrees" in doubts[1]
    entry["board_geometry"]["scale_error_pct"] = -0.02
    entry["opencv_multiview"]["cameras"]["b"]["difference_rotation_deg"] = 0.01
    assert rig_doubts(entry) == []


@pytest.mark.parametrize("pattern", [{"kind": "checkerboard"},
                                     {"kind": "charuco", "squares_x": 7, "squares_y": 5,
                                      "square_mm": 30.0, "marker_mm": 22.0,
                                      "dictionary": "DICT_4X4_50"}])
def test_an_inverted_board_is_found_said_or_not(tmp_path, pattern):
    """A board printed white on black: rendered so, found in every frame the plain board is
    found in, as precisely, whether the rig file says so or not (before: 0 frames)."""
    d = quickstart(6)
    found = {}
    for label, extra in (("plain", {}), ("inverted", {"inverted": True})):
        d["pattern"] = {**pattern, **extra}
        rig = tmp_path / f"{label}.yaml"
        rig.write_text(yaml.safe_dump(d, sort_keys=False))
        assert main([str(rig), "--out", str(tmp_path / label), "--methods", "opencv"]) == 0
        found[label] = json.loads(RunPaths(tmp_path / label).results.read_text())[
            "trials"][0]["detection"]
    texture = cv2.imread(str(RunPaths(tmp_path / "inverted").trial(7).dataset.texture), 0)
    assert texture[0, 0] == 0  # the quiet zone is black
    for cam in ("left", "right"):
        plain, inverted = found["plain"][cam], found["inverted"][cam]
        assert inverted["found"] == plain["found"] > 0
        assert inverted["rms_px"] < 2 * plain["rms_px"] + 0.01
    # Not said: the capture of the inverted images, described as a plain board, finds them too.
    images = RunPaths(tmp_path / "inverted").trial(7).dataset.root / "images"
    argv = ["calibrate-images", f"left={images / 'left'}", f"right={images / 'right'}",
            "--methods", "opencv", "--out", str(tmp_path / "cap")]
    if pattern["kind"] == "checkerboard":
        argv += ["--board", "checkerboard", "--inner-corners", "8x11", "--square-mm", "15"]
    else:
        argv += ["--board", "charuco", "--squares", "7x5", "--square-mm", "30", "--marker-mm",
                 "22", "--dictionary", "DICT_4X4_50"]
    assert main(argv) == 0
    res = json.loads((tmp_path / "cap" / "results.json").read_text())
    assert res["detection"]["left"]["found"] == found["plain"]["left"]["found"]
