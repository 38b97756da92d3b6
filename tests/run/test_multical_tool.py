"""multical in compare-tools (stereo_bench/tools/multical.py) and its calibration.json
(stereo_bench/io/multical.py): the file round-trips and reads multical's own layout; the tool,
run as ``multical calibrate`` on a rendered ChArUco pair in its own environment, lands where its
detector lets it; what it cannot take is refused by name."""

import dataclasses
import json
import os
import subprocess

import numpy as np
import pytest

from quickstart import quickstart
from stereo_bench import io as formats
from stereo_bench.config.schema import parse_rig
from stereo_bench.core.camera import Camera
from stereo_bench.core.poses import look_at_rotation, matrix_to_rodrigues
from stereo_bench.io import multical as multical_file
from stereo_bench.run.exchange import score_cameras
from stereo_bench.scene.dataset import write_dataset
from stereo_bench.tools import Session, ToolError, module

TARGET = np.array([0.0, 0.0, 2000.0])


def _rig(world: bool = False) -> list[Camera]:
    """Three cameras looking at TARGET: camera 0 at the identity (multical's master form), or
    every camera posed in a world frame (``world``)."""
    cams = []
    for i, (position, dist) in enumerate([
            ([0.0, 0.0, 0.0], [-0.21, 0.13, 1e-3, -2e-3, -0.04, 0, 0, 0]),
            ([450.0, 30.0, 80.0], [0.05, -0.02, 3e-4, 1e-4, 0.01, 0.02, -0.003, 0.001]),
            ([-380.0, -60.0, 150.0], [-0.1, 0.02, 0, 0, 0, 0, 0, 0])]):
        position = np.array(position) + ([120.0, -40.0, -300.0] if world else 0.0)
        R = look_at_rotation(position, TARGET, np.array([0.0, -1.0, 0.0]))
        if i == 0 and not world:
            R = np.eye(3)
        cams.append(Camera(f"cam{i}", 1920, 1080, 1400.0 + 10 * i, 1398.0 + 10 * i,
                           960.3 - i, 541.7 + i, 0.0, dist, matrix_to_rodrigues(R),
                           -R @ position))
    return cams


@pytest.mark.parametrize("world", [False, True])
def test_calibration_json_round_trips_exactly(tmp_path, world):
    cams = _rig(world)
    files = formats.export(cams, tmp_path, "multical")
    assert files == [tmp_path / "calibration.json"]
    doc = json.loads(files[0].read_text())
    # multical calibrate's layout: the master and <camera>_to_<master>, in metres; a rig with
    # a world frame keeps it with every camera's absolute pose.
    keys = ["cam0", "cam1", "cam2"] if world else ["cam0", "cam1_to_cam0", "cam2_to_cam0"]
    assert list(doc["camera_poses"]) == keys
    assert [c["model"] for c in doc["cameras"].values()] == ["standard", "rational", "standard"]
    back = formats.load(tmp_path)  # the format guessed from the folder
    assert formats.guess_format(files[0]) == "multical"
    X = TARGET + np.random.default_rng(3).uniform(-400, 400, (200, 3))
    for a, b in zip(cams, back):
        assert b.name == a.name and b.size == a.size
        assert [b.fx, b.fy, b.cx, b.cy, b.skew] == [a.fx, a.fy, a.cx, a.cy, a.skew]
        assert np.array_equal(b.dist, a.dist)
        # Rotations pass through a 3x3 matrix, translations through metres: rounding only.
        np.testing.assert_allclose(b.tvec, a.tvec, rtol=0, atol=1e-12)
        np.testing.assert_allclose(b.rvec, a.rvec, rtol=0, atol=1e-14)
        assert np.abs(b.project(X) - a.project(X)).max() < 1e-9


MULTICAL_PROJECT = """
import sys, numpy as np
from multical.io.import_calib import load_calibration
calib = load_calibration(sys.argv[1])
X = np.load(sys.argv[2])
uv = []
for name in sys.argv[4:]:
    P = calib.camera_poses[name]
    uv.append(calib.cameras[name].project(X @ P[:3, :3].T + P[:3, 3]))
np.save(sys.argv[3], np.stack(uv))
"""


