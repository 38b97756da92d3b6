"""Kalibr's camera chain, ``camchain.yaml`` (the layout of kalibr_calibrate_cameras' output, read
by Kalibr's ConfigReader.CameraChainParameters).

Per camera ``cam<i>``: ``camera_model``, ``intrinsics``, ``distortion_model``,
``distortion_coeffs``, ``resolution: [w, h]``, ``rostopic: /<name>/image_raw`` (the only place a
camera's name fits; read back from it), ``cam_overlaps`` (every other camera: the suite's rigs
all observe one target; edit it for a rig whose views are disjoint) and, from cam1 on,
``T_cn_cnm1``: the 4x4 transform of this camera from the previous one (``p_n = T p_{n-1}``), in
metres, Kalibr's unit (the suite's millimetres are divided by 1000 on writing and multiplied back
on reading).

Subset: one Kalibr model per lens model of the camera core (core/lens.py), each checked against
Kalibr's C++ camera classes (aslam_cv/aslam_cameras/include/aslam/cameras/implementation/) and
written with the intrinsics order of its Python writer (kalibr_camera_calibration/CameraUtils.py,
saveChainParametersYaml):

    lens            camera_model-distortion_model  intrinsics                   distortion_coeffs
    opencv          pinhole-radtan                 [fu, fv, pu, pv]             [k1, k2, r1, r2]
    kannala_brandt  pinhole-equidistant            [fu, fv, pu, pv]             [k1, k2, k3, k4]
    mei             omni-radtan                    [xi, fu, fv, pu, pv]         [k1, k2, r1, r2]
    double_sphere   ds-none                        [xi, alpha, fu, fv, pu, pv]  []

radtan is OpenCV's k1, k2, p1, p2, in that order and with the same formula (k3..k6 are refused);
equidistant is cv2.fisheye's theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 +
k4 theta^8) on theta = atan(r) of the pinhole point (X/Z, Y/Z); omni is Mei's projection from
(0, 0, -xi) followed by radtan; ds is Usenko et al.'s double sphere. No model has skew (refused).
Kalibr's pinhole projection divides by Z, so its equidistant lens projects only points in front
of the camera, where the camera core's Kannala-Brandt lens also sees beyond 90 degrees: the same
parameters, the same pixels over Kalibr's half of the view. mrcal's mrcal-from-kalibr converts
pinhole-radtan and pinhole-none only.
Read: those, and pinhole-none (opencv without distortion) and omni-none (mei without it); any
other (eucm, fov, ...) is refused with a ValueError naming the camera.

Pixel convention: OpenCV's (top-left pixel centre at (0, 0)): Kalibr fits its models to the
corners OpenCV's detectors give, unshifted, and mrcal's Kalibr converters copy pu, pv unchanged.

The chain has no world frame: a rig whose camera 0 is not at the identity is refused unless
``rebase=True``. Reading puts cam0 at the identity.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Sequence

import numpy as np
import yaml
from ..core.camera import Camera
from ..core.lens import lens_model
from ..core.poses import compose, invert, matrix_to_rodrigues
from ..config.yaml_reader import load_yaml
from ..core.files import write_text
from . import common

FORMAT = "Kalibr camchain"
FILE = "camchain.yaml"
_TOPIC = re.compile(r"/(.+)/image_raw")
_NAME = re.compile(r"[^/\s]+")

#: Kalibr's (camera_model, distortion_model) of each lens written (module notes).
KALIBR_MODELS = {"opencv": ("pinhole", "radtan"), "kannala_brandt": ("pinhole", "equidistant"),
                 "mei": ("omni", "radtan"), "double_sphere": ("ds", "none")}
#: Every pair read: (lens, how many of the lens's parameters lead the intrinsics before fu fv
#: pu pv, how many distortion coefficients follow them in the lens's parameter vector).
#: Kalibr puts omni's xi and ds's xi, alpha first in ``intrinsics``, where the camera core puts
#: them first in ``dist``; a model without distortion reads as its lens with zeros.
READ_MODELS = {("pinhole", "radtan"): ("opencv", 0, 4), ("pinhole", "none"): ("opencv", 0, 0),
               ("pinhole", "equidistant"): ("kannala_brandt", 0, 4),
               ("omni", "radtan"): ("mei", 1, 4), ("omni", "none"): ("mei", 1, 0),
               ("ds", "none"): ("double_sphere", 2, 0)}
LENSES = tuple(KALIBR_MODELS)


def _transform(R: np.ndarray, t_mm: np.ndarray) -> list[list[float]]:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t_mm / common.MM_PER_M
    return T.tolist()


def _entry(cam: Camera) -> dict:
    """The model keys of one camera (module notes)."""
    model, dist_model = KALIBR_MODELS[cam.model]
    lead, count = READ_MODELS[(model, dist_model)][1:]
    if cam.model == "opencv":
        common.refuse_distortion(cam, "Kalibr's radtan model", 4)
    return {"camera_model": model,
            "intrinsics": cam.dist[:lead].tolist() + [cam.fx, cam.fy, cam.cx, cam.cy],
            "distortion_model": dist_model,
            "distortion_coeffs": cam.dist[lead:lead + count].tolist()}


def write(cameras: Sequence[Camera], out_dir, rebase: bool = False) -> list[Path]:
    """Write ``camchain.yaml`` in ``out_dir`` (module notes)."""
    cameras = common.rig(cameras, FORMAT, lenses=LENSES)
    for cam in cameras:
        common.refuse_skew(cam, "Kalibr")  # none of its camera models has one
        common.refuse_name(cam, FORMAT, "characters other than '/' and whitespace (it becomes "
                           "the rostopic /<name>/image_raw)", _NAME)
    R, t = common.cam_from_cam0(cameras, FORMAT, rebase)
    chain = {}
    for i, cam in enumerate(cameras):
        entry = {
            **_entry(cam),
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
    if not isinstance(model, str) or not isinstance(dist_model, str) or \
            (model, dist_model) not in READ_MODELS:
        raise ValueError(f"{at}: camera_model {model!r} with distortion_model {dist_model!r} is "
                         f"not one of {', '.join('-'.join(k) for k in READ_MODELS)} (the ones "
                         f"the camera core holds)")
    lens, lead, count = READ_MODELS[(model, dist_model)]
    names = lens_model(lens).param_names
    p = common.numbers(intrinsics, (lead + 4,), f"{at}: intrinsics "
                       f"[{', '.join(names[:lead] + ('fu', 'fv', 'pu', 'pv'))}]")
    coeffs = common.numbers(coeffs, (count,), f"{at}: distortion_coeffs of {dist_model}")
    dist = np.zeros(len(names))
    dist[:lead], dist[lead:lead + count] = p[:lead], coeffs
    fu, fv, pu, pv = p[lead:]
    w, h = common.numbers(resolution, (2,), f"{at}: resolution [w, h]")
    topic = entry.get("rostopic")
    match = _TOPIC.fullmatch(topic) if isinstance(topic, str) else None
    try:
        return Camera(match.group(1) if match else key, int(w), int(h), fu, fv, pu, pv, 0.0,
                      dist, rvec, tvec, lens)
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
    return common.rig(cameras, str(path), lenses=LENSES)
