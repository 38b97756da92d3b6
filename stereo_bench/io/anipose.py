"""anipose's ``calibration.toml``, the file aniposelib's CameraGroup.dump writes and
CameraGroup.load reads.

One table per camera, ``[cam_<i>]``, with ``name``, ``size = [w, h]``, ``matrix`` (3x3),
``distortions`` (OpenCV's order: 5 coefficients k1, k2, p1, p2, k3 when k4..k6 are zero, else
8), ``rotation`` (Rodrigues) and ``translation``: cam_from_world, ``p_cam = R p_world + t``; and
a ``[metadata]`` table. aniposelib's lengths are those of its board (``square_length`` in the
anipose config); this module writes millimetres, the suite's unit, and says so in
``metadata.length_unit``. Reading converts a file whose ``length_unit`` is "m" or "cm" and takes
one without it to be in millimetres.

Subset: two lens models (core/lens.py), aniposelib's two camera classes (aniposelib/cameras.py):
OpenCV's pinhole (``Camera``, projecting with cv2.projectPoints) and the Kannala-Brandt lens,
written with ``fisheye = true`` and its 4 coefficients k1..k4 as ``distortions`` (``FisheyeCamera``,
which CameraGroup.load makes of a table so flagged, projecting with cv2.fisheye.projectPoints:
the rays in front of the camera). Mei's and the double sphere lens have no aniposelib class and
are refused, naming the camera. Zero skew (aniposelib passes K to cv2.projectPoints, which
ignores K[0][1], and no skew argument to cv2.fisheye.projectPoints: refused). Pixel convention:
OpenCV's, as aniposelib is OpenCV's. aniposelib's load orders the tables by sorting their names
as strings, so with more than ten cameras the indices are zero-padded (cam_00, cam_01, ...) to
keep the rig's order; reading sorts them by number.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Sequence

import numpy as np

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

from ..core.camera import Camera
from ..config.bounds import MAX_FILE_BYTES
from ..core.files import read_text, write_text
from . import common

FORMAT = "anipose calibration.toml"
FILE = "calibration.toml"
LENGTH_UNIT = "mm"
MM_PER_UNIT = {"mm": 1.0, "cm": 10.0, "m": common.MM_PER_M}
#: The lens models of aniposelib's tables (caliscope's share them): OpenCV's pinhole, and the
#: Kannala-Brandt lens as a ``fisheye = true`` table (cv2.fisheye's model).
LENSES = ("opencv", "kannala_brandt")
_TABLE = re.compile(r"cam_(\d+)")


def toml_value(value) -> str:
    """A TOML value for a string, a bool, an int, a float or nested lists of them (floats as
    Python's shortest round-trip repr, which TOML accepts)."""
    if isinstance(value, (str, bool)):
        return json.dumps(value)  # a JSON string or boolean is a TOML one too
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    return repr(float(value))


def table_distortions(camera: Camera) -> tuple[list[float], bool]:
    """(``distortions``, ``fisheye``) of a camera in aniposelib's table layout: a pinhole's
    5 coefficients k1, k2, p1, p2, k3 (8 when k4..k6 are used), or a Kannala-Brandt lens's 4
    with the fisheye flag. caliscope's tables share the layout (io/caliscope.py)."""
    if camera.model == "kannala_brandt":
        return camera.dist.tolist(), True
    return (camera.dist if np.any(camera.dist[5:]) else camera.dist[:5]).tolist(), False


def write(cameras: Sequence[Camera], out_dir) -> list[Path]:
    """Write ``calibration.toml`` in ``out_dir`` (module notes)."""
    cameras = common.rig(cameras, FORMAT, lenses=LENSES)
    for cam in cameras:
        common.refuse_skew(cam, "aniposelib (cv2.projectPoints ignores it)")
    width = len(str(len(cameras) - 1))
    lines = []
    for i, cam in enumerate(cameras):
        dist, fisheye = table_distortions(cam)
        # The flag only on a fisheye table, as aniposelib's own FisheyeCamera.get_dict writes it.
        lines += [f"[cam_{i:0{width}d}]"] + [f"{k} = {toml_value(v)}" for k, v in (
            ("name", cam.name), ("size", [cam.width, cam.height]), ("matrix", cam.K.tolist()),
            ("distortions", dist), *((("fisheye", True),) if fisheye else ()),
            ("rotation", cam.rvec.tolist()), ("translation", cam.tvec.tolist()))] + [""]
    lines += ["[metadata]", f"length_unit = {toml_value(LENGTH_UNIT)}", ""]
    return [write_text(Path(out_dir) / FILE, "\n".join(lines))]


def table_camera(table, at: str, name: str, read_pose) -> Camera:
    """A camera from a TOML table of aniposelib's layout (``matrix``, ``distortions`` in OpenCV's
    order, ``size``; with ``fisheye = true``, cv2.fisheye's k1..k4 of a Kannala-Brandt lens),
    named ``name``, its cam_from_world (rvec, tvec in mm) given by ``read_pose(table)``;
    ValueError naming ``at`` and the field otherwise. caliscope's tables share the layout
    (io/caliscope.py)."""
    if not isinstance(table, dict):
        raise ValueError(f"{at}: expected a table")
    fisheye = table.get("fisheye", False)
    if type(fisheye) is not bool:  # TOML's true or false, not a truthy string
        raise ValueError(f"{at}: fisheye = {fisheye!r}; expected true or false")
    try:
        K = common.camera_matrix(table["matrix"], f"{at}: matrix")
        dist = common.numbers(table["distortions"], None, f"{at}: distortions")
        w, h = common.numbers(table["size"], (2,), f"{at}: size [w, h]")
        rvec, tvec = read_pose(table)
    except KeyError as e:
        raise ValueError(f"{at}: missing {e.args[0]!r}") from None
    except (TypeError, ValueError) as e:
        raise ValueError(f"{at}: {e}") from None
    if fisheye and dist.size != 4:
        # aniposelib and caliscope hand these to cv2.fisheye, which takes exactly 4.
        raise ValueError(f"{at}: a fisheye camera with {dist.size} distortions; cv2.fisheye's "
                         f"model has 4, k1 k2 k3 k4")
    if dist.size > 8:
        raise ValueError(f"{at}: distortions has {dist.size} coefficients; the camera core holds "
                         f"at most 8 [k1, k2, p1, p2, k3, k4, k5, k6]")
    try:
        return Camera.from_K(name, int(w), int(h), K, dist, rvec, tvec,
                             "kannala_brandt" if fisheye else "opencv")
    except ValueError as e:
        raise ValueError(f"{at}: {e}") from None


def _camera(table, key: str, where: str, mm_per_unit: float) -> Camera:
    at = f"{where}: [{key}]"

    def pose(t):
        return (common.numbers(t["rotation"], (3,), f"{at}: rotation"),
                common.numbers(t["translation"], (3,), f"{at}: translation") * mm_per_unit)

    name = str(table.get("name", key)) if isinstance(table, dict) else key
    return table_camera(table, at, name, pose)


def read(path) -> list[Camera]:
    """The rig of a calibration.toml (or of the folder holding it), in the order of its tables'
    numbers."""
    path = common.existing(common.in_folder(path, (FILE, "*.toml"), "anipose calibration file"),
                           "anipose calibration file")
    try:
        doc = tomllib.loads(read_text(path, "anipose calibration file", MAX_FILE_BYTES))
    except tomllib.TOMLDecodeError as e:
        raise ValueError(f"{path}: not TOML ({e})") from None
    except RecursionError:
        raise ValueError(f"{path}: nested too deeply; expected an anipose calibration "
                         f"file") from None
    tables = sorted(((int(m.group(1)), k) for k in doc if (m := _TABLE.fullmatch(k))))
    if not tables:
        raise ValueError(f"{path}: no [cam_<i>] tables")
    meta = doc.get("metadata", {})
    unit = meta.get("length_unit", LENGTH_UNIT) if isinstance(meta, dict) else LENGTH_UNIT
    if unit not in MM_PER_UNIT:
        raise ValueError(f"{path}: metadata.length_unit is {unit!r}, expected one of "
                         f"{', '.join(MM_PER_UNIT)}")
    return common.rig([_camera(doc[k], k, str(path), MM_PER_UNIT[unit]) for _, k in tables],
                      str(path), lenses=LENSES)