def test_multicals_own_reader_projects_the_file_as_written(tmp_path):
    """multical's load_calibration (in its environment) and its Camera.project
    (cv2.projectPoints), on this module's files (camera 0 as the master, and a rig with a world
    frame), in metres: the suite's projections to 1e-9 px."""
    tool = module("multical")
    if (why := tool.missing()) is not None:
        pytest.skip(why)
    X = TARGET + np.random.default_rng(4).uniform(-400, 400, (200, 3))
    np.save(tmp_path / "X.npy", X / 1000.0)
    env = {**os.environ, "MPLCONFIGDIR": str(tmp_path / "mpl")}  # its matplotlib's cache
    for world in (False, True):
        cams = _rig(world)
        (path,) = multical_file.write(cams, tmp_path / str(world))
        subprocess.run([str(tool.python()), "-c", MULTICAL_PROJECT, str(path),
                        str(tmp_path / "X.npy"), str(tmp_path / "uv.npy"),
                        *[c.name for c in cams]], check=True, capture_output=True, env=env)
        for uv, cam in zip(np.load(tmp_path / "uv.npy"), cams):
            assert np.abs(uv - cam.project(X)).max() < 1e-9


def test_reads_multicals_own_layout_and_refuses_what_it_cannot_hold(tmp_path):
    # As multical writes it: dist as cv2's 1 x 5 row, image_size as floats, the master's pose
    # with denormal noise, image_sets beside (FORMAT.md's example, completed).
    doc = {"cameras": {
        "cam1": {"model": "standard", "image_size": [2000.0, 1500.0],
                 "K": [[2251.52, 0.0, 985.68], [0.0, 2252.8, 763.0], [0.0, 0.0, 1.0]],
                 "dist": [[-0.12, 0.32, -0.001, -0.002, -0.2]]},
        "cam2": {"model": "standard", "image_size": [2000, 1500],
                 "K": [[2257.19, 0.0, 983.84], [0.0, 2258.64, 754.08], [0.0, 0.0, 1.0]],
                 "dist": [[-0.12, 0.39, -0.001, -0.002, -0.28]]}},
        "camera_poses": {
            "cam1": {"R": [[1.0, 1e-40, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
                     "T": [1e-56, 0.0, 0.0]},
            "cam2_to_cam1": {"R": [[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]],
                             "T": [-0.05, 0.001, 0.3]}},
        "image_sets": {"rgb": [{"cam1": "cam1/0.png", "cam2": "cam2/0.png"}]}}
    path = tmp_path / "calibration.json"
    path.write_text(json.dumps(doc))
    a, b = multical_file.read(path)
    assert (a.name, a.size, a.cx, b.fy) == ("cam1", (2000, 1500), 985.68, 2258.64)
    assert np.array_equal(a.dist, [-0.12, 0.32, -0.001, -0.002, -0.2, 0, 0, 0])
    np.testing.assert_allclose(b.tvec, [-50.0, 1.0, 300.0], atol=1e-12)  # metres read as mm
    np.testing.assert_allclose(b.R, doc["camera_poses"]["cam2_to_cam1"]["R"], atol=1e-15)

    def refused(change, match):
        broken = json.loads(json.dumps(doc))
        change(broken)
        path.write_text(json.dumps(broken))
        with pytest.raises(ValueError, match=match):
            multical_file.read(path)

    refused(lambda d: d["cameras"]["cam2"]["K"][0].__setitem__(1, 0.5),
            r"cameras\['cam2'\]: skew K\[0\]\[1\] = 0.5; multical projects")
    refused(lambda d: d["cameras"]["cam2"].__setitem__("dist", [[0.1, 0.01, 0.0, 0.0]]),
            r"cameras\['cam2'\]: dist has 4 coefficients, .*ambiguous")
    refused(lambda d: d["cameras"]["cam2"].__setitem__("dist", [[0.1] + [0.0] * 8 + [0.002]
                                                                + [0.0] * 2]),
            r"cameras\['cam2'\]: s2 = 0.002 is not 0")
    refused(lambda d: d["camera_poses"]["cam1"]["T"].__setitem__(0, 0.2),
            r"camera_poses\['cam2_to_cam1'\]: relative to camera 'cam1', whose own pose is not")
    refused(lambda d: d["camera_poses"].pop("cam2_to_cam1"), r"no pose for camera\(s\) cam2")
    refused(lambda d: d["camera_poses"].__setitem__("cam3_to_cam1", {}),
            r"camera_poses\['cam3_to_cam1'\]: expected a camera's name")
    cams = _rig()
    with pytest.raises(ValueError, match="camera 'cam1': skew 0.2 is not 0; multical"):
        multical_file.write([cams[0], cams[1].with_params(skew=0.2)], tmp_path / "w")
    with pytest.raises(ValueError, match="camera 'a_to_b': .* without '_to_'"):
        multical_file.write([cams[0], cams[1].with_params(name="a_to_b")], tmp_path / "w")
    assert not (tmp_path / "w").exists()


@pytest.fixture(scope="module")
def charuco_pair(tmp_path_factory):
    """The quick-start pair (16 frames, clean) with a ChArUco board multical detects; its exact
    image points as the session's detections (multical detects its own in the images)."""
    rig = quickstart(16)
    rig["pattern"] = {"kind": "charuco", "squares_x": 7, "squares_y": 5, "square_mm": 40,
                      "marker_mm": 30, "dictionary": "DICT_4X4_50"}
    ds = write_dataset(parse_rig(rig), tmp_path_factory.mktemp("charuco") / "ds")
    gt = ds.ground_truth
    points = np.where(gt.visible[..., None], gt.points, np.nan)
    return ds, Session([c.name for c in ds.cameras], [c.size for c in ds.cameras],
                       ds.object_points, points, gt.visible.any(-1), ds.pattern,
                       images=ds.root / "images")


# Measured on this pair (multical 0.4 with OpenCV 4.6.0.66; multical is deterministic with the
# adapter's options): its ChArUco corners sit +0.49 px right and down of the true ones (OpenCV
# 4.6's half-pixel shift around cornerSubPix), which its principal point follows: cx +0.82 and
# +1.08 px, cy -0.07 and -0.27 px; fx, fy within 0.46 px; k1 within 0.016; the projection
# difference 1.79 and 1.83 px mean over the image (18.9 px at its corners, which no view
# reaches: k3 extrapolated); the right camera's centre 0.095 mm and rotation 0.040 deg from the
# truth; RMSE_cal 1.11 mm. The bounds below are about twice these: a slip of the adapter (units
# m vs mm, a pose's direction, fx for fy, a camera order) moves them by far more.
BOUNDS = {"projection_mean_px": 3.5, "focal_px": 1.0, "principal_point_px": 2.0, "k1": 0.035,
          "centre_mm": 0.2, "rotation_deg": 0.08, "rmse_cal_mm": 2.2}


def test_multical_calibrates_the_rendered_pair(charuco_pair, tmp_path):
    ds, session = charuco_pair
    mod = module("multical")
    if (why := mod.missing()) is not None:
        pytest.skip(why)
    images = sorted(p.relative_to(ds.root) for p in (ds.root / "images").rglob("*"))
    result = mod.calibrate(session, tmp_path / "multical", "multical")
    assert result.fmt == "multical" and result.path == tmp_path / "multical" / "calibration.json"
    assert [c.name for c in result.cameras] == session.names
    assert result.time_s > 0 and result.log["points_detected"].keys() == {"left", "right"}
    # Everything multical wrote is in the tool's folder; the dataset's images are untouched.
    assert sorted(p.relative_to(ds.root) for p in (ds.root / "images").rglob("*")) == images
    assert (tmp_path / "multical" / "calibration.txt").is_file()
    scored = score_cameras(ds, result.cameras, session.image_points, "multical")
    for cam in scored["cameras"].values():
        e = cam["parameter_errors"]
        assert cam["projection_difference"]["mean_px"] < BOUNDS["projection_mean_px"]
        assert max(abs(e["fx"]), abs(e["fy"])) < BOUNDS["focal_px"]
        assert np.hypot(e["cx"], e["cy"]) < BOUNDS["principal_point_px"]
        assert abs(e["k1"]) < BOUNDS["k1"]
    right = scored["rig"]["camera_errors"]["right"]
    assert right["centre_mm"] < BOUNDS["centre_mm"]
    assert right["rotation_deg"] < BOUNDS["rotation_deg"]
    assert scored["rig"]["rmse_cal_mm"] < BOUNDS["rmse_cal_mm"]


def test_multical_refuses_what_its_command_line_cannot_take(charuco_pair, tmp_path):
    ds, s = charuco_pair
    mod = module("multical")

    def session(**changes):
        fields = dict(names=s.names, sizes=s.sizes, object_points=s.object_points,
                      image_points=s.image_points, found=s.found, pattern=s.pattern,
                      images=s.images)
        fields.update(changes)
        return Session(**fields)

    cases = [
        (session(images=None), "multical: its command line reads image folders .* detections "
                               "only"),
        (session(pattern=parse_rig(quickstart(2)).pattern.build()),
         "multical: .* ChArUco and AprilGrid boards only .* the session's board is "
         "checkerboard"),
        (session(pattern=dataclasses.replace(s.pattern, two_sided=True)),
         "multical: a two-sided ChArUco board"),
        (session(names=["left", "../right"]), "multical: camera '../right' cannot name"),
        (session(names=["left", "middle"]), "multical: no image folder .*middle"),
    ]
    for bad, match in cases:
        with pytest.raises(ToolError, match=match):
            mod.calibrate(bad, tmp_path / "refused", "multical")
    # Nothing of multical's was run or written for a refused session.
    assert not (tmp_path / "refused" / "calibration.json").exists()
