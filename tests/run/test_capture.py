"""A user's own images (`stereo-bench calibrate-images`): the same stages as a rendered dataset,
frames paired by number, the board as users describe it, and the real OpenCV sample pair."""

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from stereo_bench.core.camera import Camera
from stereo_bench.run.capture import calibrate_capture
from stereo_bench.cli import main
from stereo_bench.config.bounds import ConfigError
from stereo_bench.config.schema import parse_rig
from stereo_bench.scene.image_folders import (ImageFolders, frame_key, paired_by_time,
                                              read_timestamps)
from stereo_bench.core.patterns import Checkerboard
from stereo_bench.run.pipeline import run
from stereo_bench.io.rundir import RunPaths
from quickstart import quickstart

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """A small clean stereo run and the same images laid out as a user's two folders, named
    differently per camera (frames pair by their number)."""
    d = quickstart(10)
    cfg = parse_rig(d)
    tmp = tmp_path_factory.mktemp("capture")
    trial = run(cfg, tmp / "run", ["opencv"])[0]
    images = RunPaths(tmp / "run").trial(cfg.seed).dataset.root / "images"
    folders = {}
    for cam, prefix in (("left", "img_"), ("right", "right-")):
        folders[cam] = tmp / "user" / cam
        folders[cam].mkdir(parents=True)
        for f, png in enumerate(sorted((images / cam).glob("*.png"))):
            shutil.copy(png, folders[cam] / f"{prefix}{f + 1:04d}.png")
    return cfg, trial, folders, tmp


def test_frames_pair_by_the_last_number_in_the_name():
    assert frame_key(Path("left07.jpg")) == frame_key(Path("cam2/0007.png")) == (0, 7)
    assert frame_key(Path("take3_frame_12.tif")) == (0, 12)
    assert frame_key(Path("board.png")) == (1, "board")


def test_capture_runs_the_synthetic_stages_to_the_same_numbers(rendered):
    """The capture of the rendered images gives the estimate and the rig the synthetic run gave
    (shared stages), and only the synthetic run has the truth's scores."""
    cfg, trial, folders, tmp = rendered
    source = ImageFolders.open({k: str(v) for k, v in folders.items()}, cfg.pattern.build())
    assert source.frames == 10 and source.warnings == []
    res = calibrate_capture(source, ["opencv"], tmp / "out", folds=3)
    for cam in ("left", "right"):
        ours, theirs = res["calibration"]["opencv"][cam], trial["calibration"]["opencv"][cam]
        assert ours["rpe_rms_px"] == pytest.approx(theirs["rpe_rms_px"], rel=1e-12)
        assert "projection_difference" not in ours  # no truth here
        # Clean renders: held-out error near the in-sample one, a tiny projection uncertainty.
        assert ours["heldout"]["heldout_rms_px"] < 2 * ours["rpe_rms_px"] + 0.01
        assert ours["uncertainty"]["projection"]["centre_px"] < 0.05
    rig, ref = res["rig"]["opencv"], trial["rig"]["opencv"]
    assert rig["rms_px"] == pytest.approx(ref["rms_px"], rel=1e-9)
    assert rig["baseline_mm"]["right"] == pytest.approx(120.0, abs=0.5)  # the true baseline
    assert abs(rig["board_geometry"]["scale_error_pct"]) < 0.1
    peer = rig["opencv_multiview"]["cameras"]["right"]
    assert peer["difference_rotation_deg"] < 0.01 and peer["difference_centre_mm"] < 0.1
    assert (tmp / "out" / "plots" / "capture_left.png").is_file()
    assert json.loads((tmp / "out" / "results.json").read_text())["kind"] == "capture"


def test_missing_frames_and_bad_images_are_recorded(rendered, tmp_path):
    cfg, _, folders, _ = rendered
    left = tmp_path / "left"
    shutil.copytree(folders["left"], left)
    (left / "img_0003.png").unlink()
    cv2.imwrite(str(left / "img_0004.png"), np.zeros((10, 10), np.uint8))  # another size
    source = ImageFolders.open({"left": str(left), "right": str(folders["right"])},
                               cfg.pattern.build())
    assert "frame 3" in source.warnings[0]
    res = calibrate_capture(source, ["opencv"], tmp_path / "out", folds=3)
    errors = res["detection"]["left"]["errors"]
    assert "no image of frame 3" in errors["frame 3"]
    assert "10x10 px, expected 640x480" in errors["frame 4"]
    assert res["detection"]["left"]["found"] == 8
    assert "error" not in res["rig"]["opencv"]


