"""mrcal's ``.cameramodel``: one camera per file, a Python-literal dict (read with
ast.literal_eval, as mrcal.cameramodel reads it).

Keys written: ``lensmodel``, ``intrinsics`` = [fx, fy, cx, cy, distortion...], ``rt_cam_ref``
(Rodrigues r then translation t: cam_from_world, ``p_cam = R(r) p_ref + t``), the same six
numbers as ``extrinsics`` (the key mrcal before 2.5 reads; mrcal 2.5 checks the two agree) and
``imagersize`` = [w, h]. The lens model is the smallest of mrcal's OpenCV family holding every
nonzero coefficient: LENSMODEL_OPENCV4 (k1 k2 p1 p2), OPENCV5 (+ k3) or OPENCV8 (+ k4 k5 k6), the
distortion of cv2.projectPoints in OpenCV's order. Numbers are written with 17 significant
digits (mrcal's own writer keeps 10, which moves a 4000 px camera by ~1e-7 px).

Subset: OpenCV's pinhole lens with zero skew (mrcal's OpenCV models have none: refused). The
wide lenses of core/lens.py are refused, naming the camera: mrcal 2.5 has no lens model equal
to any of them (its models: PINHOLE, STEREOGRAPHIC, LONLAT, LATLON, OPENCV4/5/8/12, CAHVOR,
CAHVORE, SPLINED_STEREOGRAPHIC). Its nearest are special cases, not the lenses: CAHVORE with
linearity 0, no alpha, beta, R0 or E projects as a Kannala-Brandt lens with k3 = k4 = 0, and
STEREOGRAPHIC as Mei's with xi = 1 and no distortion; a calibrated lens is neither, and
mrcal-convert-lensmodel fits one model to another rather than converting it. Units: mrcal has
none of its own (extrinsics are in its calibration object's unit); this module writes
millimetres and says so in a comment at the top of the file. Pixel convention: OpenCV's, the
top-left pixel's centre at (0, 0) (mrcal puts an image's centre at ((W-1)/2, (H-1)/2) and its
corner pixels at 0 and W-1).

Files are named ``camera-<i>-<name>.cameramodel`` (mrcal's tools write camera-<i>.cameramodel;
the file holds no name), so reading a folder gives the rig back in order with its names; any
other file name gives the camera its stem. Read: LENSMODEL_PINHOLE, OPENCV4, OPENCV5, OPENCV8,
and OPENCV12 when its thin-prism terms s1..s4 are zero; any other model (splined, CAHVOR, LATLON,
...) is refused with a ValueError naming the file.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path
from typing import Sequence

import numpy as np

from ..core.camera import Camera
from ..config.bounds import MAX_FILE_BYTES
from ..core.files import UnreadableFileError, read_text, write_text
from . import common

FORMAT = "mrcal .cameramodel"
SUFFIX = ".cameramodel"
#: mrcal's lens models the camera core holds, by their number of distortion coefficients.
LENSMODELS = {"LENSMODEL_PINHOLE": 0, "LENSMODEL_OPENCV4": 4, "LENSMODEL_OPENCV5": 5,
              "LENSMODEL_OPENCV8": 8, "LENSMODEL_OPENCV12": 12}
_FILE = re.compile(r"camera-(\d+)-(.+)")
_NAME = re.compile(r"[^/\x00]+")


def lensmodel(camera: Camera) -> str:
    """The smallest of mrcal's OPENCV4/5/8 models holding the camera's nonzero coefficients."""
    nonzero = np.flatnonzero(camera.dist)
    last = int(nonzero[-1]) + 1 if nonzero.size else 0
    return next(m for m, n in LENSMODELS.items() if n >= max(last, 4))


def _literal(values) -> str:
    return "[ " + ", ".join(map(repr, values)) + " ]"


def write_camera(camera: Camera, path) -> Path:
    """Write one camera's .cameramodel to ``path`` (module notes)."""
    common.rig([camera], FORMAT)
    common.refuse_skew(camera, "mrcal's OpenCV lens models")
    model = lensmodel(camera)
    intrinsics = [camera.fx, camera.fy, camera.cx, camera.cy] + \
        camera.dist[:LENSMODELS[model]].tolist()
    rt = camera.rvec.tolist() + camera.tvec.tolist()
    text = (f"# camera {camera.name!r}; rt_cam_ref: cam_from_world, translation in mm\n"
            "{\n"
            f"    'lensmodel':  '{model}',\n"
            "    # intrinsics are fx,fy,cx,cy,distortion0,distortion1,....\n"
            f"    'intrinsics': {_literal(intrinsics)},\n"
            f"    'rt_cam_ref': {_literal(rt)},\n"
            f"    'extrinsics': {_literal(rt)}, # for compatibility with mrcal < 2.5\n"
            f"    'imagersize': [ {camera.width}, {camera.height} ],\n"
            "}\n")
    return write_text(path, text)


