"""EasyMocap's camera files, ``intri.yml`` and ``extri.yml`` (OpenCV FileStorage YAML), with the
keys of EasyMocap's own reader and writer (easymocap/mytools/camera_utils.py: read_camera,
write_camera).

``intri.yml``: ``names`` (the cameras, in order) and per camera ``K_<name>`` (3x3),
``dist_<name>`` (1x5: k1, k2, p1, p2, k3), ``H_<name>``, ``W_<name>`` (image size).
``extri.yml``: ``names`` and per camera ``R_<name>`` (Rodrigues 3x1, what the reader uses),
``Rot_<name>`` (the same rotation as a 3x3 matrix) and ``T_<name>`` (3x1): cam_from_world,
``p_cam = R p_world + T``, with T in metres as EasyMocap requires (the suite's millimetres are
divided by 1000 on writing and multiplied back on reading).

Subset: zero skew (EasyMocap projects through OpenCV, which ignores K[0][1]: refused) and at most
5 distortion coefficients (EasyMocap's write_intri accepts 4 or 5: k4..k6 are refused). Names are
letters, digits, ``_`` and ``-`` (they become FileStorage keys, and EasyMocap cuts a name at its
first '.'). OpenCV's pinhole lens only: EasyMocap's cameras have no lens flag and project through
cv2.projectPoints (its dist read as k1, k2, p1, p2[, k3]), so a fisheye or omnidirectional lens
(core/lens.py) is refused, naming the camera, rather than written to be read back as a pinhole.
Pixel convention: OpenCV's, as EasyMocap uses OpenCV throughout. A file without
``H_``/``W_`` (EasyMocap makes them optional) is refused: the camera core needs an image size.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Sequence


from ..core.camera import Camera
from ..core.poses import matrix_to_rodrigues
from ..core.files import write_text
from . import common
from .opencv_yaml import node_distortion, node_int, node_matrix, open_storage

FORMAT = "EasyMocap"
FILES = ("intri.yml", "extri.yml")
_NAME = re.compile(r"[A-Za-z0-9_-]+")


def write(cameras: Sequence[Camera], out_dir) -> list[Path]:
    """Write ``intri.yml`` and ``extri.yml`` in ``out_dir`` (module notes)."""
    import cv2

    cameras = common.rig(cameras, FORMAT)
    for cam in cameras:
        common.refuse_skew(cam, FORMAT)
        common.refuse_distortion(cam, f"{FORMAT}'s dist", 5)
        common.refuse_name(cam, FORMAT, "letters, digits, '_' and '-' (FileStorage keys)", _NAME)
    # In memory, then written atomically (as opencv_yaml does).
    intri, extri = (cv2.FileStorage(".yml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
                    for _ in FILES)
    names = [cam.name for cam in cameras]
    intri.write("names", names)
    extri.write("names", names)
    extri.writeComment("cam_from_world: p_cam = Rot p_world + T, T in metres")
    for cam in cameras:
        intri.write(f"K_{cam.name}", cam.K)
        intri.write(f"dist_{cam.name}", cam.dist[:5].reshape(1, 5))
        intri.write(f"H_{cam.name}", cam.height)
        intri.write(f"W_{cam.name}", cam.width)
        extri.write(f"R_{cam.name}", cam.rvec.reshape(3, 1))
        extri.write(f"Rot_{cam.name}", cam.R)
        extri.write(f"T_{cam.name}", (cam.tvec / common.MM_PER_M).reshape(3, 1))
    out_dir = Path(out_dir)
    return [write_text(out_dir / f, fs.releaseAndGetString())
            for f, fs in zip(FILES, (intri, extri))]


def _names(fs, where: str) -> list[str]:
    """The ``names`` list, read as EasyMocap reads it (a number-like unquoted name as digits)."""
    node = fs.getNode("names")
    if node.empty() or not node.isSeq() or node.size() == 0:
        raise ValueError(f"{where}: names: expected a list of camera names")
    names = []
    for i in range(node.size()):
        item = node.at(i)
        names.append(item.string() if item.isString() else str(int(item.real())))
    return names


def read(path) -> list[Camera]:
    """The rig of an EasyMocap folder (``path``: the folder, or its intri.yml or extri.yml)."""
    folder = Path(path)
    if folder.is_file():
        folder = folder.parent
    intri_path, extri_path = (folder / f for f in FILES)
    intri, extri = open_storage(intri_path), open_storage(extri_path)
    try:
        names = _names(intri, str(intri_path))
        cameras = []
        for name in names:
            at_i, at_e = f"{intri_path}: camera {name!r}", f"{extri_path}: camera {name!r}"
            K = common.camera_matrix(node_matrix(intri.getNode(f"K_{name}"), (3, 3),
                                                 f"{at_i}: K_{name}"), f"{at_i}: K_{name}")
            dist = node_distortion(intri.getNode(f"dist_{name}"), f"{at_i}: dist_{name}")
            height = node_int(intri.getNode(f"H_{name}"), f"{at_i}: H_{name} (image height)")
            width = node_int(intri.getNode(f"W_{name}"), f"{at_i}: W_{name} (image width)")
            rnode = extri.getNode(f"R_{name}")
            if not rnode.empty():
                rvec = node_matrix(rnode, (3,), f"{at_e}: R_{name}")
            else:  # some writers give only the matrix
                Rot = node_matrix(extri.getNode(f"Rot_{name}"), (3, 3),
                                  f"{at_e}: R_{name} or Rot_{name}")
                rvec = matrix_to_rodrigues(common.rotation(Rot, f"{at_e}: Rot_{name}"))
            T = node_matrix(extri.getNode(f"T_{name}"), (3,), f"{at_e}: T_{name}")
            try:
                cameras.append(Camera.from_K(name, width, height, K, dist, rvec,
                                             T * common.MM_PER_M))
            except ValueError as e:
                raise ValueError(f"{at_i}: {e}") from None
        return common.rig(cameras, str(folder))
    finally:
        intri.release()
        extri.release()
