"""COLMAP's text model of a rig snapshot: ``cameras.txt``, ``images.txt``, ``points3D.txt``.

Subset written: cameras with zero skew (COLMAP's models have none; refused otherwise), each as
model OPENCV (fx fy cx cy k1 k2 p1 p2) when k3..k6 are all zero, else FULL_OPENCV (fx fy cx cy
k1 k2 p1 p2 k3 k4 k5 k6): the same distortion formula as the camera core's. One image per
camera, named after the camera (so names are non-empty and without whitespace), holding the
camera's cam_from_world as COLMAP's ``QW QX QY QZ TX TY TZ`` (a unit quaternion with w >= 0 and
the translation in mm: COLMAP's models have no unit of their own), and no 2D points; an empty
``points3D.txt``. Camera and image ids are 1..N in the rig's order. The three files are the
layout every COLMAP version reads (COLMAP 3.12 and later add rigs.txt and frames.txt when they
write, and build a trivial rig per camera when they read a model without them).

Pixel convention: COLMAP puts the centre of the top-left pixel at (0.5, 0.5), OpenCV and the
suite at (0, 0); cx and cy are shifted by ``PIXEL_SHIFT`` = +0.5 on writing and -0.5 on reading
(the conversions of colmap_ref.py, the suite's COLMAP reference, used here).

A Kannala-Brandt lens (cv2.fisheye's, core/lens.py) is written and read as OPENCV_FISHEYE
(fx fy cx cy k1 k2 k3 k4); the other wide-angle lenses have no COLMAP model and are refused.

Read: any folder in that layout (``points3D.txt`` is not needed), or a pycolmap.Reconstruction
(:func:`from_reconstruction`). Models SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV,
FULL_OPENCV and OPENCV_FISHEYE are read exactly (each is a special case of the camera core's);
any other model, a
camera with no image or with more than one, is refused with a ValueError naming it.
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Sequence

import numpy as np

from ..core.camera import DIST_NAMES, Camera
from ..core.lens import lens_model
from ..core.poses import matrix_to_rodrigues
from ..core.files import read_text, write_text
from . import common

FORMAT = "COLMAP"
FILES = ("cameras.txt", "images.txt", "points3D.txt")
_NAME = re.compile(r"\S+")

#: COLMAP's models that are special cases of the camera core's, by their parameters' names
#: (``f`` is fx = fy), from COLMAP's src/colmap/sensor/models.h.
MODELS = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k1"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    "FULL_OPENCV": ("fx", "fy", "cx", "cy") + DIST_NAMES,
    "OPENCV_FISHEYE": ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4"),
}
#: The camera core's lens model (core/lens.py) of each, OpenCV's pinhole unless named here.
#: COLMAP's OPENCV_FISHEYE is cv2.fisheye's Kannala-Brandt projection.
LENSES = {"OPENCV_FISHEYE": "kannala_brandt"}
CARRIED_LENSES = ("opencv", "kannala_brandt")


PIXEL_SHIFT = 0.5  # COLMAP pixel coordinate = OpenCV pixel coordinate + PIXEL_SHIFT


def opencv_to_colmap_pixels(uv: np.ndarray) -> np.ndarray:
    """Pixels (..., 2) in OpenCV's convention -> COLMAP's (+PIXEL_SHIFT on u and v)."""
    return np.asarray(uv, dtype=np.float64) + PIXEL_SHIFT


def colmap_model(camera: Camera) -> tuple[str, np.ndarray]:
    """(COLMAP model name, params) of a project Camera, principal point in COLMAP's convention.

    OPENCV when k3..k6 are zero, else FULL_OPENCV; OPENCV_FISHEYE for a Kannala-Brandt lens.
    Raises ValueError for skew != 0 or another lens model.
    """
    if camera.skew != 0:
        raise ValueError(f"camera {camera.name!r}: skew {camera.skew!r} is not 0; COLMAP's "
                         f"OPENCV, FULL_OPENCV and OPENCV_FISHEYE models have no skew")
    pinhole = [camera.fx, camera.fy, camera.cx + PIXEL_SHIFT, camera.cy + PIXEL_SHIFT]
    d = camera.dist
    if camera.model == "kannala_brandt":
        return "OPENCV_FISHEYE", np.array(pinhole + d.tolist())
    if camera.model != "opencv":
        raise ValueError(f"camera {camera.name!r}: COLMAP has no model of the {camera.model} "
                         f"lens; it carries {' and '.join(CARRIED_LENSES)} lenses")
    if not np.any(d[4:]):
        return "OPENCV", np.array(pinhole + d[:4].tolist())
    return "FULL_OPENCV", np.array(pinhole + d.tolist())


def from_colmap_camera(colmap_camera, camera: Camera) -> Camera:
    """The project Camera ``camera`` with the intrinsics of a pycolmap.Camera (pose unchanged)."""
    p = np.asarray(colmap_camera.params, dtype=np.float64)
    dist = np.zeros(len(camera.dist))
    dist[: len(p) - 4] = p[4:]
    return camera.with_params(fx=float(p[0]), fy=float(p[1]), cx=float(p[2]) - PIXEL_SHIFT,
                              cy=float(p[3]) - PIXEL_SHIFT, dist=dist)


def from_rigid3d(pose) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) of a pycolmap Rigid3d."""
    return (np.asarray(pose.rotation.matrix(), dtype=np.float64),
            np.asarray(pose.translation, dtype=np.float64).reshape(3))