@pytest.mark.parametrize("argv, message", [
    (["--board", "charuco", "--inner-corners", "9x6"], "--inner-corners: not an option of a"),
    (["--board", "checkerboard", "--inner-corners", "9"], "expected COLUMNSxROWS"),
    (["--board", "checkerboard", "--inner-corners", "9x1"], "inner_corners"),
    (["--board", "symmetric_circles", "--circles", "4x4", "--spacing-mm", "10",
      "--diameter-mm", "12"], "diameter_mm must be below spacing_mm"),
    (["--inner-corners", "9x6"], "--board: expected the board's kind"),
])
def test_bad_board_options_are_named(argv, message, tmp_path, capsys):
    assert main(["calibrate-images", f"x={tmp_path}", *argv, "--out", str(tmp_path / "o")]) == 2
    assert message in capsys.readouterr().err


def test_empty_folder_is_named(tmp_path, capsys):
    code = main(["calibrate-images", f"cam={tmp_path}", "--board", "checkerboard",
                 "--inner-corners", "9x6", "--out", str(tmp_path / "o")])
    assert code == 2 and f"camera 'cam': no JPEG, PNG or TIFF image in folder {tmp_path}" in \
        capsys.readouterr().err


def test_board_file_reads_the_rig_files_pattern_section(tmp_path):
    from argparse import Namespace

    from stereo_bench.run.capture_options import board_from_args

    path = tmp_path / "board.yaml"
    path.write_text("pattern:\n  kind: checkerboard\n  inner_corners: [9, 6]\n  square_mm: 24.5\n")
    board, diameter_given = board_from_args(Namespace(board_file=str(path)))
    assert isinstance(board, Checkerboard) and board.pattern_size == (9, 6)
    assert board.square_mm == 24.5 and not diameter_given
    path.write_text("kind: checkerboard\ninner_corners: [9, 6\n")  # not YAML
    with pytest.raises(ConfigError, match="board.yaml: not valid YAML"):
        board_from_args(Namespace(board_file=str(path)))


def test_real_opencv_pair_through_the_command(tmp_path, opencv_pair):
    """OpenCV's sample stereo pair, square size 1 (lengths in squares, as OpenCV's sample):
    the rig agrees with OpenCV's calibrateMultiview on the same detections and intrinsics, and
    the baseline is OpenCV's stereo_calib's 3.345 squares within a few hundredths."""
    out = tmp_path / "real"
    code = main(["calibrate-images", f"left={opencv_pair}/left*.jpg",
                 f"right={opencv_pair}/right*.jpg",
                 "--board", "checkerboard", "--inner-corners", "9x6", "--square-mm", "1",
                 "--methods", "opencv", "--folds", "3", "--out", str(out)])
    assert code == 0
    res = json.loads((out / "results.json").read_text())
    for cam in ("left", "right"):
        e = res["calibration"]["opencv"][cam]
        assert e["views"] == 13
        # OpenCV's own pipeline reaches 0.408 / 0.458 px (shared/real/README.md).
        assert e["rpe_rms_px"] < 0.42
        assert e["heldout"]["heldout_rms_px"] < 1.2 * e["rpe_rms_px"]
    rig = res["rig"]["opencv"]
    assert rig["baseline_mm"]["right"] == pytest.approx(3.345, abs=0.05)
    peer = rig["opencv_multiview"]["cameras"]["right"]
    assert peer["difference_rotation_deg"] < 0.05 and peer["difference_centre_mm"] < 0.01


