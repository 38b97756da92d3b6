"""What every exchange format shares: the checks on a rig before it is written and on numbers
read back, the refusals of what a format cannot hold, and the unit of length.

A rig is a ``list[Camera]`` whose poses are cam_from_world in millimetres (camera 0 usually the
reference, at the identity); a single camera is a list of one. Formats that store the rig
relative to its first camera (OpenCV's stereo and multi-camera files, Kalibr) have no world
frame: :func:`cam_from_cam0` refuses a rig whose camera 0 is not at the identity unless the
caller asks for the rebase, so that a pose is never dropped silently.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from ..core.camera import DIST_NAMES, Camera
from ..core.poses import nearest_rotation
from ..config.bounds import (MAX_DISTANCE_MM, MAX_DISTORTION, MAX_FOCAL_PX, MAX_IMAGE_PIXELS,
                             MAX_IMAGE_SIDE, MAX_PIXEL_ASPECT, MAX_SKEW_PX)
from ..core.poses import cam_from_cam0 as _cam_from_cam0

MM_PER_M = 1000.0

#: A rotation read from a file must be orthonormal to this (Kalibr writes 8 digits, COLMAP
#: normalizes quaternions itself); it is then projected onto SO(3) exactly.
ROTATION_TOLERANCE = 1e-6


def rig(cameras: Sequence[Camera], fmt: str, min_count: int = 1, posed: bool = True,
        lenses: Sequence[str] = ("opencv",)) -> list[Camera]:
    """The cameras as a list, refused (ValueError naming the entry) unless they are at least
    ``min_count`` stereo_bench Cameras with distinct names, plausible, with a lens model the
    format carries (``lenses``, core/lens.py: a fisheye written as a pinhole would be read back
    as another camera), and (``posed``: they are a rig, not cameras known for their intrinsics
    only) with distinct centres."""
    if isinstance(cameras, Camera):
        cameras = [cameras]
    cameras = list(cameras)
    if len(cameras) < min_count:
        raise ValueError(f"{fmt}: expected at least {min_count} camera(s), got {len(cameras)}")
    for c, cam in enumerate(cameras):
        if not isinstance(cam, Camera):
            raise ValueError(f"{fmt}: cameras[{c}] is a {type(cam).__name__}, expected a "
                             f"stereo_bench Camera")
    names = [cam.name for cam in cameras]
    duplicated = sorted({n for n in names if names.count(n) > 1})
    if duplicated:
        raise ValueError(f"{fmt}: camera names must be distinct, {duplicated} repeat")
    for cam in cameras:
        plausible(cam, fmt)
        if cam.model not in lenses:
            carried = " and ".join([", ".join(lenses[:-1]), lenses[-1]] if len(lenses) > 1
                                   else lenses)
            raise ValueError(f"{fmt}: camera {cam.name!r}: a {cam.model} lens; the format "
                             f"carries {carried} lenses only")
    centres = np.array([cam.center for cam in cameras])
    for a in range(len(cameras) if posed else 0):
        for b in range(a + 1, len(cameras)):
            if np.linalg.norm(centres[a] - centres[b]) < MIN_BASELINE_MM:
                raise ValueError(f"{fmt}: cameras {names[a]!r} and {names[b]!r} share one centre "
                                 f"({centres[a].tolist()} mm); a rig's cameras need a baseline "
                                 f"to triangulate")
    return cameras


#: Cameras of a rig closer than this share a centre: a baseline of zero, which no triangulation
#: or rig metric can use (a rig file written with T = 0 is a rig nobody calibrated).
MIN_BASELINE_MM = 1e-3


def plausible(camera: Camera, where: str) -> None:
    """Refuse (ValueError naming the camera and the parameter) a camera that is not a camera:
    the bounds a rig file puts on a lens (config.LensConfig) and a position, loosened where an
    estimate may legitimately differ from a designed camera (a principal point anywhere within
    an image's size of the image). Camera itself already refuses non-finite numbers."""
    at = f"{where}: camera {camera.name!r}"
    w, h = camera.width, camera.height
    if not (2 <= w <= MAX_IMAGE_SIDE and 2 <= h <= MAX_IMAGE_SIDE) or w * h > MAX_IMAGE_PIXELS:
        raise ValueError(f"{at}: image size {w}x{h}; expected 2..{MAX_IMAGE_SIDE} px a side and "
                         f"at most {MAX_IMAGE_PIXELS:,} pixels")
    for name in ("fx", "fy"):
        value = getattr(camera, name)
        if not 0 < value <= MAX_FOCAL_PX:
            raise ValueError(f"{at}: {name} = {value!r}; expected 0 < {name} <= {MAX_FOCAL_PX:g} px")
    if max(camera.fx / camera.fy, camera.fy / camera.fx) > MAX_PIXEL_ASPECT:
        raise ValueError(f"{at}: fx / fy = {camera.fx / camera.fy:.4g}; expected pixels at most "
                         f"{MAX_PIXEL_ASPECT:g} times as tall as wide or as wide as tall")
    if abs(camera.skew) > MAX_SKEW_PX:
        raise ValueError(f"{at}: skew = {camera.skew!r}; expected |skew| <= {MAX_SKEW_PX:g} px")
    for name, c, size in (("cx", camera.cx, w), ("cy", camera.cy, h)):
        if not -size <= c <= 2 * size:
            raise ValueError(f"{at}: {name} = {c!r}; expected a principal point within "
                             f"{-size}..{2 * size} px of an image {size} px wide")
    worst = int(np.argmax(np.abs(camera.dist)))
    if abs(camera.dist[worst]) > MAX_DISTORTION:
        raise ValueError(f"{at}: {camera.dist_names[worst]} = {float(camera.dist[worst])!r}; expected "
                         f"coefficients of magnitude at most {MAX_DISTORTION:g}")
    if np.linalg.norm(camera.tvec) > MAX_DISTANCE_MM:
        raise ValueError(f"{at}: translation {camera.tvec.tolist()} mm; expected a camera "
                         f"within {MAX_DISTANCE_MM:g} mm of the world origin")


def refuse_skew(camera: Camera, fmt: str) -> None:
    if camera.skew != 0:
        raise ValueError(f"camera {camera.name!r}: skew {camera.skew!r} is not 0; {fmt} has no "
                         f"skew")


def refuse_distortion(camera: Camera, fmt: str, kept: int) -> None:
    """Refuse a camera with a nonzero coefficient past the first ``kept`` of
    [k1, k2, p1, p2, k3, k4, k5, k6] (naming the first one)."""
    extra = np.flatnonzero(camera.dist[kept:])
    if extra.size:
        i = kept + int(extra[0])
        raise ValueError(f"camera {camera.name!r}: {DIST_NAMES[i]} = {float(camera.dist[i])!r} "
                         f"is not 0; {fmt} holds only {', '.join(DIST_NAMES[:kept])}")


def refuse_name(camera: Camera, fmt: str, allowed: str, pattern) -> None:
    """Refuse a name the format cannot carry (``pattern`` a compiled regex, ``allowed`` says
    what it accepts)."""
    if not pattern.fullmatch(camera.name):
        raise ValueError(f"camera {camera.name!r}: {fmt} needs names of {allowed}")


def cam_from_cam0(cameras: Sequence[Camera], fmt: str, rebase: bool) -> tuple[np.ndarray,
                                                                               np.ndarray]:
    """Each camera's pose relative to the first (R (C,3,3), t (C,3) in mm) for a format with no
    world frame. Without ``rebase`` a camera 0 that is not at the identity is refused: writing
    the rig relative to it would drop the world frame."""
    if not rebase and (np.any(cameras[0].rvec) or np.any(cameras[0].tvec)):
        raise ValueError(
            f"camera {cameras[0].name!r}: cam_from_world is not the identity, but {fmt} stores "
            f"the rig relative to its first camera and has no world frame; pass rebase=True to "
            f"write it relative to camera {cameras[0].name!r} (the world frame is then lost)")
    return _cam_from_cam0(cameras)


def rotation(value, where: str) -> np.ndarray:
    """A rotation matrix read from a file: (3, 3), finite, orthonormal to ROTATION_TOLERANCE and
    proper, returned projected onto SO(3)."""
    R = numbers(value, (3, 3), where)
    if (np.abs(R @ R.T - np.eye(3)).max() > ROTATION_TOLERANCE
            or np.linalg.det(R) < 0):
        raise ValueError(f"{where}: expected a rotation matrix, got {R.tolist()} (R R^T != I "
                         f"or det < 0)")
    return nearest_rotation(R)


def camera_matrix(value, where: str) -> np.ndarray:
    """A camera matrix read from a file: [[fx, s, cx], [0, fy, cy], [0, 0, 1]]."""
    K = numbers(value, (3, 3), where)
    if K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1:
        raise ValueError(f"{where}: expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got "
                         f"{K.tolist()}")
    return K


def numbers(value, shape: tuple | None, where: str) -> np.ndarray:
    """Finite float64 numbers of ``shape`` read from a file, or a ValueError naming ``where``;
    ``shape`` None: a vector of any length (a list of coefficients)."""
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):  # OverflowError: an integer of 400 digits
        raise ValueError(f"{where}: expected numbers of shape {shape}, got {repr(value)[:200]}") from None
    if shape is None:
        shape = (a.size,) if a.ndim <= 1 or max(a.shape) == a.size else a.shape
    if len(shape) == 1 and a.size == shape[0] and max(a.shape, default=0) == a.size:
        a = a.reshape(shape)  # a vector stored as a row or a column (OpenCV's matrices)
    if a.shape != shape:
        raise ValueError(f"{where}: expected shape {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{where}: expected finite numbers, got {a.tolist()}")
    return a


def in_folder(path, patterns: Sequence[str], what: str) -> Path:
    """``path`` itself, or when it is a folder the one file in it matching the first of
    ``patterns`` (glob patterns, in order of preference) that matches any."""
    path = Path(path)
    if not path.is_dir():
        return path
    for pattern in patterns:
        found = sorted(path.glob(pattern))
        if len(found) == 1:
            return found[0]
        if found:
            raise ValueError(f"{path}: {len(found)} files match {pattern} "
                             f"({', '.join(f.name for f in found)}); name the {what}")
    raise ValueError(f"{path}: no {what} ({' or '.join(patterns)}) in this folder")


def existing(path, what: str, folder: bool = False) -> Path:
    """``path`` as a Path, refused unless it is an existing file (or folder)."""
    path = Path(path)
    if not (path.is_dir() if folder else path.is_file()):
        raise ValueError(f"{path}: no such {what}")
    return path
