"""A fisheye stereo pair end to end (configs/fisheye/fisheye_pair.yaml): rendered through its
Kannala-Brandt lenses, calibrated with the fisheye model and with OpenCV's pinhole model, scored
against the truth; the wrong model's cost in millimetres."""

import json
from pathlib import Path

import numpy as np
import pytest

from stereo_bench.cli import main
from stereo_bench.core.camera import Camera
from stereo_bench.io import opencv_yaml

RIG = Path(__file__).resolve().parents[2] / "configs" / "fisheye" / "fisheye_pair.yaml"


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    out = tmp_path_factory.mktemp("fisheye_pair")
    assert main(["run", str(RIG), "--out", str(out), "--methods", "zhang-fisheye,opencv"]) == 0
    return out


def test_a_fisheye_pair_is_calibrated_with_its_model_and_the_pinhole_costs_millimetres(run):
    tmp_path = run
    results = json.loads((tmp_path / "results.json").read_text())["aggregate"]
    rig = {m: v["RMSE_cal mm"]["mean"] for m, v in results["rig"].items()}
    # 30 clean frames of a 150-degree lens: the fisheye model triangulates the board to about
    # 0.05 mm (0.0527 measured); OpenCV's 5-coefficient pinhole, which cannot describe the lens
    # past ~60 degrees and folds inside the image, to 12 mm.
    assert rig["zhang-fisheye"] < 0.2
    assert rig["opencv"] > 20 * rig["zhang-fisheye"]
    calib = results["calibration"]["zhang-fisheye"]["left"]
    assert calib["RPE_RMS px"]["mean"] < 0.2
    assert results["calibration"]["opencv"]["left"]["valid image fraction"]["mean"] < 0.9
    # The calibration is stored with its lens and reads back as the same camera.
    stored = next((tmp_path / "trials").glob("seed_*/calibrations/zhang-fisheye/left.yaml"))
    camera = opencv_yaml.read(stored)[0]
    assert camera.model == "kannala_brandt"
    as_json = Camera.load_json(stored.with_suffix(".json"))
    assert camera.to_dict() == as_json.to_dict()


def test_its_images_calibrate_as_a_capture_with_the_lens_named(run, tmp_path, capsys):
    """calibrate-images --lens fisheye: every method that fits the lens (zhang, bouguet, opencv
    as zhang-fisheye...), the rig through the project's adjustment and OpenCV's
    calibrateMultiview with its fisheye model, beside the truth the images were rendered with."""
    dataset = next(run.glob("trials/seed_*/dataset"))
    truth = {c["name"]: Camera.from_dict(c)
             for c in json.loads((dataset / "ground_truth" / "cameras.json").read_text())}
    assert main(["calibrate-images", *(f"{c}={dataset / 'images' / c}" for c in truth),
                 "--board", "checkerboard", "--inner-corners", "8x11", "--square-mm", "15",
                 "--lens", "fisheye", "--out", str(tmp_path)]) == 0
    results = json.loads((tmp_path / "results.json").read_text())
    assert results["methods"] == ["zhang-fisheye", "bouguet-fisheye", "opencv-fisheye"]
    for method in ("zhang-fisheye", "bouguet-fisheye"):
        rig = results["rig"][method]
        cams = {c["name"]: Camera.from_dict(c) for c in rig["cameras"]}
        for name, cam in cams.items():
            assert cam.model == "kannala_brandt"
            # Detected corners at ~0.1 px (the RPE): fx, fy, cx, cy within 0.1 px (measured
            # up to 0.04 px).
            assert np.abs(cam.intrinsics[:4] - truth[name].intrinsics[:4]).max() < 0.1
        assert abs(rig["baseline_mm"]["right"] - 120.0) < 0.1  # measured 0.009 mm
    # OpenCV's calibrateMultiview, given bouguet-fisheye's cameras (zero skew) as fisheye
    # cameras, finds the same rig; zhang-fisheye estimates a skew, which it cannot take.
    ref = results["rig"]["bouguet-fisheye"]["opencv_multiview"]["cameras"]["right"]
    assert ref["difference_centre_mm"] < 1e-3 and ref["difference_rotation_deg"] < 1e-4
    assert "skew" in results["rig"]["zhang-fisheye"]["opencv_multiview"]["error"]
    # cv2.fisheye.calibrate fails on these views (in its initialisation, which drops the points
    # its first guess puts past 90 degrees, or by diverging to a negative focal length); each
    # failure is reported in words, not raised.
    errors = [e.get("error", "") for e in results["calibration"]["opencv-fisheye"].values()]
    assert all(e.startswith("ValueError: opencv-fisheye: OpenCV") for e in errors)
    # A method that cannot fit the lens is refused by name, not dropped.
    assert main(["calibrate-images", f"left={dataset / 'images' / 'left'}", "--board",
                 "checkerboard", "--inner-corners", "8x11", "--square-mm", "15", "--lens",
                 "fisheye", "--methods", "zhang,tsai", "--out", str(tmp_path / "t")]) == 2
    assert "--lens fisheye: method 'tsai-fisheye': tsai fits Tsai's own model" in (
        capsys.readouterr().err.replace("\n", " "))


def test_a_190_degree_lens_is_calibrated_over_its_whole_field(tmp_path):
    """configs/fisheye/fisheye_190_mono.yaml: the board over the whole field of a 190-degree
    lens (some views past 90 degrees, behind the camera's plane) is detected in every frame;
    the Kannala-Brandt fit projects the true rays to a tenth of a pixel on average where
    cv2.fisheye cannot run and the 8-coefficient pinhole misses by tens of pixels."""
    rig = RIG.parent / "fisheye_190_mono.yaml"
    assert main(["run", str(rig), "--out", str(tmp_path), "--methods",
                 "zhang-fisheye,opencv-fisheye,opencv-rational"]) == 0
    results = json.loads((tmp_path / "results.json").read_text())["aggregate"]
    assert results["detection"]["cam"]["rate"]["mean"] == 1.0
    calib = results["calibration"]
    diff = {m: calib[m]["cam"]["proj. diff mean px"]["mean"] for m in calib}
    assert diff["zhang-fisheye"] < 0.2  # measured 0.101 px (max 0.79 px)
    assert diff["opencv-rational"] > 10  # measured 99 px
    assert calib["opencv-fisheye"]["cam"]["failures"][0].startswith(
        "ValueError: opencv-fisheye: OpenCV")