def test_circle_grid_diameter_is_measured_when_not_given(tmp_path):
    """An asymmetric grid described as OpenCV describes it (4 x 11 style patternSize and its
    squareSize), the disc diameter left out: measured from the images, and the calibration
    matches the one given the true diameter."""
    d = quickstart(8)
    d["pattern"] = {"kind": "asymmetric_circles"}  # 10 per row x 9 rows, 9 mm discs
    cfg = parse_rig(d)
    from stereo_bench.scene.dataset import write_dataset

    ds = write_dataset(cfg, tmp_path / "ds")
    folder = ds.root / "images" / "left"
    args = ["calibrate-images", f"left={folder}", "--board", "asymmetric_circles",
            "--circles", "10x9", "--spacing-mm", f"{22 / 2 ** 0.5!r}", "--methods", "opencv",
            "--folds", "3"]
    assert main(args + ["--out", str(tmp_path / "measured")]) == 0
    assert main(args + ["--diameter-mm", "9", "--out", str(tmp_path / "given")]) == 0
    measured, given = (json.loads((tmp_path / k / "results.json").read_text())
                       for k in ("measured", "given"))
    assert measured["pattern"]["diameter_mm"] == pytest.approx(9.0, rel=0.02)
    assert any("disc diameter measured" in n for n in measured["notes"])
    # Clean renders fit to about 0.01 px, a figure set by the centroid windows the diameter
    # sizes: a 1-2 % different diameter moves it by a few thousandths of a pixel.
    a, b = (r["calibration"]["opencv"]["left"]["rpe_rms_px"] for r in (measured, given))
    assert abs(a - b) < 0.005 and max(a, b) < 0.03


def test_random_board_options_never_give_a_traceback(rendered, tmp_path, capsys):
    """calibrate-images with options drawn at random from plausible and nasty values: each exits
    0, 1 or 2 with a message, never a traceback, and writes only into --out."""
    import random

    _, _, folders, _ = rendered
    rng = random.Random(11)
    values = ["9x6", "8x11", "0x0", "-3x4", "x", "1e9x2", "5x5", "", "10", "2.5", "-1", "nan",
              "inf", "0", "1e12", "DICT_4X4_50", "DICT_NOPE", "../x"]
    options = ["--inner-corners", "--squares", "--circles", "--square-mm", "--marker-mm",
               "--dictionary", "--spacing-mm", "--diameter-mm", "--folds", "--methods"]
    kinds = ["checkerboard", "charuco", "symmetric_circles", "asymmetric_circles"]
    for case in range(25):
        argv = ["calibrate-images", f"left={folders['left']}", "--board", rng.choice(kinds)]
        for option in rng.sample(options, rng.randint(1, 4)):
            argv += [option, rng.choice(values)]
        out = tmp_path / f"o{case}"
        try:
            code = main(argv + ["--out", str(out)])
        except SystemExit as e:  # argparse's own refusal of a value of the wrong type
            code = e.code
        err = capsys.readouterr().err
        assert code in (0, 1, 2), (argv, code)
        assert "Traceback" not in err, (argv, err)
        assert code == 0 or "error" in err, (argv, err)
    assert sorted(p.name for p in tmp_path.iterdir() if not p.name.startswith("o")) == []


