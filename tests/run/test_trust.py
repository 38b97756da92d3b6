"""Runs you can trust: reuse by fingerprint, one writer per run directory, torn markers, changed
images, strict JSON, estimates flagged where they fold, and byte-identical reruns."""

import json
import math
import multiprocessing
import os
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from stereo_bench.core.camera import Camera
from stereo_bench.cli import main
from stereo_bench.config.bounds import ConfigError
from stereo_bench.config.schema import load_rig, parse_rig
from stereo_bench.evaluate.metrics import projection_difference, validity
from stereo_bench.run.pipeline import load_run
from stereo_bench.io.rundir import RunLockedError, RunPaths, locked
from stereo_bench.core.files import read_json, strict, write_json
from quickstart import quickstart

ROOT = Path(__file__).resolve().parents[2]


def small_rig(tmp_path, name="rig.yaml", frames=6, **changes) -> Path:
    d = quickstart(frames)
    d.update(changes)
    path = tmp_path / name
    path.write_text(yaml.safe_dump(d))
    return path


def results(out: Path) -> dict:
    return json.loads((out / "results.json").read_text())


def test_strict_json_has_no_nan_and_says_why(tmp_path):
    path = write_json(tmp_path / "x.json", {"a": float("nan"), "b": [1.0, float("inf")],
                                            "c": np.float32(2.5), "d": np.arange(2)})
    text = path.read_text()
    assert "NaN" not in text and "Infinity" not in text
    assert json.loads(text) == {"a": None, "a_reason": "not a number", "b": [1.0, None],
                                "c": 2.5, "d": [0, 1]}
    assert not list(tmp_path.glob(".*.tmp"))  # the temporary file was moved into place


def test_lock_refuses_a_second_writer(tmp_path):
    with locked(tmp_path / "run"):
        ctx = multiprocessing.get_context("spawn")
        with ctx.Pool(1) as pool:
            message = pool.apply(_try_lock, (str(tmp_path / "run"),))
    assert "another run is writing into this folder" in message
    assert str(os.getpid()) in message
    with locked(tmp_path / "run"):  # released: a later run gets it
        pass


def _try_lock(path):
    try:
        with locked(path):
            return "acquired"
    except RunLockedError as e:
        return str(e)


def test_out_that_is_a_file_is_refused(tmp_path, capsys):
    rig = small_rig(tmp_path)
    (tmp_path / "file").write_text("x")
    assert main([str(rig), "--out", str(tmp_path / "file")]) == 2
    assert "exists and is not a directory" in capsys.readouterr().err


def test_edited_config_rerun_gives_the_new_results_and_says_so(tmp_path, capsys):
    out = tmp_path / "run"
    rig = small_rig(tmp_path)
    assert main([str(rig), "--out", str(out), "--methods", "opencv"]) == 0
    first = results(out)["trials"][0]
    capsys.readouterr()
    d = yaml.safe_load(rig.read_text())
    d["cameras"][0]["fx"] = 560.0  # an edited lens
    rig.write_text(yaml.safe_dump(d))
    assert main([str(rig), "--out", str(out), "--methods", "opencv"]) == 0
    err = capsys.readouterr().err.replace("\n", "")
    assert "rendered from another configuration" in err
    second = results(out)["trials"][0]
    truth = read_json(RunPaths(out).trial(7).dataset.cameras)[0]
    assert truth["fx"] == 560.0
    est = Camera.load_json(RunPaths(out).trial(7).calibration("opencv", "left"))
    assert abs(est.fx - 560.0) < 1.0  # calibrated from the new renders, not reused
    assert second["fingerprint"] != first["fingerprint"]
    assert any("another configuration" in n for n in results(out)["aggregate"]["notes"])


def test_changed_methods_redo_calibration_but_reuse_detections(tmp_path):
    out = tmp_path / "run"
    rig = small_rig(tmp_path)
    assert main([str(rig), "--out", str(out), "--methods", "opencv"]) == 0
    trial = RunPaths(out).trial(7)
    detected = trial.detections_done.stat().st_mtime_ns
    assert main([str(rig), "--out", str(out), "--methods", "opencv,bouguet"]) == 0
    assert trial.detections_done.stat().st_mtime_ns == detected
    assert set(results(out)["aggregate"]["rig"]) == {"opencv", "bouguet"}