def quaternion_from_rodrigues(rvec: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z), w >= 0, of the rotation of a Rodrigues vector (3,)."""
    rvec = np.asarray(rvec, dtype=np.float64)
    theta = float(np.linalg.norm(rvec))
    if theta == 0:
        return np.array([1.0, 0.0, 0.0, 0.0])
    q = np.concatenate([[math.cos(theta / 2)], math.sin(theta / 2) / theta * rvec])
    return q if q[0] >= 0 else -q


def rodrigues_from_quaternion(q: np.ndarray, where: str) -> np.ndarray:
    """Rodrigues vector (3,) of a quaternion (w, x, y, z); refused unless of unit norm to
    common.ROTATION_TOLERANCE (COLMAP normalizes before writing), then normalized."""
    q = common.numbers(q, (4,), where)
    n = float(np.linalg.norm(q))
    if abs(n - 1.0) > common.ROTATION_TOLERANCE:
        raise ValueError(f"{where}: quaternion {q.tolist()} is not of unit norm ({n!r})")
    q = q / n * (1.0 if q[0] >= 0 else -1.0)
    vn = float(np.linalg.norm(q[1:]))
    if vn == 0:
        return np.zeros(3)
    return 2.0 * math.atan2(vn, q[0]) / vn * q[1:]


def camera_from_model(name: str, model: str, width: int, height: int, params,
                      rvec=(0, 0, 0), tvec=(0, 0, 0), where: str = FORMAT) -> Camera:
    """A Camera from a COLMAP camera (model name, size, params with the principal point in
    COLMAP's convention) and a pose; ValueError naming ``where`` for another model."""
    if model not in MODELS:
        raise ValueError(f"{where}: camera model {model} is not one of {', '.join(MODELS)} (the "
                         f"ones the camera core holds exactly)")
    names = MODELS[model]
    p = common.numbers(params, (len(names),), f"{where}: {model} params")
    v = dict(zip(names, p.tolist()))
    if "f" in v:
        v["fx"] = v["fy"] = v["f"]
    lens = LENSES.get(model, "opencv")
    try:
        return Camera(name, width, height, v["fx"], v["fy"], v["cx"] - PIXEL_SHIFT,
                      v["cy"] - PIXEL_SHIFT, 0.0,
                      np.array([v.get(k, 0.0) for k in lens_model(lens).param_names]),
                      rvec, tvec, lens)
    except ValueError as e:
        raise ValueError(f"{where}: {e}") from None


# ----------------------------------------------------------------------------------------------
# Writing
# ----------------------------------------------------------------------------------------------

def write(cameras: Sequence[Camera], out_dir) -> list[Path]:
    """Write the rig as a COLMAP text model in ``out_dir`` (module notes)."""
    cameras = common.rig(cameras, FORMAT, lenses=CARRIED_LENSES)
    models = []
    for cam in cameras:
        common.refuse_name(cam, FORMAT, "non-blank characters without whitespace (COLMAP's "
                           "image names)", _NAME)
        models.append(colmap_model(cam))  # refuses skew
    cam_lines = [f"{i} {model} {cam.width} {cam.height} " + " ".join(map(repr, params.tolist()))
                 for i, (cam, (model, params)) in enumerate(zip(cameras, models), 1)]
    img_lines = []
    for i, cam in enumerate(cameras, 1):
        pose = quaternion_from_rodrigues(cam.rvec).tolist() + cam.tvec.tolist()
        img_lines += [f"{i} " + " ".join(map(repr, pose)) + f" {i} {cam.name}", ""]
    out_dir = Path(out_dir)
    n = len(cameras)
    texts = (
        "# Camera list with one line of data per camera:\n"
        "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
        f"# Number of cameras: {n}\n" + "\n".join(cam_lines) + "\n",
        "# Image list with two lines of data per image:\n"
        "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n"
        "#   POINTS2D[] as (X, Y, POINT3D_ID)\n"
        f"# Number of images: {n}, mean observations per image: 0\n"
        "# A rig snapshot: one image per camera, cam_from_world with TX, TY, TZ in mm\n"
        + "\n".join(img_lines) + "\n",
        "# 3D point list with one line of data per point:\n"
        "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n"
        "# Number of points: 0, mean track length: 0\n",
    )
    return [write_text(out_dir / f, t) for f, t in zip(FILES, texts)]


# ----------------------------------------------------------------------------------------------
# Reading
# ----------------------------------------------------------------------------------------------

def _data_lines(path: Path):
    """(line number, stripped line) of every line of a text file."""
    for n, line in enumerate(read_text(path, "COLMAP text file").splitlines(), 1):
        yield n, line.strip()


def _read_cameras_txt(path: Path) -> dict[int, tuple]:
    cams = {}
    for n, line in _data_lines(path):
        if not line or line.startswith("#"):
            continue
        f = line.split()
        where = f"{path}:{n}"
        if len(f) < 4:
            raise ValueError(f"{where}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[], got "
                             f"{line!r}")
        try:
            cid, width, height = int(f[0]), int(f[2]), int(f[3])
        except ValueError:
            raise ValueError(f"{where}: CAMERA_ID, WIDTH and HEIGHT must be integers, got "
                             f"{line!r}") from None
        cams[cid] = (f[1], width, height, f[4:], where)
    return cams


def _read_images_txt(path: Path) -> list[tuple]:
    """(image id, rvec, tvec, camera id, name, where) per image, following COLMAP's reader:
    blank and comment lines are skipped before an image line, whose next line is its points."""
    images = []
    lines = _data_lines(path)
    for n, line in lines:
        if not line or line.startswith("#"):
            continue
        f = line.split()
        where = f"{path}:{n}"
        if len(f) != 10:
            raise ValueError(f"{where}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, "
                             f"got {line!r}")
        try:
            iid, cid = int(f[0]), int(f[8])
        except ValueError:
            raise ValueError(f"{where}: IMAGE_ID and CAMERA_ID must be integers, got "
                             f"{line!r}") from None
        rvec = rodrigues_from_quaternion(f[1:5], f"{where}: QW QX QY QZ")
        tvec = common.numbers(f[5:8], (3,), f"{where}: TX TY TZ")
        images.append((iid, rvec, tvec, cid, f[9], where))
        next(lines, None)  # the image's POINTS2D line
    return images


def _snapshot(cams: dict, images: list[tuple], where: str) -> list[Camera]:
    """The rig of a model with one image per camera, in the images' id order."""
    out = []
    for iid, rvec, tvec, cid, name, at in sorted(images, key=lambda im: im[0]):
        if cid not in cams:
            raise ValueError(f"{at}: image {iid} refers to camera {cid}, which {where} lacks")
        model, width, height, params, cam_at = cams[cid]
        out.append(camera_from_model(name, model, width, height, params, rvec, tvec, cam_at))
    per_camera = [im[3] for im in images]
    for cid in cams:
        if per_camera.count(cid) != 1:
            raise ValueError(f"{cams[cid][4]}: camera {cid} has {per_camera.count(cid)} images; a "
                             f"rig snapshot has exactly one image per camera (its pose)")
    if not out:
        raise ValueError(f"{where}: no cameras")
    return common.rig(out, where, lenses=CARRIED_LENSES)


def read(path) -> list[Camera]:
    """The rig of a COLMAP text model: ``path`` is its folder or one of its files, or a
    pycolmap.Reconstruction."""
    if not isinstance(path, (str, Path)):
        return from_reconstruction(path)
    folder = Path(path)
    if folder.is_file():
        folder = folder.parent
    folder = common.existing(folder, "COLMAP model folder", folder=True)
    paths = [common.existing(folder / f, f"COLMAP {f}") for f in FILES[:2]]
    return _snapshot(_read_cameras_txt(paths[0]), _read_images_txt(paths[1]), str(folder))


def from_reconstruction(reconstruction) -> list[Camera]:
    """The rig of a pycolmap.Reconstruction holding one image per camera."""
    cams = {int(cid): (c.model.name, int(c.width), int(c.height), np.asarray(c.params),
                       f"reconstruction camera {cid}")
            for cid, c in reconstruction.cameras.items()}
    images = []
    for iid, im in reconstruction.images.items():
        R, t = from_rigid3d(im.cam_from_world())
        images.append((int(iid), matrix_to_rodrigues(common.rotation(R, f"image {iid}")), t,
                       int(im.camera_id), im.name, f"reconstruction image {iid}"))
    return _snapshot(cams, images, "pycolmap.Reconstruction")