def write(cameras: Sequence[Camera], out_dir) -> list[Path]:
    """One ``camera-<i>-<name>.cameramodel`` per camera in ``out_dir``."""
    cameras = common.rig(cameras, FORMAT)
    for cam in cameras:
        common.refuse_name(cam, FORMAT, "characters allowed in a file name (no '/')", _NAME)
    return [write_camera(cam, Path(out_dir) / f"camera-{i}-{cam.name}{SUFFIX}")
            for i, cam in enumerate(cameras)]


def read_model(path) -> dict:
    """The dict of one .cameramodel file, whatever its lens model (bounded read, literal_eval;
    a ValueError naming the file for anything else)."""
    path = common.existing(path, "mrcal .cameramodel file")
    try:
        model = ast.literal_eval(read_text(path, "mrcal .cameramodel file", MAX_FILE_BYTES))
    except UnreadableFileError:
        raise
    except (SyntaxError, ValueError) as e:
        raise ValueError(f"{path}: not a Python-literal cameramodel ({e})") from None
    except (RecursionError, MemoryError):  # the parser's own stack, on deeply nested brackets
        raise ValueError(f"{path}: nested too deeply; expected a mrcal .cameramodel file") from None
    if not isinstance(model, dict):
        raise ValueError(f"{path}: expected a dict with lensmodel, intrinsics, rt_cam_ref, "
                         f"imagersize")
    return model


def read_camera(path) -> Camera:
    """The camera of one .cameramodel file."""
    path = Path(path)
    model = read_model(path)
    try:
        lens = model["lensmodel"]
        intrinsics = model["intrinsics"]
        rt = model["rt_cam_ref"] if "rt_cam_ref" in model else model["extrinsics"]
        size = model["imagersize"]
    except KeyError as e:
        raise ValueError(f"{path}: missing {e.args[0]!r}") from None
    if lens not in LENSMODELS:
        raise ValueError(f"{path}: lensmodel {lens!r} is not one of {', '.join(LENSMODELS)} (the "
                         f"ones the camera core holds)")
    n = LENSMODELS[lens]
    p = common.numbers(intrinsics, (4 + n,), f"{path}: intrinsics of {lens}")
    if np.any(p[12:]):
        raise ValueError(f"{path}: thin-prism terms s1..s4 = {p[12:].tolist()} are not 0; the "
                         f"camera core holds [k1, k2, p1, p2, k3, k4, k5, k6]")
    rt = common.numbers(rt, (6,), f"{path}: rt_cam_ref")
    w, h = common.numbers(size, (2,), f"{path}: imagersize")
    match = _FILE.fullmatch(path.stem)
    try:
        return Camera(match.group(2) if match else path.stem, int(w), int(h), *p[:4], 0.0,
                      p[4:12], rt[:3], rt[3:])
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None


def read(path) -> list[Camera]:
    """One .cameramodel file, or every one in a folder (in the order of their camera-<i>
    prefixes, then by name)."""
    path = Path(path)
    if not path.is_dir():
        return [read_camera(path)]
    files = list(path.glob(f"*{SUFFIX}"))
    if not files:
        raise ValueError(f"{path}: no {SUFFIX} files")

    def order(f: Path):
        m = _FILE.fullmatch(f.stem)
        return (0, int(m.group(1)), f.name) if m else (1, 0, f.name)

    return common.rig([read_camera(f) for f in sorted(files, key=order)], str(path))