def test_edited_calibration_settings_redo_only_the_stages_that_read_them(tmp_path):
    """The rig stage's settings redo the rig stage alone; the images and the detections are
    reused; the dataset does not carry the settings (a stale copy would mislead), the results
    and the report record the ones used."""
    out = tmp_path / "run"
    rig = small_rig(tmp_path)
    assert main([str(rig), "--out", str(out), "--methods", "opencv"]) == 0
    trial = RunPaths(out).trial(7)
    stamps = {p: p.stat().st_mtime_ns for p in (trial.dataset.manifest, trial.detections_done,
                                                  trial.metrics, trial.rig("opencv"))}
    d = yaml.safe_load(rig.read_text())
    d["calibration"] = {"loss": "huber", "loss_scale_px": 2.0}
    rig.write_text(yaml.safe_dump(d))
    assert main([str(rig), "--out", str(out), "--methods", "opencv"]) == 0
    changed = {p.name for p, t in stamps.items() if p.stat().st_mtime_ns != t}
    assert changed == {"opencv.json"}
    entry = read_json(trial.rig("opencv"))
    assert entry["settings"] == {"refine_intrinsics": False, "loss": "huber",
                                 "loss_scale_px": 2.0}
    assert entry["log"]["loss"] == "huber"
    assert "calibration" not in yaml.safe_load(trial.dataset.config.read_text())
    assert "calibration" not in read_json(trial.dataset.manifest)["config"]
    assert "huber loss (scale 2 px)" in (out / "report.md").read_text()
    # pose-eval reads the rig made with the settings it records.
    assert "opencv" in load_run(out)[0].rigs


# detections/done.json is read only when the calibration stage is redone (metrics.json carries
# the detections' fingerprint), so a torn one alone changes nothing and goes unmentioned.
@pytest.mark.parametrize("marker", ["dataset/manifest.json", "metrics.json", "rig/opencv.json",
                                    "dataset/ground_truth/cameras.json"])
