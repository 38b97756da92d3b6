"""OpenCV FileStorage YAML: one camera, a stereo pair, or a multi-camera rig.

Units and pixels are OpenCV's and the suite's: lengths in mm, the centre of the top-left pixel at
(0, 0), distortion [k1, k2, p1, p2, k3, k4, k5, k6]. Numbers are written as OpenCV writes doubles
(17 significant digits), so a file reads back bit for bit.

Three layouts, told apart by their keys when read (:func:`read`):

* **one camera** (:func:`write_camera`, :func:`read_camera`), the keys of OpenCV's calibration
  sample: ``camera_name``, ``image_width``, ``image_height``, ``camera_matrix`` (3x3),
  ``distortion_coefficients`` (1x8), plus ``rvec_cam_from_world`` and ``tvec_cam_from_world``
  (3x1, mm). The whole model, skew included as ``camera_matrix[0][1]``; OpenCV's own functions
  (cv2.projectPoints, cv2.undistortPoints) read that entry as 0, so a camera with skew projects
  as written only through a reader that applies the full matrix, as this one does.
* **stereo pair** (:func:`write_stereo`), the keys OpenCV's stereo_calib sample writes:
  ``M1``, ``D1``, ``M2``, ``D2`` (1x8; 1x4 for a fisheye pair), ``R``, ``T`` (camera 2 from
  camera 1, ``p2 = R p1 + T``, mm), ``E``, ``F`` and the rectification (CALIB_ZERO_DISPARITY, at camera
  1's image size) ``R1``, ``R2``, ``P1``, ``P2``, ``Q``; plus ``camera_name1/2``,
  ``image_width1/2`` and ``image_height1/2``. Two pinhole cameras are rectified by
  cv2.stereoRectify (alpha = -1); two Kannala-Brandt lenses by cv2.fisheye.stereoRectify
  (balance 0), the layout of cv2.fisheye.stereoCalibrate's output (D1, D2: its 4 coefficients)
  with ``lens_model1/2: kannala_brandt``. E and F are the pair's as pinhole cameras of matrices
  M1, M2 (for a fisheye pair, of its rays in front of the cameras). Any other pair (Mei's or
  the double sphere lens, whose rectification OpenCV computes as a rotation only or not at all,
  or two different lenses) is refused: the multi-camera file holds it. Skew is refused: the
  rectification OpenCV computes would ignore it.
* **multi-camera rig** (:func:`write_multicam`): ``camera_count`` and one map ``camera_<i>`` per
  camera with ``camera_name``, ``image_width``, ``image_height``, ``camera_matrix``,
  ``distortion_coefficients`` and ``R``, ``T``: cam_i_from_cam0 (mm), camera 0's the identity.

Lens models (core/lens.py): the one-camera and multi-camera files carry every lens, a wide one
named by ``lens_model`` (omitted for OpenCV's pinhole) with its parameters in
``distortion_coefficients``: for ``kannala_brandt`` the D of cv2.fisheye (k1..k4); for ``mei``
cv2.omnidir's xi followed by its D (k1, k2, p1, p2); for ``double_sphere`` xi, alpha (no OpenCV
function projects it). OpenCV's fisheye and omnidir functions take the skew as their own
argument (cv2.fisheye's alpha = skew / fx) or from K[0][1] (cv2.omnidir).

The stereo and multi-camera files have no world frame: a rig whose camera 0 is not at the
identity is refused unless ``rebase=True`` (then written relative to camera 0). Reading them
puts camera 0 at the identity.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from ..core.camera import Camera
from ..core.poses import matrix_to_rodrigues, skew_matrix
from ..core.files import write_text
from . import common

FORMAT = "OpenCV YAML"
STEREO_FILE = "stereo.yaml"
MULTICAM_FILE = "cameras.yaml"


# ----------------------------------------------------------------------------------------------
# FileStorage in and out
# ----------------------------------------------------------------------------------------------

def _writer():
    import cv2

    # In memory, then written atomically: a killed run leaves no half file.
    return cv2.FileStorage(".yaml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)


def _save(fs, path) -> Path:
    return write_text(path, fs.releaseAndGetString())


def open_storage(path):
    """An opened cv2.FileStorage for reading ``path``; a ValueError naming it if it is missing or
    not a FileStorage file."""
    import cv2

    path = common.existing(path, "OpenCV YAML file")
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as e:
        reason = str(getattr(e, "__cause__", None) or e).strip().splitlines()[-1]
        raise ValueError(f"{path}: not an OpenCV FileStorage file ({reason})") from None
    if not fs.isOpened():
        raise ValueError(f"{path}: not an OpenCV FileStorage file")
    return fs


def _mat(node):
    """A node's opencv-matrix, or None: OpenCV raises, rather than returning None, for a
    matrix whose data is not a plain list of numbers or does not hold rows x cols of them."""
    import cv2

    try:
        return node.mat()
    except cv2.error:
        return None


def node_matrix(node, shape: tuple, where: str) -> np.ndarray:
    """The matrix of a FileStorage node as float64 of ``shape`` (a ValueError naming ``where``
    when the node is missing or not such a matrix)."""
    if node.empty():
        raise ValueError(f"{where}: missing")
    m = _mat(node)
    if m is None:
        raise ValueError(f"{where}: expected an opencv-matrix of shape {shape}")
    return common.numbers(m, shape, where)


def node_int(node, where: str) -> int:
    if node.empty() or not node.isInt():
        raise ValueError(f"{where}: expected an integer")
    return int(node.real())


def node_string(node, default: str) -> str:
    return node.string() if not node.empty() else default


#: The lens models (core/lens.py) the one-camera and multi-camera files carry (module notes).
LENSES = ("opencv", "kannala_brandt", "mei", "double_sphere")
#: The lens models of a stereo file: a pair of one of them, each with OpenCV's rectification of
#: it (cv2.stereoRectify, cv2.fisheye.stereoRectify).
STEREO_LENSES = ("opencv", "kannala_brandt")

#: The lengths of a distortion vector OpenCV's functions accept (0: no distortion).
OPENCV_DIST_LENGTHS = (0, 4, 5, 8, 12, 14)


def node_distortion(node, where: str) -> np.ndarray:
    """Distortion coefficients of a length OpenCV takes (4, 5, 8, 12 or 14; or none), of which
    the model holds the first 8."""
    if node.empty():
        raise ValueError(f"{where}: missing")
    m = _mat(node)
    if m is None:
        raise ValueError(f"{where}: expected an opencv-matrix of coefficients")
    d = np.asarray(m, dtype=np.float64).reshape(-1)
    if d.size not in OPENCV_DIST_LENGTHS:
        raise ValueError(f"{where}: {d.size} coefficients; OpenCV takes "
                         f"{', '.join(map(str, OPENCV_DIST_LENGTHS))} ([k1, k2, p1, p2[, k3[, k4, "
                         f"k5, k6[, s1..s4[, tx, ty]]]]])")
    if d.size > 8 and np.any(d[8:]):
        raise ValueError(f"{where}: {d.size} coefficients with nonzero ones past k6 (thin prism "
                         f"or tilt); the camera model holds [k1, k2, p1, p2, k3, k4, k5, k6]")
    return common.numbers(d[:8], (min(d.size, 8),), where)


def _write_intrinsics(fs, camera: Camera, suffix: str = "", keys=("camera_matrix",
                                                                    "distortion_coefficients")):
    fs.write(f"camera_name{suffix}", camera.name)
    fs.write(f"image_width{suffix}", camera.width)
    fs.write(f"image_height{suffix}", camera.height)
    fs.write(keys[0], camera.K)
    if camera.model != "opencv":
        fs.write(f"lens_model{suffix}", camera.model)
    fs.write(keys[1], camera.dist.reshape(1, -1))


def _read_intrinsics(node_of, where: str, default_name: str, suffix: str = "",
                     keys=("camera_matrix", "distortion_coefficients"), rvec=(0, 0, 0),
                     tvec=(0, 0, 0)) -> Camera:
    """A Camera from the nodes ``node_of(key)`` of one camera's intrinsics."""
    K = common.camera_matrix(node_matrix(node_of(keys[0]), (3, 3), f"{where}: {keys[0]}"),
                             f"{where}: {keys[0]}")
    lens = node_string(node_of(f"lens_model{suffix}"), "opencv")
    if lens == "opencv":
        dist = node_distortion(node_of(keys[1]), f"{where}: {keys[1]}")
    else:
        m = _mat(node_of(keys[1]))
        if m is None:
            raise ValueError(f"{where}: {keys[1]}: expected an opencv-matrix of the {lens} "
                             f"lens's parameters")
        dist = np.asarray(m, dtype=np.float64).reshape(-1)
    name = node_string(node_of(f"camera_name{suffix}"), default_name)
    try:
        return Camera.from_K(name, node_int(node_of(f"image_width{suffix}"),
                                            f"{where}: image_width{suffix}"),
                             node_int(node_of(f"image_height{suffix}"),
                                      f"{where}: image_height{suffix}"),
                             K, dist, rvec, tvec, lens)
    except ValueError as e:
        raise ValueError(f"{where}: {e}") from None


