"""multical's ``calibration.json``, the file ``multical calibrate`` writes (multical/io/
export_calib.py) and multical's ``load_calibration`` reads (multical/io/import_calib.py; its
FORMAT.md describes it).

``cameras``: one object per camera, keyed by its name (multical's camera folder), in the rig's
order, with ``model`` (multical's name of OpenCV's distortion model: "standard" for the 5
coefficients k1 k2 p1 p2 k3 of cv2.calibrateCamera, "rational" for 8, + k4 k5 k6),
``image_size`` [w, h], ``K`` (3x3) and ``dist`` (OpenCV's order, written as cv2 returns it, a
1 x n row). ``camera_poses``: each camera's cam_from_world, ``p_cam = R p_world + T`` with ``R``
3x3 and ``T`` (3): under the camera's own name for an absolute pose, or under
``<camera>_to_<master>`` relative to a master camera whose own pose is the identity (what
multical calibrate writes, its first camera the master; despite its name, the entry holds the
camera's cam_from_master). A file without ``camera_poses`` (``multical intrinsic``'s) holds
intrinsics only: its cameras are read at the identity pose. ``image_sets`` (the image files of
each frame) is read past and not written.

Units: multical has none of its own; its lengths are those of its boards.yaml, in metres in
its documentation and examples (``square_length: 0.025``). This module writes metres and reads
a file as metres (the file cannot say otherwise). Pixel convention: OpenCV's (multical is
OpenCV's: cv2.calibrateCamera, cv2.projectPoints), the top-left pixel's centre at (0, 0).

Subset: OpenCV's pinhole lens with zero skew, 5 coefficients (8 when k4..k6 are not zero).
Refused, naming the camera and the parameter: skew (multical projects with cv2.projectPoints,
which reads no K[0][1]); a lens of core/lens.py other than OpenCV's; a name with ``_to_`` in it
(multical's reader splits pose keys there). Read also: 12 or 14 coefficients (its
"thin_prism" and "tilted" models) when the terms past k6 are zero; not read: 4 coefficients,
which multical writes for cv2.fisheye's k1..k4 (``--isFisheye``) under the same model name
"standard" while its own reader takes them for a pinhole's k1 k2 p1 p2 (so the file is
ambiguous), and a relative pose to a camera not at the identity (multical composes such
chains in an order that is not a pose's; its files never hold one).
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Sequence

import numpy as np

from ..config.bounds import MAX_FILE_BYTES
from ..core.camera import DIST_NAMES, Camera
from ..core.files import UnreadableFileError, read_text, write_text
from ..core.poses import matrix_to_rodrigues
from . import common

FORMAT = "multical calibration.json"
FILE = "calibration.json"
#: multical's models (multical/camera.py Camera.model) by their number of coefficients.
MODELS = {5: "standard", 8: "rational", 12: "thin_prism", 14: "tilted"}
#: The names of the coefficients past k6 in the thin-prism and tilted models, OpenCV's order.
EXTRA_NAMES = ("s1", "s2", "s3", "s4", "tau_x", "tau_y")
SEPARATOR = "_to_"
_NO_SEPARATOR = re.compile(r"(?:(?!_to_).)*", re.DOTALL)  # a name without the separator


def write(cameras: Sequence[Camera], out_dir) -> list[Path]:
    """Write ``calibration.json`` in ``out_dir`` (module notes): camera 0 as the master with the
    others ``<camera>_to_<camera 0>`` when camera 0 is at the identity, as multical calibrate
    writes it; else every camera's absolute pose, which multical's reader takes too."""
    cameras = common.rig(cameras, FORMAT)
    for cam in cameras:
        common.refuse_skew(cam, "multical (it projects with cv2.projectPoints)")
        common.refuse_name(cam, FORMAT, f"characters without {SEPARATOR!r} (multical splits "
                                        f"its pose keys there)", _NO_SEPARATOR)
    doc = {"cameras": {}, "camera_poses": {}}
    for cam in cameras:
        dist = cam.dist if np.any(cam.dist[5:]) else cam.dist[:5]
        doc["cameras"][cam.name] = {"model": MODELS[dist.size], "image_size": list(cam.size),
                                    "K": cam.K.tolist(), "dist": [dist.tolist()]}
    master = cameras[0]
    relative = not (np.any(master.rvec) or np.any(master.tvec))
    for cam in cameras:
        key = cam.name if (not relative or cam is master) else \
            f"{cam.name}{SEPARATOR}{master.name}"
        doc["camera_poses"][key] = {"R": cam.R.tolist(),
                                    "T": (cam.tvec / common.MM_PER_M).tolist()}
    return [write_text(Path(out_dir) / FILE, json.dumps(doc, indent=2) + "\n")]


def looks_like(path) -> bool:
    """Whether a JSON file is multical's: an object whose ``cameras`` is an object of cameras
    with ``K`` (what io.guess_format asks of a .json before taking it for OpenCV's)."""
    try:
        doc = json.loads(read_text(path, FORMAT, MAX_FILE_BYTES))
    except (OSError, ValueError, RecursionError):
        return False
    cams = doc.get("cameras") if isinstance(doc, dict) else None
    return isinstance(cams, dict) and bool(cams) and all(
        isinstance(c, dict) and "K" in c for c in cams.values())


def _camera(name: str, entry, at: str) -> Camera:
    if not isinstance(entry, dict):
        raise ValueError(f"{at}: expected an object")
    try:
        K = common.camera_matrix(entry["K"], f"{at}: K")
        w, h = common.numbers(entry["image_size"], (2,), f"{at}: image_size [w, h]")
        dist = common.numbers(entry["dist"], None, f"{at}: dist")
    except KeyError as e:
        raise ValueError(f"{at}: missing {e.args[0]!r}") from None
    model = entry.get("model", "standard")
    if model not in MODELS.values():
        raise ValueError(f"{at}: model {model!r}; expected one of {', '.join(MODELS.values())}")
    if w != int(w) or h != int(h):
        raise ValueError(f"{at}: image_size {[w, h]}; expected whole pixels")
    if K[0, 1] != 0:
        raise ValueError(f"{at}: skew K[0][1] = {float(K[0, 1])!r}; multical projects with "
                         f"cv2.projectPoints, which reads none (expected 0)")
    if dist.size == 4:
        raise ValueError(f"{at}: dist has 4 coefficients, which multical writes for cv2.fisheye's "
                         f"k1..k4 (--isFisheye) while its reader takes them for k1 k2 p1 p2; "
                         f"ambiguous, expected 5, 8, 12 or 14")
    if dist.size not in MODELS:
        raise ValueError(f"{at}: dist has {dist.size} coefficients; expected 5, 8, 12 or 14 "
                         f"(OpenCV's models)")
    extra = np.flatnonzero(dist[8:])
    if extra.size:
        i = int(extra[0])
        raise ValueError(f"{at}: {EXTRA_NAMES[i]} = {float(dist[8 + i])!r} is not 0; the camera "
                         f"core holds {', '.join(DIST_NAMES)} only")
    try:
        return Camera.from_K(name, int(w), int(h), K, dist[:8])
    except ValueError as e:
        raise ValueError(f"{at}: {e}") from None


def _pose(entry, at: str) -> np.ndarray:
    """A 4x4 cam_from_world (T in mm) of a camera_poses entry."""
    if not isinstance(entry, dict):
        raise ValueError(f"{at}: expected an object with R and T")
    try:
        R = common.rotation(entry["R"], f"{at}: R")
        T = common.numbers(entry["T"], (3,), f"{at}: T")
    except KeyError as e:
        raise ValueError(f"{at}: missing {e.args[0]!r}") from None
    with np.errstate(over="ignore"):
        T = T * common.MM_PER_M
    if not np.all(np.isfinite(T)):
        raise ValueError(f"{at}: T = {entry['T']!r} m is too large to hold in mm")
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = R, T
    return M


def _poses(entries, names: list[str], where: str) -> dict[str, np.ndarray]:
    if not isinstance(entries, dict):
        raise ValueError(f"{where}: camera_poses: expected an object")
    absolute, relative = {}, {}
    for key, entry in entries.items():
        at = f"{where}: camera_poses[{key!r}]"
        if key in names:
            absolute[key] = _pose(entry, at)
            continue
        parts = key.split(SEPARATOR)  # as multical's import_pose_graph splits it
        if len(parts) != 2 or not set(parts) <= set(names):
            raise ValueError(f"{at}: expected a camera's name or <camera>{SEPARATOR}<camera> "
                             f"of the cameras {names}")
        if parts[0] in relative:
            raise ValueError(f"{at}: a second relative pose of camera {parts[0]!r}")
        relative[parts[0]] = (parts[1], _pose(entry, at), at)
    poses = dict(absolute)
    for name, (target, M, at) in relative.items():
        if name in absolute:
            raise ValueError(f"{at}: camera {name!r} has an absolute pose too")
        base = absolute.get(target)
        if base is None or not np.allclose(base, np.eye(4), rtol=0, atol=1e-9):
            raise ValueError(f"{at}: relative to camera {target!r}, whose own pose is not the "
                             f"identity; expected the master camera at the identity (multical "
                             f"writes no other chain)")
        poses[name] = M
    missing = [n for n in names if n not in poses]
    if missing:
        raise ValueError(f"{where}: camera_poses: no pose for camera(s) {', '.join(missing)}")
    return poses


def read(path) -> list[Camera]:
    """The rig of a multical calibration.json (or of the folder holding it), in the order of
    its cameras."""
    path = common.existing(common.in_folder(path, (FILE, "*.json"), "multical calibration"),
                           "multical calibration")
    try:
        doc = json.loads(read_text(path, FORMAT, MAX_FILE_BYTES))
    except UnreadableFileError:
        raise
    except ValueError as e:
        raise ValueError(f"{path}: not JSON ({e})") from None
    except RecursionError:
        raise ValueError(f"{path}: nested too deeply; expected a {FORMAT}") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("cameras"), dict) or \
            not doc["cameras"]:
        raise ValueError(f"{path}: expected an object with 'cameras' (a {FORMAT})")
    names = list(doc["cameras"])
    cams = [_camera(n, doc["cameras"][n], f"{path}: cameras[{n!r}]") for n in names]
    if "camera_poses" not in doc:  # intrinsics only (multical intrinsic)
        return common.rig(cams, str(path), posed=False)
    poses = _poses(doc["camera_poses"], names, str(path))
    return common.rig([c.with_params(rvec=matrix_to_rodrigues(poses[c.name][:3, :3]),
                                     tvec=poses[c.name][:3, 3]) for c in cams], str(path))
