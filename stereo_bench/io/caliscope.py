"""Caliscope's ``camera_array.toml``, the file caliscope's CameraArray.to_toml writes and
CameraArray.from_toml reads (and, read only, the ``config.toml`` of its older sessions).

One table per camera, ``[cameras.<cam_id>]``, with ``cam_id``, ``size = [w, h]``, ``matrix``
(3x3), ``distortions`` (OpenCV's order, 5 coefficients k1, k2, p1, p2, k3; 8 when k4..k6 are
not zero), ``rotation`` (Rodrigues; a 3x3 matrix in older files) and ``translation``:
cam_from_world, ``p_cam = R p_world + t`` (caliscope's ``normalized_projection_matrix`` is
[R | t]), in metres, caliscope's unit (its board's square size is set in centimetres and used
in metres). Older sessions keep the same fields in ``config.toml`` under ``[cam_<id>]`` with the
3x3 rotation; they are read alike.

Cameras are named ``cam_<id>``, as caliscope names its videos (``cam_0.mp4``) and its aniposelib
export; a written file numbers the cameras in the rig's order (caliscope keeps no names).

Subset: two lens models (core/lens.py), caliscope's two (CameraData.fisheye): OpenCV's pinhole
(``fisheye = false``, projected by caliscope.core.reprojection.project_points with
cv2.projectPoints) and the Kannala-Brandt lens (``fisheye = true`` with its 4 coefficients
k1..k4 as ``distortions``, projected with cv2.fisheye.projectPoints, as caliscope's
calibrate_intrinsics fits it with cv2.fisheye.calibrate); Mei's and the double sphere lens have
none and are refused, naming the camera. Zero skew (caliscope's matrices come from
cv2.calibrateCamera and cv2.fisheye.calibrate, which fit none), images as recorded (a camera
with a ``rotation_count``, images turned by quarter turns before detection, is refused when
read: its matrix is of the turned image). A camera whose extrinsics are not yet calibrated has
no rotation and translation: a file whose cameras all lack them holds intrinsics only (read at
the identity pose, for their intrinsics: ``calibrate-images --intrinsics``); a file where some
lack them is refused, naming them. Pixel convention: OpenCV's.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Sequence

import numpy as np

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

from ..core.camera import Camera
from ..core.poses import matrix_to_rodrigues
from ..config.bounds import MAX_FILE_BYTES
from ..core.files import read_text, write_text
from . import common
from .anipose import LENSES, table_camera, table_distortions, toml_value

FORMAT = "caliscope camera_array.toml"
FILE = "camera_array.toml"
LEGACY_FILE = "config.toml"
_LEGACY_TABLE = re.compile(r"cam_(\d+)")


def write(cameras: Sequence[Camera], out_dir) -> list[Path]:
    """Write ``camera_array.toml`` in ``out_dir`` (module notes)."""
    cameras = common.rig(cameras, FORMAT, lenses=LENSES)
    lines = []
    for i, cam in enumerate(cameras):
        common.refuse_skew(cam, "caliscope (its matrices come from cv2.calibrateCamera)")
        dist, fisheye = table_distortions(cam)
        lines += [f"[cameras.{i}]"] + [f"{k} = {toml_value(v)}" for k, v in (
            ("cam_id", i), ("size", [cam.width, cam.height]), ("rotation_count", 0),
            ("matrix", cam.K.tolist()), ("distortions", dist),
            ("translation", (cam.tvec / common.MM_PER_M).tolist()),
            ("rotation", cam.rvec.tolist()), ("fisheye", fisheye))] + [""]
    return [write_text(Path(out_dir) / FILE, "\n".join(lines))]


def _camera(table, key: str, where: str) -> tuple[Camera, bool]:
    """One camera of the file and whether it has a pose."""
    at = f"{where}: [{key}]"
    if isinstance(table, dict) and table.get("rotation_count", 0):
        raise ValueError(f"{at}: rotation_count {table['rotation_count']!r}: its images were "
                         f"turned by quarter turns before detection, so its matrix is of the "
                         f"turned image; expected 0")
    posed = isinstance(table, dict) and table.get("rotation") is not None and \
        table.get("translation") is not None

    def pose(t):
        if not posed:
            return np.zeros(3), np.zeros(3)
        rotation = np.asarray(t["rotation"], dtype=object)
        rvec = (matrix_to_rodrigues(common.rotation(t["rotation"], f"{at}: rotation"))
                if rotation.shape == (3, 3)
                else common.numbers(t["rotation"], (3,), f"{at}: rotation"))
        return rvec, common.numbers(t["translation"], (3,), f"{at}: translation") * common.MM_PER_M

    cam_id = (table.get("cam_id", key.rsplit(".", 1)[-1].removeprefix("cam_"))
              if isinstance(table, dict) else key)
    try:
        name = f"cam_{int(cam_id)}"
    except (TypeError, ValueError):
        raise ValueError(f"{at}: cam_id {cam_id!r}: expected an integer") from None
    return table_camera(table, at, name, pose), posed


def read(path) -> list[Camera]:
    """The cameras of a camera_array.toml or an older session's config.toml (or of the folder
    holding one), in the order of their ids."""
    what = "caliscope camera array"
    path = common.existing(common.in_folder(path, (FILE, LEGACY_FILE), what), what)
    try:
        doc = tomllib.loads(read_text(path, what, MAX_FILE_BYTES))
    except tomllib.TOMLDecodeError as e:
        raise ValueError(f"{path}: not TOML ({e})") from None
    except RecursionError:
        raise ValueError(f"{path}: nested too deeply; expected a {what}") from None
    if isinstance(doc.get("cameras"), dict):
        tables = {f"cameras.{k}": v for k, v in doc["cameras"].items()}
    else:
        tables = {k: v for k, v in doc.items() if _LEGACY_TABLE.fullmatch(k)}
    numbered = []
    for key in tables:
        try:
            numbered.append((int(key.rsplit(".", 1)[-1].removeprefix("cam_")), key))
        except ValueError:
            raise ValueError(f"{path}: [{key}]: expected a camera id (an integer)") from None
    if not numbered:
        raise ValueError(f"{path}: no [cameras.<id>] (or [cam_<id>]) tables")
    read_ = [_camera(tables[k], k, str(path)) for _, k in sorted(numbered)]
    unposed = [c.name for c, posed in read_ if not posed]
    if unposed and len(unposed) < len(read_):
        raise ValueError(f"{path}: camera(s) {', '.join(unposed)} have no rotation and "
                         f"translation while the others have: expected every camera posed "
                         f"(a rig) or none (intrinsics only)")
    return common.rig([c for c, _ in read_], str(path), posed=not unposed, lenses=LENSES)