# ----------------------------------------------------------------------------------------------
# One camera
# ----------------------------------------------------------------------------------------------

def write_camera(camera: Camera, path) -> Path:
    """Write one camera (the whole model, pose as cam_from_world) to ``path``."""
    common.rig([camera], FORMAT, lenses=LENSES)
    fs = _writer()
    _write_intrinsics(fs, camera)
    fs.write("rvec_cam_from_world", camera.rvec.reshape(3, 1))
    fs.write("tvec_cam_from_world", camera.tvec.reshape(3, 1))
    return _save(fs, path)


def read_camera(path) -> Camera:
    """The camera of a one-camera file (name: ``camera_name``, else the file's stem; pose: the
    identity when the file has none, as OpenCV's calibration sample writes none)."""
    fs = open_storage(path)
    try:
        return _camera_node(fs.getNode, str(path), Path(path).stem)
    finally:
        fs.release()


def _camera_node(node_of, where: str, default_name: str) -> Camera:
    rv, tv = node_of("rvec_cam_from_world"), node_of("tvec_cam_from_world")
    rvec = node_matrix(rv, (3,), f"{where}: rvec_cam_from_world") if not rv.empty() else (0, 0, 0)
    tvec = node_matrix(tv, (3,), f"{where}: tvec_cam_from_world") if not tv.empty() else (0, 0, 0)
    return _read_intrinsics(node_of, where, default_name, rvec=rvec, tvec=tvec)


