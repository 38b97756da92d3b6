"""stereo-bench twin: the imaging measured on a board's images (render/imaging_fit.py) and a
capture's twin (run/twin.py), checked where the truth is known (a rendered capture) and on the
real OpenCV pair, whose twin must say it does not match."""

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from stereo_bench.cli import main
from stereo_bench.core.camera import Camera
from stereo_bench.evaluate.metrics import projection_difference
from stereo_bench.render.imaging_fit import jpeg_quality

ROOT = Path(__file__).resolve().parents[2]

TRUE_ENVIRONMENT = {"kind": "clean", "background": 100, "black_level": 30, "white_level": 220,
                    "optics": {"blur_px": 0.6, "corner_illumination": 0.7},
                    "sensor": {"full_well_e": 3000.0, "exposure": 0.8, "read_noise_e": 8.0},
                    "board": {"warp_mm": [0.8, 0.5]}}


@pytest.mark.parametrize("quality", [30, 50, 75, 80, 95])
def test_jpeg_quality_is_read_from_the_files_tables(tmp_path, quality):
    image = np.random.default_rng(0).integers(0, 255, (64, 64), dtype=np.uint8)
    path = tmp_path / "x.jpg"
    cv2.imwrite(str(path), image, [cv2.IMWRITE_JPEG_QUALITY, quality])
    assert jpeg_quality(path) == quality
    cv2.imwrite(str(tmp_path / "x.png"), image)
    assert jpeg_quality(tmp_path / "x.png") is None


def test_the_twin_of_a_rendered_capture_finds_its_imaging_and_its_errors(tmp_path):
    """A pair rendered under known imaging with a bowed board, calibrated as a capture that fits
    the warp and twinned: the measured imaging and warp are the true ones, and the twin's
    prediction of each calibration's true error holds the capture's own true error (opencv's,
    which keeps the board flat, at several pixels; zhang-brown's at a tenth)."""
    rig = yaml.safe_load((ROOT / "configs" / "quickstart.yaml").read_text())
    rig.update(name="capture", environment=TRUE_ENVIRONMENT)
    rig["trajectory"]["frames"] = 15
    (tmp_path / "rig.yaml").write_text(yaml.safe_dump(rig))
    data, capture, twin = tmp_path / "data", tmp_path / "capture", tmp_path / "twin"
    assert main(["render", str(tmp_path / "rig.yaml"), "--out", str(data)]) == 0
    assert main(["calibrate-images", f"left={data}/images/left", f"right={data}/images/right",
                 "--board", "checkerboard", "--inner-corners", "8x11", "--square-mm", "15",
                 "--methods", "opencv,zhang-brown", "--fit-board-warp", "--out", str(capture)]
                ) == 0
    assert main(["twin", str(capture), "--method", "zhang-brown", "--seeds", "2", "--out",
                 str(twin)]) == 0
    results = json.loads((twin / "results.json").read_text())
    measured = results["imaging"]["measured_on_real"]["left"]
    env = results["rig"]["environment"]
    # Measured on 15 views (values of a 25-view run: blur 0.573, corner 0.70, 0.090 DN/e for
    # 220 / 2400 = 0.0917, 8.2 e- of read noise, background 100, black 29).
    assert env["optics"]["blur_px"] == pytest.approx(0.6, abs=0.08)
    assert measured["corner_illumination"] == pytest.approx(0.7, abs=0.03)
    assert measured["gain_dn_per_e"] == pytest.approx(220 / 2400, rel=0.1)
    assert env["sensor"]["read_noise_e"] == pytest.approx(8.0, rel=0.35)
    assert abs(measured["background"] - 100) <= 2 and abs(measured["black_level"] - 30) <= 2
    assert abs(measured["white_level"] - 220) <= 2
    assert env["board"]["warp_mm"] == pytest.approx([0.8, 0.5], abs=0.02)
    assert results["matches"], results["mismatch"]
    # The capture's own true error lies where the twin's seeds put it.
    truth = {c["name"]: Camera.from_dict(c)
             for c in json.loads((data / "ground_truth" / "cameras.json").read_text())}
    for method in ("opencv", "zhang-brown"):
        for name, cam in truth.items():
            est = Camera.load_json(capture / "calibrations" / method / f"{name}.json")
            true_error = projection_difference(est, cam.with_params(
                rvec=np.zeros(3), tvec=np.zeros(3)))["mean_px"]
            predicted = results["true_errors"][method]["cameras"][name]["projection_mean_px"]
            print(method, name, true_error, predicted)
            assert true_error < 4 * predicted["mean"] and predicted["mean"] < 4 * true_error
    for name in truth:
        twin_rpe = results["side_by_side"][name]["twin"]["rpe_px"]["mean"]
        assert twin_rpe == pytest.approx(results["side_by_side"][name]["real"]["rpe_px"],
                                         rel=0.15)


