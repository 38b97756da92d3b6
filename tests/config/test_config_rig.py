"""Rig files: validation messages, shipped configs, and the conical-spring trajectory."""

from pathlib import Path

import numpy as np
import pytest
import yaml

from stereo_bench.config.bounds import ConfigError
from stereo_bench.config.schema import load_rig, parse_rig
from stereo_bench.scene.rig import Rig, spring_extent

CONFIGS = sorted(p for p in Path(__file__).resolve().parents[2].joinpath("configs").rglob("*.yaml")
                 if p.parent.name not in ("grids", "studies"))
QUICK = Path(__file__).resolve().parents[2] / "configs" / "quickstart.yaml"


def quick_dict():
    return yaml.safe_load(QUICK.read_text())


def test_unknown_key_is_named():
    d = quick_dict()
    d["cameras"][0]["focal"] = 3
    with pytest.raises(ConfigError, match=r"cameras\.0\.focal: unknown key"):
        parse_rig(d, "x.yaml")


def test_missing_and_wrong_type_are_named():
    d = quick_dict()
    del d["cameras"][1]["fx"]
    d["trajectory"]["frames"] = "many"
    with pytest.raises(ConfigError) as e:
        parse_rig(d, "x.yaml")
    msg = str(e.value)
    assert "cameras.1.fx: missing required field" in msg
    assert "trajectory.frames" in msg and "integer" in msg


def test_bad_pattern_kind_and_dist_length():
    d = quick_dict()
    d["pattern"]["kind"] = "dots"
    d["cameras"][0]["dist"] = [0.1]
    with pytest.raises(ConfigError) as e:
        parse_rig(d, "x.yaml")
    assert "pattern.kind" in str(e.value) and "cameras.0.dist" in str(e.value)


def test_unreadable_file(tmp_path):
    with pytest.raises(ConfigError, match="cannot read"):
        load_rig(tmp_path / "nope.yaml")
    (tmp_path / "bad.yaml").write_text("cameras: [")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_rig(tmp_path / "bad.yaml")


SPRINGS = [p for p in CONFIGS if load_rig(p).trajectory.kind == "spring"]


@pytest.mark.parametrize("path", SPRINGS, ids=[p.stem for p in SPRINGS])
def test_shipped_spring_configs_keep_the_board_in_view(path):
    rig = Rig.from_config(load_rig(path))
    gt = rig.ground_truth()
    seen = gt.visible.all(axis=2)  # (C, F): whole board seen
    # The conical spring is designed to keep the whole board in every camera's view (a
    # studio's session is not: tests/scene/test_studio.py).
    assert seen.mean() >= 0.95, rig.coverage(gt)


def test_a_dome_spreads_the_board_over_a_wide_lens_past_90_degrees():
    """configs/fisheye/fisheye_190_mono.yaml: every frame shows the whole board (each facing
    the camera) and the frames reach the lens's field, some past 90 degrees off its axis."""
    rig = Rig.from_config(load_rig(QUICK.parent / "fisheye" / "fisheye_190_mono.yaml"))
    cam = rig.cameras[0]
    assert rig.ground_truth().visible[0].all()
    Pc = cam.world_to_cam(rig.board_points_world())
    angle = np.degrees(np.arccos(Pc[..., 2] / np.linalg.norm(Pc, axis=-1))).max(axis=1)
    assert angle.min() < 30 and angle.max() > 90  # measured 22.5 and 90.3 degrees
    assert np.all(np.einsum("fi,fni->fn", rig.trajectory.rotations[:, :, 2], Pc) > 0)
    d = quick_dict()
    d["trajectory"]["max_angle_deg"] = 80
    with pytest.raises(ConfigError, match="max_angle_deg: only a dome trajectory"):
        parse_rig(d, "x.yaml")
    d["trajectory"].update(kind="dome", radius_mm=[10, 20])
    with pytest.raises(ConfigError, match="radius_mm: a dome trajectory"):
        parse_rig(d, "x.yaml")


def test_a_poses_trajectory_puts_the_board_where_it_says():
    d = quick_dict()
    poses = [[0.0, 0.0, 0.0, -60.0, -40.0, 500.0], [0.2, -0.1, 0.05, -50.0, -30.0, 650.0]]
    d["trajectory"] = {"kind": "poses", "poses": poses}
    rig = Rig.from_config(parse_rig(d, "x.yaml"))
    assert len(rig.trajectory) == 2
    assert np.array_equal(np.c_[rig.trajectory.rvecs, rig.trajectory.tvecs], poses)
    for change, message in (({"frames": 3}, "frames: 3, but poses has 2"),
                            ({"kind": "spring"}, "poses: a poses trajectory"),
                            ({"poses": [[0, 0, 0, 0, 0]]}, "trajectory.poses.0"),
                            ({"poses": [[20.0, 0, 0, 0, 0, 500]]}, "within 4 pi rad")):
        with pytest.raises(ConfigError, match=message):
            parse_rig({**d, "trajectory": {**d["trajectory"], **change}}, "x.yaml")


def test_trajectory_is_a_conical_spring_facing_the_rig():
    cfg = load_rig(QUICK)
    rig = Rig.from_config(cfg)
    obj = rig.pattern.object_points()
    centre = 0.5 * (obj.min(0) + obj.max(0))
    p = np.einsum("fij,j->fi", rig.trajectory.rotations, centre) + rig.trajectory.tvecs
    w, h = rig.pattern.size_mm
    depth, radii = spring_extent(rig.cameras, 0.5 * np.hypot(w, h), cfg.trajectory)
    # Depth grows linearly along the rig axis (world z here) from near to far, and so does the
    # radius of the helix around it.
    assert np.allclose(p[:, 2], np.linspace(*depth, cfg.trajectory.frames))
    semi = np.linspace(*radii, cfg.trajectory.frames)  # (F, 2) ellipse semi-axes
    assert np.allclose(np.hypot(p[:, 0] / semi[:, 0], p[:, 1] / semi[:, 1]), 1.0)
    # Board normal makes exactly the configured tilt with the line of sight to the rig centre.
    normal = rig.trajectory.rotations[:, :, 2]
    sight = p / np.linalg.norm(p, axis=1, keepdims=True)
    angle = np.degrees(np.arccos(np.clip(np.sum(normal * sight, 1), -1, 1)))
    assert np.allclose(angle, cfg.trajectory.tilt_deg)
