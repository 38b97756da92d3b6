"""multical's calibration, as its users run it: ``multical calibrate`` (multical 0.4) on the
session's rendered images, with OpenCV's standard model (fx, fy, cx, cy, k1 k2 p1 p2 k3: its
default ``--distortion_model standard``) and its defaults but for the options below (its
intrinsic initialisation per camera with cv2.calibrateCamera, its pose initialisation, three
rounds of bundle adjustment over the cameras and the board poses with its outlier rejection).

multical runs on Python 3.10 only (its command line dies at import on 3.11+, and it needs
numpy < 1.24): it runs in its own environment (``make multical-env``), found at
SYNTHCAL_MULTICAL_PYTHON or .venv/multical.

* Its input. multical's command line reads image folders only (one per camera, matching file
  names) and detects the board itself, so it is the one tool here that does not calibrate the
  suite's detections: it is given the session's rendered images (``Session.images``), and a
  session of detections only is refused. Its detector is OpenCV 4.6's ChArUco corner
  interpolation (the OpenCV its package pins), which returns every corner +0.5 px right and down
  of the true one in OpenCV's pixel convention (OpenCV shifts the corners by 0.5 px around
  cornerSubPix; later OpenCV releases drop the shift; measured +0.49 px in x and y on a
  rendered studio session): its principal points follow it, which is what its users get.
* Its board: a ChArUco board only (its boards.yaml takes ``charuco`` and ``aprilgrid``, and the
  suite renders no AprilGrid; a checkerboard is refused, by multical and here), written as
  ``boards.yaml`` with multical's fields: ``size`` [squares_x, squares_y], ``square_length`` and
  ``marker_length`` in metres (its documentation's unit: the camera translations come back in
  metres), ``aruco_dict`` (the dictionary's name without DICT_) and ``aruco_offset`` (the id of
  its first marker). multical numbers the corners as OpenCV's CharucoBoard does, row by row from
  the corner at (square, square): the board's own points here. Refused: a two-sided board
  (multical poses a second board from images that show both, and no image shows both sides)
  and a legacy board with an even number of rows (OpenCV 4.6 draws the current layout only).
* Its files. multical writes its outputs into ``--image_path`` whatever ``--output_path`` says,
  so each camera's image folder is linked into the tool's folder (nothing is written next to
  the dataset's images) and multical is pointed there: ``calibration.json`` (read back with
  io.multical), its log ``calibration.txt``, its workspace ``calibration.pkl`` and its
  detections ``calibration.detections.pkl``; ``tool.log`` holds what it printed, and
  ``.matplotlib`` the font cache of the matplotlib it imports.
* Options given: ``--cameras`` in the session's order (the first is multical's master, the
  reference camera 0); ``--limit_images`` the session's frame count (its default, 200, would
  calibrate a random subset of a longer session while every other tool gets every view);
  ``--limit_intrinsic`` without a value (None: every view initialises the intrinsics). Its
  default, 50, sorts the views by their coverage plus noise drawn from numpy's unseeded
  generator (its ``--seed`` is never used), so that runs on one session differed by up to
  0.8 px in a principal point (8 runs on a studio session: its bundle adjustment ends where
  its start leads it), and it fails outright ("Can't parse 'objectPoints'") when every view of
  a camera holds the same number of corners, e.g. every view whole: multical then stacks the
  views into one array. Without the limit multical is deterministic. ``--num_threads`` is its
  default (the CPUs but one), at least 1.
"""

from __future__ import annotations

import os
import re
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from ..core.files import is_safe_name, write_text
from ..io import multical as multical_file
from . import Session, ToolError, ToolResult, environment_python

ABOUT = ("multical calibrate (multical 0.4, its own ChArUco detection on the images), OpenCV's "
         "standard model, its defaults (in its own environment)")
TIMEOUT_S = 1800
#: What multical calibrate writes (with --name calibration, its default) into --image_path.
OUTPUTS = ("calibration.json", "calibration.txt", "calibration.pkl",
           "calibration.detections.pkl")


def python() -> Path:
    return environment_python("SYNTHCAL_MULTICAL_PYTHON", "multical")


def missing() -> str | None:
    exe = python()
    tool = exe.parent / "multical"
    if not exe.is_file() or not tool.is_file():
        return (f"no multical environment: {tool} not found (`make multical-env`, which needs "
                f"a python3.10; or set SYNTHCAL_MULTICAL_PYTHON to its python)")
    with tempfile.TemporaryDirectory() as scratch:
        done = subprocess.run([str(exe), "-c", "import multical.app.multical, cv2"],
                              capture_output=True, text=True, env=_env(Path(scratch)))
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or ["no message"])[-1]
        return f"{exe} cannot import multical ({last}; `make multical-env` installs it)"
    return None