def test_synchronised_videos_calibrate_like_their_frames(rendered, tmp_path, capsys):
    """Each camera's frames as an MP4 video (each frame held for 3 video frames, as a board
    held still is filmed): calibrate-images takes the videos as they come, pairs them by frame
    index, takes every 3rd frame to stay within --max-frames, and finds the rig."""
    _, trial, folders, _ = rendered
    videos = tmp_path / "videos"
    videos.mkdir()
    for cam, folder in folders.items():
        images = sorted(folder.glob("*.png"))
        h, w = cv2.imread(str(images[0]), 0).shape
        writer = cv2.VideoWriter(str(videos / f"{cam}.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 30,
                                 (w, h))
        for png in images:
            for _ in range(3):
                writer.write(cv2.imread(str(png)))
        writer.release()
    out = tmp_path / "out"
    assert main(["calibrate-images", str(videos), "--board", "checkerboard", "--inner-corners",
                 "8x11", "--square-mm", "15", "--methods", "opencv", "--max-frames", "10",
                 "--out", str(out)]) == 0
    res = json.loads((out / "results.json").read_text())
    assert [c["name"] for c in res["cameras"]] == ["left", "right"]
    assert res["frames"] == 10 and res["frame_names"][:2] == ["frame 0", "frame 3"]
    assert res["detection"]["left"]["found"] == 10
    frames = json.loads((out / "frames.json").read_text())["frames"]
    assert frames[1]["files"]["left"].endswith("left.mp4@3")
    # MPEG-4 at its default quality moves corners by a fraction of a pixel, not the rig.
    rig = res["rig"]["opencv"]
    assert abs(rig["baseline_mm"]["right"] - 120.0) < 1.0
    assert rig["rms_px"] < 0.5


def test_videos_not_triggered_together_pair_by_their_timestamps(rendered, tmp_path):
    """The right camera started two video frames before the left and its clock runs 4 ms off:
    paired by frame index, a moment mixes two board poses (a rig far off, or none); paired by
    the timestamps file, every moment is one pose and the rig is the rendered one."""
    _, trial, folders, _ = rendered
    videos = tmp_path / "videos"
    videos.mkdir()
    rows = ["sync_index,cam_id,frame_time"]
    for cam, lead in (("left", 0), ("right", 2)):
        images = sorted(folders[cam].glob("*.png"))
        h, w = cv2.imread(str(images[0]), 0).shape
        writer = cv2.VideoWriter(str(videos / f"{cam}.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 30,
                                 (w, h))
        frames = [np.zeros((h, w, 3), np.uint8)] * lead + [
            cv2.imread(str(png)) for png in images for _ in range(3)]
        for k, frame in enumerate(frames):
            writer.write(frame)
            rows.append(f"{k},{cam},{(k - lead) / 30 + (0.004 if lead else 0.0):.6f}")
        writer.release()
    (videos / "timestamps.csv").write_text("\n".join(rows) + "\n")
    common = ["calibrate-images", f"left={videos / 'left.mp4'}",
              f"right={videos / 'right.mp4'}", "--board", "checkerboard", "--inner-corners",
              "8x11", "--square-mm", "15", "--methods", "opencv", "--max-frames", "10"]
    assert main([*common, "--timestamps", str(videos / "timestamps.csv"),
                 "--out", str(tmp_path / "timed")]) == 0
    res = json.loads((tmp_path / "timed" / "results.json").read_text())
    frames = json.loads((tmp_path / "timed" / "frames.json").read_text())["frames"]
    both = [f for f in frames if None not in f["files"].values()]
    # right, the longer video, leads the moments: only its first (black) frame pairs nothing.
    assert len(both) == len(frames) - 1 >= 7
    for f in both:
        left, right = (int(f["files"][c].rpartition("@")[2]) for c in ("left", "right"))
        assert right == left + 2 and f["time_spread_s"] == pytest.approx(0.004, abs=1e-6)
    rig = res["rig"]["opencv"]
    assert abs(rig["baseline_mm"]["right"] - 120.0) < 1.0 and rig["rms_px"] < 0.5
    assert rig["log"]["covisibility"][0][1] == len(both) and not rig["log"]["orientation"]
    # Paired by index, most moments mix two poses: the rig stage drops them as views whose
    # board pose disagrees with the other camera's (orientation.agree), naming each.
    by_index = tmp_path / "by_index"
    main([*common, "--out", str(by_index)])
    log = json.loads((by_index / "results.json").read_text())["rig"]["opencv"]["log"]
    assert len(log["orientation"]) >= 4 and log["covisibility"][0][1] <= 3


def test_timestamps_pair_by_nearest_time_and_are_checked(tmp_path):
    times = {"a": np.arange(6) / 30, "b": np.delete(np.arange(7) / 30 - 0.01, 3)}
    moments, spread = paired_by_time(times)
    # b dropped its fourth frame: moment 3 has none of b's (its nearest is 23 ms off, beyond half
    # a frame), and the later ones pair b's frames one index lower.
    assert moments == [{"a": 0, "b": 0}, {"a": 1, "b": 1}, {"a": 2, "b": 2}, {"a": 3},
                       {"a": 4, "b": 3}, {"a": 5, "b": 4}]
    np.testing.assert_allclose(spread, [0.01, 0.01, 0.01, 0.0, 0.01, 0.01], atol=1e-12)
    ts = tmp_path / "ts.csv"
    ts.write_text("camera,time\n" + "".join(f"cam_0,{t}\n" for t in range(3)))
    with pytest.raises(ValueError, match="3 rows for camera 'cam_0', whose video has 4 frames"):
        read_timestamps(ts, {"cam_0": 4})
    ts.write_text("cam,when\n0,1\n")
    with pytest.raises(ValueError, match="a time column"):
        read_timestamps(ts, {"cam_0": 1})
    ts.write_text("port,time\n0,0.5\n0,x\n")
    with pytest.raises(ValueError, match="line 3: time 'x' is not a time"):
        read_timestamps(ts, {"cam_0": 2})


def test_pose_eval_takes_a_capture_and_a_calibration_file(rendered, tmp_path, capsys):
    """A user's own rig: pose-eval --capture triangulates through each method's rig against
    the reference (opencv's), and --calibration FILE alone takes the file's cameras."""
    from pose_eval.cli import main as pose_main

    cfg, _, folders, _ = rendered
    cap = tmp_path / "cap"
    assert main(["calibrate-images", *(f"{c}={p}" for c, p in folders.items()), "--board",
                 "checkerboard", "--inner-corners", "8x11", "--square-mm", "15", "--methods",
                 "opencv,bouguet", "--out", str(cap)]) == 0
    assert pose_main(["--capture", str(cap), "--calib", "all", "--frames", "10"]) == 0
    res = json.loads((cap / "pose_eval" / "results.json").read_text())
    tri = {m: r["triangulated"] for m, r in res["methods"].items()}
    # Two calibrations of the same clean images: the same pose to a fraction of a millimetre
    # beside the floor of a 120 mm baseline with the body 2.2 m away (134 mm).
    assert set(tri) == {"gt", "bouguet"} and abs(tri["bouguet"]["excess_mpjpe_mm"]["mean"]) < 0.5
    assert res["environment"] == "capture (reference: opencv's rig)"
    exported = tmp_path / "exported"
    assert main(["export", str(cap), "--format", "opencv", "--out", str(exported)]) == 0
    assert pose_main(["--calibration", str(exported), "--frames", "10",
                      "--out", str(tmp_path / "pe")]) == 0
    res = json.loads((tmp_path / "pe" / "results.json").read_text())
    assert list(res["methods"]) == ["gt"]
    assert res["methods"]["gt"]["triangulated"]["mpjpe_mm"]["mean"] == pytest.approx(
        tri["gt"]["mpjpe_mm"]["mean"], rel=1e-6)  # the same rig, read back from the file


def test_intrinsics_from_a_file_fit_only_the_poses_and_the_rig(rendered, tmp_path, capsys):
    """--intrinsics FILE: the file's cameras (here the true ones, named as the capture's) keep
    their intrinsics for every method, even where the views alone could not determine them (one
    view, refused without the file); the rig from them is the true one. A file whose cameras the capture does not have, or of another size, is
    refused naming it."""
    from stereo_bench.io import anipose, caliscope

    cfg, _, folders, _ = rendered
    truth = cfg.cameras_true()
    (named,) = anipose.write(truth, tmp_path / "a")
    (path,) = caliscope.write(truth, tmp_path / "c")  # cameras cam_0, cam_1
    few = tmp_path / "few"
    for cam, folder in folders.items():
        (few / cam).mkdir(parents=True)
        for png in sorted(folder.glob("*.png"))[:1]:
            shutil.copy(png, few / cam / png.name)
    board = ["--board", "checkerboard", "--inner-corners", "8x11", "--square-mm", "15"]
    cams = [f"{c}={few / c}" for c in folders]
    assert main(["calibrate-images", *cams, *board, "--methods", "opencv",
                 "--out", str(tmp_path / "without")]) == 1
    assert main(["calibrate-images", *cams, *board, "--intrinsics", str(named), "--methods",
                 "opencv,zhang", "--out", str(tmp_path / "with")]) == 0
    res = json.loads((tmp_path / "with" / "results.json").read_text())
    assert res["intrinsics_given"] == {"file": str(named), "cameras": ["left", "right"]}
    for m in ("opencv", "zhang"):
        back = Camera.load_json(tmp_path / "with" / "calibrations" / m / "left.json")
        assert back.fx == truth[0].fx and np.array_equal(back.dist, truth[0].dist)
        e = res["calibration"][m]["left"]
        assert e["intrinsics_given"] and e["rpe_rms_px"] < 0.05 and e["views"] == 1
        rig = res["rig"][m]
        assert abs(rig["baseline_mm"]["right"] - 120.0) < 0.5
    assert res["recapture"] == []  # nothing to recapture for intrinsics not fitted here
    assert "intrinsics from" in capsys.readouterr().err
    assert main(["calibrate-images", *cams, *board, "--intrinsics", str(path),
                 "--out", str(tmp_path / "x")]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert "are none of the capture's ['left', 'right']" in err
    wrong = named.read_text().replace("size = [640, 480]", "size = [1280, 960]", 1)
    named.write_text(wrong)
    assert main(["calibrate-images", *cams, *board, "--intrinsics", str(named),
                 "--out", str(tmp_path / "y")]) == 2
    assert "camera 'left' is 1280x960 px there, its images 640x480 px" in \
        " ".join(capsys.readouterr().err.split())
