"""The worker environment: a virtual environment of its own for Blender and the 2D pose detector.

bpy 5.0.1 (the newest for Python 3.11) and mediapipe 0.10.21 (whose wheel carries BlazePose's
weights, so nothing is downloaded at run time) both need numpy < 2, which the main environment
does not keep; they run in a process of this environment (:mod:`.client`, :mod:`.worker`).

Where: ``$SYNTHCAL_BLENDER_ENV`` if set, else ``blender/`` inside the main environment
(``sys.prefix``), so removing the main environment removes it too. Built by
``stereo-bench blender-setup`` (``make blender``) from PyPI, about 2 GB and two minutes; its
interpreter is a Python 3.11 (the main one when it is 3.11, else one found on the PATH or under
pyenv). Blender also needs a few X11/GL libraries, which Debian ships as libx11-6 libxrender1
libxfixes3 libxi6 libxkbcommon0 libsm6 libice6 libxext6 libgl1.
"""

from __future__ import annotations

import glob
import hashlib
import os
import shutil
import subprocess
import sys
from pathlib import Path

REQUIREMENTS = ("bpy==5.0.1", "numpy<2", "mediapipe==0.10.21")
_MARKER = "synthcal-worker.txt"  # written last: the requirements the environment was built with


class WorkerUnavailable(RuntimeError):
    """The worker environment is missing or broken; the message says how to build it."""


def location() -> Path:
    return Path(os.environ.get("SYNTHCAL_BLENDER_ENV") or Path(sys.prefix) / "blender")


def python() -> Path:
    return location() / "bin" / "python"


def _stamp() -> str:
    return hashlib.sha256("\n".join(REQUIREMENTS).encode()).hexdigest()[:16]


def status() -> str | None:
    """None when the worker environment is built for today's requirements, else why not."""
    marker = location() / _MARKER
    if not python().exists() or not marker.exists():
        return (f"the Blender worker environment is not built ({location()}); build it with "
                f"`stereo-bench blender-setup` (or `make blender`)")
    if marker.read_text().strip() != _stamp():
        return (f"the Blender worker environment at {location()} was built for other "
                f"requirements; rebuild it with `stereo-bench blender-setup`")
    return None


def require() -> Path:
    """The worker's interpreter; WorkerUnavailable naming the fix when it is not built."""
    reason = status()
    if reason:
        raise WorkerUnavailable(reason)
    return python()


def find_python311() -> str | None:
    """A Python 3.11 interpreter: bpy 5.0.1 and mediapipe 0.10.21 have wheels for it."""
    if sys.version_info[:2] == (3, 11):
        return sys.executable
    candidates = [shutil.which("python3.11")] + sorted(
        glob.glob(os.path.expanduser("~/.pyenv/versions/3.11*/bin/python3.11")))
    return next((c for c in candidates if c), None)


def build(progress=print) -> Path:
    """Create (or complete) the worker environment; returns its interpreter. Raises
    WorkerUnavailable with pip's last words when a step fails."""
    base = find_python311()
    if base is None:
        raise WorkerUnavailable("the Blender worker needs a Python 3.11 (bpy 5.0.1 and mediapipe "
                                "0.10.21 have wheels for it); none was found on the PATH or "
                                "under ~/.pyenv")
    where = location()
    (where / _MARKER).unlink(missing_ok=True)
    steps = [([base, "-m", "venv", str(where)], f"creating {where} with {base}"),
             ([str(python()), "-m", "pip", "install", "--progress-bar", "off", *REQUIREMENTS],
              "installing " + ", ".join(REQUIREMENTS) + " (about 2 GB)")]
    for command, what in steps:
        progress(what + " ...")
        done = subprocess.run(command, capture_output=True, text=True)
        if done.returncode != 0:
            tail = "\n".join((done.stdout + done.stderr).strip().splitlines()[-8:])
            raise WorkerUnavailable(f"{what} failed:\n{tail}")
    check = subprocess.run([str(python()), "-c", "import bpy, mediapipe"], capture_output=True,
                           text=True)
    if check.returncode != 0:
        tail = "\n".join(check.stderr.strip().splitlines()[-4:])
        raise WorkerUnavailable(
            f"the worker environment is installed but bpy or mediapipe does not import:\n{tail}"
            "\n(Blender needs Debian's libx11-6 libxrender1 libxfixes3 libxi6 libxkbcommon0 "
            "libsm6 libice6 libxext6 libgl1)")
    (where / _MARKER).write_text(_stamp() + "\n")
    progress(f"worker environment ready: {where}")
    return python()
