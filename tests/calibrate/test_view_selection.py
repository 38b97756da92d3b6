"""Views chosen for a real capture's intrinsics: the blur measured against a known one, blurred
and repeated views left out and named, the rig still taking them."""

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from stereo_bench.cli import main
from stereo_bench.config.schema import parse_rig
from stereo_bench.detect.dataset import CameraDetections
from stereo_bench.run.pipeline import run
from stereo_bench.io.rundir import RunPaths
from stereo_bench.calibrate.view_selection import edge_spread, select_views
from quickstart import quickstart

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    """A clean stereo run of 8 frames: its left images and detections."""
    d = quickstart(8)
    cfg = parse_rig(d)
    tmp = tmp_path_factory.mktemp("selection")
    run(cfg, tmp / "run", ["opencv"])
    trial = RunPaths(tmp / "run").trial(cfg.seed)
    images = {cam: sorted((trial.dataset.root / "images" / cam).glob("*.png"))
              for cam in ("left", "right")}
    return images, CameraDetections.load(trial.detection("left")), tmp


def test_edge_spread_measures_a_known_blur(clean):
    """A Gaussian blur of sigma s added to the clean render's own edge spread s0 (the pixel's
    box and the anti-aliasing) measures sqrt(s0^2 + s^2); a motion blur along one axis shows
    (the blurrier edge direction counts), sensor noise does not."""
    images, det, _ = clean
    for f in np.flatnonzero(det.found)[:4]:
        img = cv2.imread(str(images["left"][f]), cv2.IMREAD_GRAYSCALE)
        s0 = edge_spread(img, det.points[f])
        assert 0.5 < s0 < 1.0
        for s in (1.0, 2.0, 3.0):
            measured = edge_spread(cv2.GaussianBlur(img, (0, 0), s), det.points[f])
            assert measured == pytest.approx(np.hypot(s0, s), rel=0.12)
        # A 9-px box along x (a board moving sideways for a ninth of the exposure's width):
        # sigma 9 / sqrt(12) = 2.6 px across vertical edges, none across horizontal ones.
        smeared = cv2.filter2D(img, -1, np.full((1, 9), 1 / 9, np.float32))
        assert edge_spread(smeared, det.points[f]) > 2.0
        noisy = np.clip(img + np.random.default_rng(0).normal(0, 4, img.shape), 0, 255)
        assert edge_spread(noisy.astype(np.uint8), det.points[f]) == pytest.approx(s0, abs=0.1)


def test_select_views_names_blurred_and_repeated_views():
    rng = np.random.default_rng(1)
    points = rng.uniform(0, 600, (6, 20, 2))
    points[3] = points[1] + 1.0  # frame 3 repeats frame 1 within 1.4 px RMS
    spreads = np.array([0.8, 0.9, 0.8, 0.7, 2.4, np.nan])
    found = np.array([True, True, True, True, True, True])
    out = select_views(points, found, spreads, (640, 480), lambda f: f"frame {f}")
    assert set(out) == {1, 4}  # frame 3 is sharper than frame 1: 1 repeats it
    assert out[4].startswith("blurred") and "2.40 px" in out[4]
    assert out[1].startswith("repeats frame 3") and "1.4 px RMS" in out[1]
    # A blur every view shares leaves nothing out.
    assert select_views(points[:3], found[:3], np.full(3, 2.5), (640, 480), str) == {}


def test_a_video_of_held_boards_and_a_blurred_frame(clean, tmp_path, capsys):
    """Each frame held for 3 video frames and one frame smeared: the intrinsics come from the 8
    distinct poses with the smeared one left out and named, the rig from every frame the
    cameras saw together, and the estimate is the one of the distinct sharp views."""
    images, _, _ = clean
    videos, stills = tmp_path / "videos", tmp_path / "stills"
    videos.mkdir()
    for cam, pngs in images.items():
        h, w = cv2.imread(str(pngs[0]), 0).shape
        writer = cv2.VideoWriter(str(videos / f"{cam}.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 30,
                                 (w, h))
        (stills / cam).mkdir(parents=True)
        for f, png in enumerate(pngs):
            img = cv2.imread(str(png))
            if cam == "left" and f == 5:
                img = cv2.filter2D(img, -1, np.full((1, 11), 1 / 11, np.float32))
            else:
                shutil.copy(png, stills / cam / f"{f:04d}.png")
            for _ in range(3):
                writer.write(img)
        writer.release()
    args = ["--board", "checkerboard", "--inner-corners", "8x11", "--square-mm", "15",
            "--methods", "opencv"]
    assert main(["calibrate-images", str(videos), *args, "--out", str(tmp_path / "v")]) == 0
    assert main(["calibrate-images", f"left={stills / 'left'}", f"right={stills / 'right'}",
                 *args, "--out", str(tmp_path / "s")]) == 0
    err = capsys.readouterr().err
    # The smeared frame's three copies are blurred; of the others' three copies, one is kept.
    assert ("camera 'left': 3 as blurred (frame 15, frame 16, frame 17) and 14 as repeating a "
            "board pose already taken") in " ".join(err.split())
    res = json.loads((tmp_path / "v" / "results.json").read_text())
    left = res["detection"]["left"]["views_left_out"]
    assert len(left) == 17 and all(left[f].startswith("blurred") for f in ("15", "16", "17"))
    assert len(res["detection"]["right"]["views_left_out"]) == 16
    assert res["view_blur"]["left"]["edge_spread_px"]["frame 15"] > 2.5
    ours = res["calibration"]["opencv"]
    assert ours["left"]["views"] == 7 and ours["right"]["views"] == 8
    # MJPEG moves corners a little: the video's estimate is the stills' within a few tenths of
    # a pixel of focal length (both near the true 600 px), and its rig keeps the true 120 mm
    # baseline.
    still = json.loads((tmp_path / "s" / "results.json").read_text())["calibration"]["opencv"]
    fx = [e["left"]["uncertainty"]["parameters"]["values"]["fx"] for e in (ours, still)]
    assert fx[0] == pytest.approx(fx[1], abs=0.5) and fx[1] == pytest.approx(600.0, abs=0.5)
    assert abs(res["rig"]["opencv"]["baseline_mm"]["right"] - 120.0) < 1.0
