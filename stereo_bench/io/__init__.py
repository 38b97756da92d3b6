"""Calibration exchange formats: write a rig for another tool, read one back.

A rig is a ``list[Camera]`` whose rvec/tvec are cam_from_world in mm (camera 0 usually the
reference, at the identity); a single camera is a list of one. Each format is one module, named
after it, whose docstring states the subset of the camera model it holds, its units and its
pixel convention, and which refuses the rest with a ValueError naming the camera and the
parameter (docs/formats.md has the table):

=============  ===============================================================================
opencv         OpenCV FileStorage YAML: one camera, a stereo pair (with OpenCV's rectification
               of it, pinhole or fisheye) or a multi-camera rig (:mod:`.opencv_yaml`)
colmap         COLMAP text model: cameras.txt, images.txt, points3D.txt (:mod:`.colmap`)
kalibr         Kalibr camchain.yaml (:mod:`.kalibr`)
easymocap      EasyMocap intri.yml and extri.yml (:mod:`.easymocap`)
anipose        anipose / aniposelib calibration.toml (:mod:`.anipose`)
caliscope      caliscope camera_array.toml (and its older sessions' config.toml) (:mod:`.caliscope`)
mrcal          mrcal .cameramodel files (:mod:`.mrcal`)
multical       multical's calibration.json (:mod:`.multical`)
=============  ===============================================================================

Each module has ``write(cameras, out_dir, ...) -> list[Path]`` and ``read(path) ->
list[Camera]``; :func:`export` and :func:`load` pick the module by name, and :func:`load` guesses
it from the file or folder when it is not given (:func:`guess_format`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

from ..core.camera import Camera
from . import anipose, caliscope, colmap, easymocap, kalibr, mrcal, multical, opencv_yaml

FORMATS = {
    "opencv": opencv_yaml,
    "colmap": colmap,
    "kalibr": kalibr,
    "easymocap": easymocap,
    "anipose": anipose,
    "caliscope": caliscope,
    "mrcal": mrcal,
    "multical": multical,
}


def _module(fmt: str):
    if fmt not in FORMATS:
        raise ValueError(f"format {fmt!r}: expected one of {', '.join(FORMATS)}")
    return FORMATS[fmt]


def export(cameras: Sequence[Camera], out_dir, fmt: str, **options) -> list[Path]:
    """Write the rig ``cameras`` in format ``fmt`` into ``out_dir``; the files written.
    ``options`` go to the format's ``write`` (``rebase=True`` for opencv and kalibr: write a rig
    whose camera 0 is not at the identity relative to camera 0)."""
    return _module(fmt).write(cameras, out_dir, **options)


def guess_format(path) -> str:
    """The format of a file or folder, from its name (a folder: from the files in it)."""
    path = Path(path)
    if path.is_dir():
        names = {p.name for p in path.iterdir()}
        if "cameras.txt" in names:
            return "colmap"
        if {"intri.yml", "extri.yml"} <= names:
            return "easymocap"
        if any(n.startswith("camchain") and n.endswith((".yaml", ".yml")) for n in names):
            return "kalibr"
        if any(n.endswith(mrcal.SUFFIX) for n in names):
            return "mrcal"
        if anipose.FILE in names:
            return "anipose"
        if names & {caliscope.FILE, caliscope.LEGACY_FILE}:
            return "caliscope"
        if names & {opencv_yaml.STEREO_FILE, opencv_yaml.MULTICAM_FILE}:
            return "opencv"
        if multical.FILE in names and multical.looks_like(path / multical.FILE):
            return "multical"
        raise ValueError(f"{path}: cannot tell the format of this folder (expected cameras.txt, "
                         f"intri.yml and extri.yml, camchain*.yaml, *{mrcal.SUFFIX}, "
                         f"{anipose.FILE}, {caliscope.FILE}, {opencv_yaml.STEREO_FILE}, "
                         f"{opencv_yaml.MULTICAM_FILE} or {multical.FILE}); name it with fmt=")
    if not path.is_file():
        raise ValueError(f"{path}: no such file or folder")
    name = path.name
    if name.endswith(mrcal.SUFFIX):
        return "mrcal"
    if name.startswith("camchain") and name.endswith((".yaml", ".yml")):
        return "kalibr"
    if name in easymocap.FILES:
        return "easymocap"
    if name in (caliscope.FILE, caliscope.LEGACY_FILE):
        return "caliscope"
    if name.endswith(".toml"):
        return "anipose"
    if name in colmap.FILES:
        return "colmap"
    if name.endswith(".json") and multical.looks_like(path):
        return "multical"
    if name.endswith((".yaml", ".yml", ".xml", ".json")):
        return "opencv"
    raise ValueError(f"{path}: cannot tell the format from this file name; name it with fmt=")


def load(path, fmt: str | None = None) -> list[Camera]:
    """The rig in a file or folder, in format ``fmt`` or the one :func:`guess_format` finds."""
    return _module(fmt or guess_format(path)).read(path)