@pytest.mark.slow
def test_the_twin_of_the_real_opencv_pair_says_it_does_not_match(tmp_path, opencv_pair):
    """OpenCV's sample pair: its residuals carry a structure (neighbour correlation ~0.3) and
    an RPE four times what its measured noise and blur give; the twin says so instead of
    presenting true errors."""
    capture = tmp_path / "capture"
    assert main(["calibrate-images", f"left={opencv_pair}/left*.jpg",
                 f"right={opencv_pair}/right*.jpg", "--board", "checkerboard",
                 "--inner-corners", "9x6", "--square-mm", "25", "--methods", "opencv",
                 "--out", str(capture)]) == 0
    assert main(["twin", str(capture), "--seeds", "2", "--out", str(tmp_path / "twin")]) == 0
    results = json.loads((tmp_path / "twin" / "results.json").read_text())
    assert results["imaging"]["measured_on_real"]["left"]["jpeg_quality"] == 50
    assert not results["matches"]
    assert any("RPE" in m and "the real images have error the twin lacks" in m
               for m in results["mismatch"])
    report = (tmp_path / "twin" / "report.md").read_text()
    assert "The twin does not match" in report and "How far each" not in report


def test_the_defocus_fit_finds_the_thin_lens_from_edge_widths():
    """fit_defocus on edge widths that follow the thin lens (K = fx f / N = 4000 px mm, focused
    at 450 mm, a 0.6 px lens blur) with 0.02 px of scatter; and a width that does not grow with
    depth is left to the lens blur."""
    from stereo_bench.render.imaging_fit import fit_defocus

    depth = np.linspace(300, 650, 25)
    width = np.sqrt(0.6 ** 2 + (4000 * np.abs(1 / 450 - 1 / depth) / 4) ** 2)
    noisy = width + np.random.default_rng(1).normal(0, 0.02, depth.size)
    fit = fit_defocus(depth, noisy)
    assert fit["k_px_mm"] == pytest.approx(4000, rel=0.1)
    assert fit["focus_mm"] == pytest.approx(450, rel=0.03)
    assert fit["sigma0_px"] == pytest.approx(0.6, abs=0.05)
    assert fit_defocus(depth, 0.6 + np.random.default_rng(2).normal(0, 0.02, depth.size)) is None


def test_what_is_not_a_capture_is_named(tmp_path, capsys):
    assert main(["twin", str(tmp_path / "nowhere")]) == 2
    assert "no results.json; expected a calibrate-images output folder" in capsys.readouterr().err
    (tmp_path / "results.json").write_text(json.dumps({"kind": "run", "pattern": {}}))
    assert main(["twin", str(tmp_path)]) == 2
    assert "not a calibrate-images output's" in capsys.readouterr().err
    assert main(["twin", str(tmp_path), "--seeds", "0"]) == 2
    assert not (tmp_path / "twin").exists() or not any((tmp_path / "twin").iterdir())