def _env(matplotlib_dir: Path) -> dict:
    """The environment multical runs in: this one's, without a Python path that would put the
    suite's packages (numpy 2) before multical's own, and with matplotlib's font cache (multical
    imports matplotlib) in ``matplotlib_dir``, not in the user's home."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    return env | {"MPLCONFIGDIR": str(matplotlib_dir)}


def boards_yaml(session: Session) -> str:
    """multical's boards.yaml for the session's board (module notes), or a ToolError naming why
    multical cannot take it."""
    p = session.pattern
    if p.kind != "charuco":
        raise ToolError(f"multical: its command line detects ChArUco and AprilGrid boards only "
                        f"(boards.yaml _type_ charuco or aprilgrid); the session's board is "
                        f"{p.kind}")
    if p.two_sided:
        raise ToolError("multical: a two-sided ChArUco board; multical would take its back for a "
                        "second board, posed from images that show both, and none shows both")
    if p.legacy and p.squares_y % 2 == 0:
        raise ToolError(f"multical: a legacy ChArUco board with an even number of rows "
                        f"(squares_y {p.squares_y}); multical's OpenCV 4.6 draws only the "
                        f"current layout, whose markers are in the other squares")
    # multical's corners are OpenCV's CharucoBoard's: row by row from (square, square).
    cols, rows = p.squares_x - 1, p.squares_y - 1
    j, i = np.divmod(np.arange(cols * rows), cols)
    expected = np.stack([(i + 1) * p.square_mm, (j + 1) * p.square_mm, 0 * i], axis=1)
    if session.object_points.shape != expected.shape or not np.allclose(
            session.object_points, expected, atol=1e-9):
        raise ToolError("multical: the board's points are not OpenCV's ChArUco corners (row by "
                        "row from (square, square)), which multical numbers its corners by")
    return "\n".join([
        "boards:", "  board:", "    _type_: charuco",
        f"    size: [{p.squares_x}, {p.squares_y}]",
        f"    square_length: {p.square_mm / 1000!r}",  # metres (module notes)
        f"    marker_length: {p.marker_mm / 1000!r}",
        f"    aruco_dict: {p.dictionary.removeprefix('DICT_')}",
        f"    aruco_offset: {int(p.marker_id_offset)}", ""])


def _link_images(session: Session, out_dir: Path) -> None:
    if session.images is None:
        raise ToolError("multical: its command line reads image folders and detects the board "
                        "itself; this session has detections only (no rendered images)")
    for name in session.names:
        if not is_safe_name(name) or name in ("boards.yaml", "tool.log", ".matplotlib") + OUTPUTS:
            raise ToolError(f"multical: camera {name!r} cannot name an image folder (letters, "
                            f"digits, _ - . expected)")
        folder = Path(session.images) / name
        if not folder.is_dir():
            raise ToolError(f"multical: no image folder {folder} for camera {name!r}")
        link = out_dir / name
        if link.is_symlink() or link.exists():
            if not link.is_symlink():
                raise ToolError(f"multical: {link} is in the way of camera {name!r}'s images")
            link.unlink()
        link.symlink_to(folder.resolve(), target_is_directory=True)


def _log(said: str, cmd: list[str]) -> dict:
    """What multical said of its calibration: its final reprojection RMS over the points its
    outlier rejection kept and over all, the points it detected, and the outliers it dropped."""
    log = {"command": " ".join(["multical", *cmd[1:]])}
    end = re.findall(r"Adjust_outliers end: reprojection RMS=([\d.]+) \(([\d.]+)\), "
                     r"n=(\d+) \((\d+)\)", said)
    if end:
        rms, rms_all, kept, n = end[-1]
        log.update(rms_inliers_px=float(rms), rms_px=float(rms_all), points=int(n),
                   outliers=int(n) - int(kept))
    counts = re.findall(r"Total: (\d+), cameras: (\{[^}]*\})", said)
    if counts:
        log["points_detected"] = {k: int(v) for k, v in re.findall(r"'([^']+)': (\d+)",
                                                                   counts[0][1])}
    return log


def calibrate(session: Session, out_dir: Path, name: str = "multical") -> ToolResult:
    board = boards_yaml(session)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    for stale in OUTPUTS:  # a rerun detects again (timed alike) and never reads an old answer
        (out_dir / stale).unlink(missing_ok=True)
    _link_images(session, out_dir)
    boards = write_text(out_dir / "boards.yaml", board)
    frames = session.found.shape[1]
    cmd = [str(python().parent / "multical"), "calibrate", "--image_path", str(out_dir),
           "--boards", str(boards), "--cameras", *session.names,
           "--limit_images", str(frames),
           # its default, cpu_count() - 1, is 0 on one CPU, where its process pool fails
           "--num_threads", str(max(1, (os.cpu_count() or 2) - 1)),
           "--limit_intrinsic"]  # no value: None, every view (module notes)
    t0 = time.perf_counter()
    try:
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=TIMEOUT_S,
                              cwd=out_dir, env=_env(out_dir / ".matplotlib"))
    except subprocess.TimeoutExpired:
        raise ToolError(f"multical: multical calibrate ran past {TIMEOUT_S} s") from None
    elapsed = time.perf_counter() - t0
    said = done.stdout + done.stderr
    write_text(out_dir / "tool.log", said)
    path = out_dir / multical_file.FILE
    if done.returncode != 0 or not path.is_file():
        last = (done.stderr.strip().splitlines() or ["no message"])[-1]
        raise ToolError(f"multical: multical calibrate failed ({last}; {out_dir}/tool.log)")
    cams = multical_file.read(path)
    if [c.name for c in cams] != list(session.names):
        raise ToolError(f"multical: its calibration.json holds cameras "
                        f"{[c.name for c in cams]}, expected {list(session.names)}")
    for cam, size in zip(cams, session.sizes):
        if cam.size != tuple(size):
            raise ToolError(f"multical: camera {cam.name!r} is {cam.width}x{cam.height} in its "
                            f"calibration, expected {size[0]}x{size[1]}")
    return ToolResult(cams, path, "multical", elapsed, _log(said, cmd))