def test_a_torn_marker_is_redone_and_named(tmp_path, capsys, marker):
    out = tmp_path / "run"
    rig = small_rig(tmp_path, frames=5)
    assert main([str(rig), "--out", str(out), "--methods", "opencv"]) == 0
    before = results(out)["trials"][0]["rig"]["opencv"]["rmse_cal_mm"]
    path = RunPaths(out).trial(7).root / marker
    path.write_bytes(path.read_bytes()[:len(path.read_bytes()) // 2])  # cut short by a kill
    capsys.readouterr()
    assert main([str(rig), "--out", str(out), "--methods", "opencv"]) == 0
    err = capsys.readouterr().err.replace("\n", "")
    # A torn marker is unreadable; a torn file a marker lists is no longer the one it wrote.
    assert ("unreadable" in err or "changed since its stage wrote it" in err)
    assert marker.split("/")[-1] in err
    assert results(out)["trials"][0]["rig"]["opencv"]["rmse_cal_mm"] == before


def _flip_last_byte(path):
    data = bytearray(path.read_bytes())
    data[-1] ^= 0x01  # an .npy stays loadable with another value, a JSON number changes
    path.write_bytes(bytes(data))


# A stage's outputs torn or edited after it wrote them (a kill mid-copy, a hand edit, a disk
# error) are not reused as the stage's: its marker holds their digests.
@pytest.mark.parametrize("output", ["dataset/ground_truth/visible.npy",
                                    "dataset/ground_truth/image_points.npy",
                                    "detections/left.npz", "calibrations/opencv/left.json"])
def test_an_output_changed_after_its_stage_is_redone_and_named(tmp_path, capsys, output):
    out = tmp_path / "run"
    rig = small_rig(tmp_path, frames=5)
    assert main([str(rig), "--out", str(out), "--methods", "opencv"]) == 0
    before = results(out)["trials"][0]
    path = RunPaths(out).trial(7).root / output
    if path.suffix == ".json":
        path.write_text(path.read_text().replace('"fx": ', '"fx": 1', 1))
    else:
        _flip_last_byte(path)
    capsys.readouterr()
    assert main([str(rig), "--out", str(out), "--methods", "opencv"]) == 0
    err = capsys.readouterr().err.replace("\n", "")
    assert f"{path.name}: changed since its stage wrote it" in err
    after = results(out)["trials"][0]
    assert after["rig"]["opencv"]["rmse_cal_mm"] == before["rig"]["opencv"]["rmse_cal_mm"]
    assert _without_times(after["calibration"]) == _without_times(before["calibration"])


def _without_times(d):
    """A report without its wall times (the keys ending in _s, and the sections of them), which
    a redone stage renews; a marker's "content" is the digest of its keys, wall times included."""
    if isinstance(d, dict):
        return {k: _without_times(v) for k, v in d.items()
                if not (k.endswith("_s") or k in ("timing", "time s", "content"))}
    return [_without_times(v) for v in d] if isinstance(d, list) else d


def test_a_resized_image_is_refused_naming_it(tmp_path, capsys):
    import cv2

    out = tmp_path / "run"
    rig = small_rig(tmp_path, frames=4)
    assert main(["render", str(rig), "--out", str(out)]) == 0
    image = out / "images" / "right" / "000002.png"
    cv2.imwrite(str(image), cv2.resize(cv2.imread(str(image)), (320, 240)))
    capsys.readouterr()
    assert main(["calibrate", str(out), "--methods", "opencv"]) == 2
    err = capsys.readouterr().err.replace("\n", "")
    assert "000002.png: 320x240 px, expected 640x480" in err


def test_identical_runs_differ_only_in_wall_times(tmp_path):
    """The same config and seed, twice, into two folders: every image, array, calibration and
    plot is byte-identical; the JSON files differ only in keys documented as wall times."""
    rig = small_rig(tmp_path, frames=5)
    a, b = tmp_path / "a", tmp_path / "b"
    for out in (a, b):
        assert main([str(rig), "--out", str(out), "--methods", "opencv,zhang"]) == 0
    differ = sorted(p.relative_to(a).as_posix() for p in a.rglob("*") if p.is_file()
                    and p.read_bytes() != (b / p.relative_to(a)).read_bytes())
    # report.html embeds report.md's tables, whose wall-time columns differ (as report.md's).
    assert set(differ) <= {".lock", "report.md", "report.html", "results.json",
                           "trials/seed_7/metrics.json",
                           "trials/seed_7/dataset/timing.json",
                           "trials/seed_7/detections/done.json", "trials/seed_7/rig/opencv.json",
                           "trials/seed_7/rig/zhang.json"}, differ

    for name in differ:
        if name.endswith(".json"):
            assert _without_times(json.loads((a / name).read_text())) == _without_times(
                json.loads((b / name).read_text())), name


def test_valid_config_values_that_see_nothing_are_refused_or_warned(tmp_path, capsys):
    far = small_rig(tmp_path, "far.yaml")
    d = yaml.safe_load(far.read_text())
    d["trajectory"]["depth_mm"] = [5e5, 6e5]  # the board 500 m away: blank images
    far.write_text(yaml.safe_dump(d))
    assert main(["render", str(far), "--out", str(tmp_path / "o1")]) == 2
    err = capsys.readouterr().err.replace("\n", "")
    assert str(far) in err and "spans at most" in err and "trajectory.depth_mm" in err
    assert not (tmp_path / "o1" / "manifest.json").exists()

    one = small_rig(tmp_path, "one.yaml")
    d = yaml.safe_load(one.read_text())
    d["cameras"][1]["look_at_mm"] = [-100000.0, 0.0, 700.0]  # looks away from the board
    one.write_text(yaml.safe_dump(d))
    assert main(["render", str(one), "--out", str(tmp_path / "o2")]) == 0
    err = capsys.readouterr().err.replace("\n", "")
    assert "camera 'right': the board is never in view" in err
    assert "camera 'right': the board is partly" not in err


@pytest.mark.parametrize("change, field", [
    ({"cx": -1.0}, "cameras.0"), ({"cy": 0.0}, "cameras.0"), ({"width": True}, "width"),
    ({"name": "../../x"}, "cameras.0.name"), ({"name": "/abs/x"}, "cameras.0.name"),
    ({"name": "x" * 300}, "cameras.0.name"), ({"fx": float("nan")}, "cameras.0.fx"),
    ({"position_mm": [float("nan"), 0, 0]}, "cameras.0.position_mm"),
    ({"width": int(1e12)}, "cameras.0.width"), ({"dist": [1e6, 0, 0, 0]}, "cameras.0.dist")])
def test_bad_camera_values_are_refused_by_name(tmp_path, change, field):
    d = yaml.safe_load((ROOT / "configs" / "quickstart.yaml").read_text())
    d["cameras"][0].update(change)
    with pytest.raises(ConfigError, match=field.replace(".", r"\.")):
        parse_rig(d, "x.yaml")


@pytest.mark.parametrize("text, expected", [
    (b"name: a\nname: b\n", "duplicate key 'name'"),
    ("name: x\n".encode("utf-16"), "not UTF-8 text"),
    (b"a: " + b"[" * 10000 + b"]" * 10000 + b"\n", "nested"),
    (b"\x00\x01\x02", "NUL")])
def test_unreadable_rig_files_are_named(tmp_path, text, expected):
    path = tmp_path / "rig.yaml"
    path.write_bytes(text)
    with pytest.raises(ConfigError) as e:
        load_rig(path)
    assert str(path) in str(e.value) and expected in str(e.value)


def test_pattern_overrides_are_checked_per_kind():
    d = yaml.safe_load((ROOT / "configs" / "quickstart.yaml").read_text())
    for override, message in [({"square_mm": "abc"}, "pattern.square_mm: expected a finite"),
                              ({"squares_x": "9"}, "pattern.squares_x: expected an integer"),
                              ({"squares_x": 1000}, "expected 2..100"),
                              ({"spacing_mm": 3}, "unknown field for checkerboard"),
                              ({"square_mm": 500.0}, "outline")]:
        with pytest.raises(ConfigError, match=message):
            parse_rig({**d, "pattern": {"kind": "checkerboard", **override}})
    with pytest.raises(ConfigError, match=r"pattern\.rows: expected 2\.\.100, got 1"):
        parse_rig({**d, "pattern": {"kind": "symmetric_circles", "rows": 1, "cols": 5}})


def test_sweep_refuses_duplicates_and_unknown_methods_before_rendering(tmp_path, capsys):
    rig = small_rig(tmp_path)
    for grid, message in [({"rigs": [str(rig), str(rig)]}, "would run twice"),
                          ({"rigs": [str(rig)], "methods": []}, "methods"),
                          ({"rigs": [str(rig)], "methods": ["nosuch"]}, "nosuch")]:
        path = tmp_path / "grid.yaml"
        path.write_text(yaml.safe_dump({"patterns": ["checkerboard"], **grid}))
        assert main(["sweep", str(path), "--out", str(tmp_path / "s")]) == 2
        assert message in capsys.readouterr().err
        assert not (tmp_path / "s").exists()


def test_a_folding_estimate_is_flagged_and_its_statistics_cover_only_the_valid_part():
    truth = Camera("c", 640, 480, 600, 450, 320, 240, dist=[0.5, 0.1, 0.03, 0, 0, 0, 0, 0])
    # k1 < 0 with no higher term folds at r = 1/sqrt(3 |k1|) = 0.73: inside this image.
    folded = truth.with_params(dist=np.array([-0.62, 0, 0, 0, 0, 0, 0, 0]))
    v = validity(folded)
    assert not v["usable"] and 0 < v["valid_fraction"] < 1
    assert v["fold_radius"] == pytest.approx(1 / math.sqrt(3 * 0.62), abs=1e-4)
    # Over the valid part, the statistics no longer depend on the grid (within its sampling).
    coarse, fine = (projection_difference(folded, truth, grid=g) for g in ((64, 48), (320, 240)))
    assert coarse["fraction_left_out"] > 0.3
    assert coarse["fraction_left_out"] == pytest.approx(fine["fraction_left_out"], abs=0.025)
    assert coarse["mean_px"] == pytest.approx(fine["mean_px"], rel=0.01)
    assert validity(truth) == {"valid_fraction": 1.0, "fold_radius": pytest.approx(
        validity(truth)["fold_radius"]), "usable": True}


def test_strict_handles_nested_numpy():
    assert strict({"x": [np.nan, {"y": np.inf}]}) == {"x": [None, {"y": None,
                                                                  "y_reason": "infinite"}]}


def test_pose_eval_refuses_meaningless_options(tmp_path, capsys):
    from pose_eval import cli

    rig = str(ROOT / "configs" / "quickstart.yaml")
    for option, value in [("--noise-px", "nan"), ("--noise-px", "inf"),
                          ("--distance-mm", "1e9"), ("--miss-rate", "1"),
                          ("--outlier-rate", "-0.1")]:
        assert cli.main(["--calib", "gt", "--rig", rig, option, value,
                         "--out", str(tmp_path / "p")]) == 2
        assert option in capsys.readouterr().err
    assert not (tmp_path / "p").exists()


def test_a_rerun_leaves_no_estimate_of_an_earlier_configuration(tmp_path):
    from stereo_bench.run.pipeline import load_run

    out = tmp_path / "run"
    rig = small_rig(tmp_path)
    assert main([str(rig), "--out", str(out), "--methods", "opencv,bouguet"]) == 0
    trial = RunPaths(out).trial(7)
    assert trial.calibration("opencv", "right").is_file()
    # Fewer methods: pose-eval must not pick up the bouguet rig of the earlier run.
    assert main([str(rig), "--out", str(out), "--methods", "opencv"]) == 0
    assert set(load_run(out)[0].rigs) == {"opencv"}
    # Camera 'right' now sees the board a few px wide: its old estimate must not be left behind.
    d = yaml.safe_load(rig.read_text())
    d["cameras"][1].update(fx=8.0, fy=8.0, dist=[0.0] * 8)
    rig.write_text(yaml.safe_dump(d))
    assert main([str(rig), "--out", str(out), "--methods", "opencv"]) == 0
    assert "error" in results(out)["trials"][0]["calibration"]["opencv"]["right"]
    assert not trial.calibration("opencv", "right").exists()
    assert trial.calibration("opencv", "left").is_file()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_workers_end_with_a_killed_run(tmp_path):
    """A run killed by a signal releases its lock; its workers must not go on writing into the
    run directory under the next run's lock."""
    import signal
    import subprocess
    import time

    rig = small_rig(tmp_path, frames=40)
    out = tmp_path / "run"
    run = subprocess.Popen([sys.executable, "-m", "stereo_bench.cli", str(rig), "--out",
                            str(out), "--methods", "opencv", "--trials", "2", "--workers", "2"],
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

    def children():
        found = []
        for stat in Path("/proc").glob("[0-9]*/stat"):
            try:
                fields = stat.read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == run.pid:
                found.append(int(stat.parent.name))
        return found

    deadline = time.monotonic() + 60
    while len(children()) < 2 and time.monotonic() < deadline and run.poll() is None:
        time.sleep(0.2)
    workers = children()
    assert len(workers) >= 2, "the run did not start its workers"
    time.sleep(2)  # let the workers reach their initializer and start working
    run.send_signal(signal.SIGKILL)
    run.wait()
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline and any(Path(f"/proc/{w}").exists() for w in workers):
        time.sleep(0.2)
    alive = [w for w in workers if Path(f"/proc/{w}").exists()
             and "Z" not in Path(f"/proc/{w}/stat").read_text().rsplit(")", 1)[1].split()[0]]
    for w in alive:
        os.kill(w, signal.SIGKILL)
    assert not alive, f"workers {alive} outlived their killed run"