# ----------------------------------------------------------------------------------------------
# Stereo pair
# ----------------------------------------------------------------------------------------------

def _rectify(c1: Camera, c2: Camera, R: np.ndarray, T: np.ndarray) -> tuple:
    """R1, R2, P1, P2, Q: OpenCV's rectification of a pair of one lens model."""
    import cv2

    if c1.model == "kannala_brandt":
        # Its defaults otherwise (balance 0, fov_scale 1, camera 1's image size): P1, P2 are a
        # choice of view, the rectifying rotations R1, R2 are not.
        return cv2.fisheye.stereoRectify(c1.K, c1.dist, c2.K, c2.dist, c1.size, R,
                                         T.reshape(3, 1), cv2.fisheye.CALIB_ZERO_DISPARITY)
    return cv2.stereoRectify(c1.K, c1.dist, c2.K, c2.dist, c1.size, R, T.reshape(3, 1),
                             flags=cv2.CALIB_ZERO_DISPARITY, alpha=-1)[:5]


def stereo_rectifiable(cameras: Sequence[Camera]) -> bool:
    """Whether OpenCV rectifies the pair: two cameras of one lens model of STEREO_LENSES."""
    return (len(cameras) == 2 and cameras[0].model == cameras[1].model
            and cameras[0].model in STEREO_LENSES)


def write_stereo(cameras: Sequence[Camera], path, rebase: bool = False) -> Path:
    """Write a stereo pair with OpenCV's rectification of it (module notes)."""
    where = f"the {FORMAT} stereo file"
    cameras = common.rig(cameras, where, min_count=2, lenses=STEREO_LENSES)
    if len(cameras) != 2:
        raise ValueError(f"{where}: expected 2 cameras, got {len(cameras)}")
    c1, c2 = cameras
    if not stereo_rectifiable(cameras):
        raise ValueError(f"{where}: cameras {c1.name!r} ({c1.model} lens) and {c2.name!r} "
                         f"({c2.model} lens): OpenCV rectifies a pair of one lens model; "
                         f"write_multicam holds any pair")
    for cam in cameras:
        common.refuse_skew(cam, f"the {FORMAT} stereo file (OpenCV's stereoRectify ignores it)")
    R_all, t_all = common.cam_from_cam0(cameras, where, rebase)
    R, T = R_all[1], t_all[1]
    E = skew_matrix(T) @ R
    F = np.linalg.inv(c2.K).T @ E @ np.linalg.inv(c1.K)
    R1, R2, P1, P2, Q = _rectify(c1, c2, R, T)
    fs = _writer()
    fs.writeComment("Camera 2 from camera 1: p2 = R p1 + T (mm); rectification by OpenCV's "
                    "stereoRectify at camera 1's image size")
    for i, cam in enumerate(cameras, 1):
        _write_intrinsics(fs, cam, suffix=str(i), keys=(f"M{i}", f"D{i}"))
    for key, value in (("R", R), ("T", T.reshape(3, 1)), ("E", E), ("F", F), ("R1", R1),
                       ("R2", R2), ("P1", P1), ("P2", P2), ("Q", Q)):
        fs.write(key, value)
    return _save(fs, path)


