"""Kalibr's camera chain, ``camchain.yaml`` (the layout of kalibr_calibrate_cameras' output, read
by Kalibr's ConfigReader.CameraChainParameters).

Subset: ``camera_model: pinhole`` with ``intrinsics: [fu, fv, pu, pv]`` (no skew: refused) and
``distortion_model: radtan`` with ``distortion_coeffs: [k1, k2, r1, r2]``: OpenCV's k1, k2, p1,
p2, in that order and with the same formula; k3..k6 are refused. Per camera ``cam<i>``: those
keys, ``resolution: [w, h]``, ``rostopic: /<name>/image_raw`` (the only place a camera's name
fits; read back from it), ``cam_overlaps`` (every other camera: the suite's rigs all observe one
target; edit it for a rig whose views are disjoint) and, from cam1 on, ``T_cn_cnm1``: the 4x4
transform of this camera from the previous one (``p_n = T p_{n-1}``), in metres, Kalibr's unit
(the suite's millimetres are divided by 1000 on writing and multiplied back on reading).

Pixel convention: OpenCV's (top-left pixel centre at (0, 0)): Kalibr fits its models to the
corners OpenCV's detectors give, unshifted, and mrcal's Kalibr converters copy pu, pv unchanged.

The chain has no world frame: a rig whose camera 0 is not at the identity is refused unless
``rebase=True``. Reading puts cam0 at the identity. Models other than pinhole-radtan /
pinhole-none (omni, ds, eucm, equidistant, fov) are refused with a ValueError naming the camera.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Sequence

import numpy as np
import yaml
from ..core.camera import Camera
from ..core.poses import compose, invert, matrix_to_rodrigues
from ..config.yaml_reader import load_yaml
from ..core.files import write_text
from . import common

FORMAT = "Kalibr camchain"
FILE = "camchain.yaml"
_TOPIC = re.compile(r"/(.+)/image_raw")
_NAME = re.compile(r"[^/\s]+")


def _transform(R: np.ndarray, t_mm: np.ndarray) -> list[list[float]]:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t_mm / common.MM_PER_M
    return T.tolist()


def write(cameras: Sequence[Camera], out_dir, rebase: bool = False) -> list[Path]:
    """Write ``camchain.yaml`` in ``out_dir`` (module notes)."""
    cameras = common.rig(cameras, FORMAT)
    for cam in cameras:
        common.refuse_skew(cam, "Kalibr's pinhole model")
        common.refuse_distortion(cam, "Kalibr's radtan model", 4)
        common.refuse_name(cam, FORMAT, "characters other than '/' and whitespace (it becomes "
                           "the rostopic /<name>/image_raw)", _NAME)
    R, t = common.cam_from_cam0(cameras, FORMAT, rebase)
    chain = {}
    for i, cam in enumerate(cameras):
        entry = {
            "camera_model": "pinhole",
            "intrinsics": [cam.fx, cam.fy, cam.cx, cam.cy],
            "distortion_model": "radtan",
            "distortion_coeffs": cam.dist[:4].tolist(),
            "resolution": [cam.width, cam.height],
            "rostopic": f"/{cam.name}/image_raw",
            "cam_overlaps": [j for j in range(len(cameras)) if j != i],
        }
        if i > 0:
            # cam_i_from_cam_{i-1} = cam_i_from_cam0 o cam0_from_cam_{i-1}
            entry["T_cn_cnm1"] = _transform(*compose(R[i], t[i], *invert(R[i - 1], t[i - 1])))
        chain[f"cam{i}"] = entry
    text = yaml.safe_dump(chain, sort_keys=False, default_flow_style=None)
    return [write_text(Path(out_dir) / FILE, text)]


def _camera(entry, key: str, where: str, rvec, tvec) -> Camera:
    at = f"{where}: {key}"
    if not isinstance(entry, dict):
        raise ValueError(f"{at}: expected a mapping of camera_model, intrinsics, ...")
    try:
        model, dist_model = entry["camera_model"], entry["distortion_model"]
        intrinsics, coeffs = entry["intrinsics"], entry["distortion_coeffs"]
        resolution = entry["resolution"]
    except KeyError as e:
        raise ValueError(f"{at}: missing {e.args[0]!r}") from None
    if model != "pinhole":
        raise ValueError(f"{at}: camera_model {model!r} is not 'pinhole', the only one the "
                         f"camera core holds")
    counts = {"radtan": 4, "none": 0}
    if dist_model not in counts:
        raise ValueError(f"{at}: distortion_model {dist_model!r} is not 'radtan' or 'none', the "
                         f"ones the camera core holds")
    fu, fv, pu, pv = common.numbers(intrinsics, (4,), f"{at}: intrinsics [fu, fv, pu, pv]")
    dist = common.numbers(coeffs, (counts[dist_model],), f"{at}: distortion_coeffs")
    w, h = common.numbers(resolution, (2,), f"{at}: resolution [w, h]")
    topic = entry.get("rostopic")
    match = _TOPIC.fullmatch(topic) if isinstance(topic, str) else None
    try:
        return Camera(match.group(1) if match else key, int(w), int(h), fu, fv, pu, pv, 0.0,
                      dist, rvec, tvec)
    except ValueError as e:
        raise ValueError(f"{at}: {e}") from None


def read(path) -> list[Camera]:
    """The rig of a camchain file (or of the folder holding one), cam0 at the identity."""
    path = common.existing(common.in_folder(path, ("camchain*.yaml", "camchain*.yml"),
                                            "Kalibr camchain file"), "Kalibr camchain file")
    chain = load_yaml(path, "Kalibr camchain file")
    if not isinstance(chain, dict) or "cam0" not in chain:
        raise ValueError(f"{path}: expected a mapping with cam0, cam1, ...")
    cameras, R, t = [], np.eye(3), np.zeros(3)
    for i in range(len(chain)):
        key = f"cam{i}"
        if key not in chain:
            break
        if i > 0:
            entry = chain[key]
            T = entry.get("T_cn_cnm1") if isinstance(entry, dict) else None
            if T is None:
                raise ValueError(f"{path}: {key}: missing 'T_cn_cnm1' (this camera from "
                                 f"cam{i - 1})")
            T = common.numbers(T, (4, 4), f"{path}: {key}: T_cn_cnm1")
            if np.any(T[3] != (0, 0, 0, 1)):
                raise ValueError(f"{path}: {key}: T_cn_cnm1's last row must be [0, 0, 0, 1]")
            R_step = common.rotation(T[:3, :3], f"{path}: {key}: T_cn_cnm1")
            R, t = compose(R_step, T[:3, 3] * common.MM_PER_M, R, t)
        cameras.append(_camera(chain[key], key, str(path), matrix_to_rodrigues(R), t))
    return common.rig(cameras, str(path))
