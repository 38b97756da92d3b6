"""A fisheye stereo pair end to end (configs/fisheye/fisheye_pair.yaml): rendered through its
Kannala-Brandt lenses, calibrated with the fisheye model and with OpenCV's pinhole model, scored
against the truth; the wrong model's cost in millimetres."""

import json
from pathlib import Path

from stereo_bench.cli import main
from stereo_bench.core.camera import Camera
from stereo_bench.io import opencv_yaml

RIG = Path(__file__).resolve().parents[2] / "configs" / "fisheye" / "fisheye_pair.yaml"


def test_a_fisheye_pair_is_calibrated_with_its_model_and_the_pinhole_costs_millimetres(tmp_path):
    assert main(["run", str(RIG), "--out", str(tmp_path), "--methods", "zhang-fisheye,opencv"]
                ) == 0
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