def _read_stereo(fs, where: str) -> list[Camera]:
    c1 = _read_intrinsics(fs.getNode, where, "camera1", "1", ("M1", "D1"))
    R = common.rotation(node_matrix(fs.getNode("R"), (3, 3), f"{where}: R"), f"{where}: R")
    T = node_matrix(fs.getNode("T"), (3,), f"{where}: T")
    c2 = _read_intrinsics(fs.getNode, where, "camera2", "2", ("M2", "D2"),
                          rvec=matrix_to_rodrigues(R), tvec=T)
    return common.rig([c1, c2], where, lenses=LENSES)


# ----------------------------------------------------------------------------------------------
# Multi-camera rig
# ----------------------------------------------------------------------------------------------

def write_multicam(cameras: Sequence[Camera], path, rebase: bool = False) -> Path:
    """Write N >= 2 cameras with their cam_i_from_cam0 (module notes)."""
    import cv2

    cameras = common.rig(cameras, FORMAT, min_count=2, lenses=LENSES)
    R, t = common.cam_from_cam0(cameras, f"the {FORMAT} multi-camera file", rebase)
    fs = _writer()
    fs.writeComment("R, T of camera_<i>: cam_i_from_cam0, p_i = R p_0 + T (mm)")
    fs.write("camera_count", len(cameras))
    for i, cam in enumerate(cameras):
        fs.startWriteStruct(f"camera_{i}", cv2.FILE_NODE_MAP)
        _write_intrinsics(fs, cam)
        fs.write("R", R[i])
        fs.write("T", t[i].reshape(3, 1))
        fs.endWriteStruct()
    return _save(fs, path)


def _read_multicam(fs, where: str) -> list[Camera]:
    count = node_int(fs.getNode("camera_count"), f"{where}: camera_count")
    cameras = []
    for i in range(count):
        node = fs.getNode(f"camera_{i}")
        at = f"{where}: camera_{i}"
        if node.empty() or not node.isMap():
            raise ValueError(f"{at}: missing (camera_count is {count})")
        R = common.rotation(node_matrix(node.getNode("R"), (3, 3), f"{at}: R"), f"{at}: R")
        T = node_matrix(node.getNode("T"), (3,), f"{at}: T")
        cameras.append(_read_intrinsics(node.getNode, at, f"camera{i}",
                                        rvec=matrix_to_rodrigues(R), tvec=T))
    return common.rig(cameras, where, min_count=2, lenses=LENSES)


# ----------------------------------------------------------------------------------------------
# The format's entry points
# ----------------------------------------------------------------------------------------------

def write(cameras: Sequence[Camera], out_dir, rebase: bool = False) -> list[Path]:
    """One camera: ``<name>.yaml``; a pair OpenCV rectifies (two pinhole cameras, or two
    Kannala-Brandt lenses): ``stereo.yaml``; any other pair, and more: ``cameras.yaml``."""
    cameras = common.rig(cameras, FORMAT, lenses=LENSES)
    out_dir = Path(out_dir)
    if len(cameras) == 1:
        return [write_camera(cameras[0], out_dir / f"{cameras[0].name}.yaml")]
    if stereo_rectifiable(cameras):
        return [write_stereo(cameras, out_dir / STEREO_FILE, rebase)]
    return [write_multicam(cameras, out_dir / MULTICAM_FILE, rebase)]


def read(path) -> list[Camera]:
    """The cameras of any of the three layouts, told apart by their keys (``path``: the file,
    or a folder holding one stereo.yaml or cameras.yaml)."""
    if Path(path).is_dir():
        found = [Path(path) / f for f in (STEREO_FILE, MULTICAM_FILE) if (Path(path) / f).is_file()]
        if len(found) != 1:
            raise ValueError(f"{path}: expected one of {STEREO_FILE} or {MULTICAM_FILE} in this "
                             f"folder, found {len(found)}")
        path = found[0]
    fs = open_storage(path)
    where = str(path)
    try:
        if not fs.getNode("camera_count").empty():
            return _read_multicam(fs, where)
        if not fs.getNode("M1").empty():
            return _read_stereo(fs, where)
        if not fs.getNode("camera_matrix").empty():
            return [_camera_node(fs.getNode, where, Path(path).stem)]
        raise ValueError(f"{where}: expected 'camera_matrix' (one camera), 'M1' (a stereo pair) "
                         f"or 'camera_count' (a multi-camera rig)")
    finally:
        fs.release()
