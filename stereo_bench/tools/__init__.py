"""The calibrators people run, each run as its users run it on one session's detections.

``stereo-bench compare-tools`` (run/compare.py) renders a session, detects the board once and
hands every tool the same detections (a :class:`Session`), so a difference between two rows is
the calibrators', not the detectors'. Each tool writes its answer in its own file format, and
the answer is read back through the suite's reader of that format (``stereo_bench.io``): what is
scored is what a user of the tool would load. Every tool module has

* ``ABOUT``: one line, what is run with which model (a dict by tool name when the module runs
  several: ``MODULES`` below says which names a module serves);
* ``missing() -> str | None``: why the tool cannot run on this machine (its library or its
  environment is absent, with the command that installs it), or None;
* ``calibrate(session, out_dir, name) -> ToolResult``, raising ToolError (or ValueError) with a
  message naming the tool when the tool refuses the session or fails on it.

=================  ================================================================================
synthcal           the suite's own: Zhang per camera, then its rig bundle adjustment (a reference)
synthcal-warp      the same, the board's warp fitted (as mrcal fits it by default)
opencv-stereo      cv2.calibrateCamera per camera, then cv2.stereoCalibrate (pairs)
opencv-multiview   cv2.calibrateMultiview, intrinsics by its own calibrateCamera (OpenCV >= 5)
pycolmap           OpenCV's cameras refined by pycolmap's bundle adjuster with its rig
anipose            aniposelib's CameraGroup.calibrate_rows (init, then its bundle adjustment)
caliscope          caliscope's intrinsics per camera, then its capture volume (scripting guide)
mrcal              mrcal-calibrate-cameras, LENSMODEL_OPENCV8 (in mrcal's own environment)
mrcal-splined      the same with its splined stereographic model, scored through mrcal
multical           multical calibrate on the rendered images (its own ChArUco detection)
=================  ================================================================================

The tools that report an uncertainty return it in ``ToolResult.uncertainty``: per camera, the
1-sigma of each intrinsic parameter it reports (``parameters``), and/or its projection
covariance at chosen pixels (``projection``: ``pixels`` (P, 2), ``distance_mm``, ``covariance``
(P, 2, 2) px^2, and the ``board_poses`` {frame: (rvec, tvec)} cam_from_board of its solve, which
define its camera frame), which compare-tools checks against the true error; or ``error``: why
the tool could not compute it this time.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..core.camera import Camera

#: Tool name -> module (imported when used: each pulls its own library).
MODULES = {
    "synthcal": "synthcal",
    "synthcal-warp": "synthcal",
    "opencv-stereo": "opencv",
    "opencv-multiview": "opencv",
    "pycolmap": "colmap",
    "anipose": "anipose",
    "caliscope": "caliscope",
    "mrcal": "mrcal",
    "mrcal-splined": "mrcal",
    "multical": "multical",
}
TOOLS = tuple(MODULES)


class ToolError(ValueError):
    """A tool refused a session or failed on it; the message names the tool."""


@dataclass(frozen=True, eq=False)
class Session:
    """What every tool is given: one calibration session's detections.

    names, sizes: the cameras' names and image sizes (width, height) px; nothing else of the
    cameras is the tools' to see. object_points (N, 3) mm, the board's points in its frame (z = 0).
    image_points (C, F, N, 2) px, OpenCV's pixel convention (the centre of the top-left pixel at
    (0, 0)), NaN where a point was not detected. found (C, F): the camera found the board.
    pattern: the board (core.patterns: its kind and geometry, e.g. a ChArUco board's
    dictionary). images: the folder of the session's rendered images, one subfolder per camera
    named as the camera, frame f in ``f"{f:06d}.png"`` (the dataset's layout), for a tool that
    reads images and detects the board itself (multical); None for a session of detections
    only.
    """

    names: list[str]
    sizes: list[tuple[int, int]]
    object_points: np.ndarray
    image_points: np.ndarray
    found: np.ndarray
    pattern: object
    images: Path | None = None

    def full_views(self) -> np.ndarray:
        """(C, F): the views where every point of the board was detected."""
        return self.found & np.isfinite(self.image_points).all(axis=(-1, -2))

    def grid(self) -> tuple[int, int, float]:
        """(columns, rows, spacing mm) of a board whose points are a square grid numbered row
        by row, x fastest (OpenCV's order for a checkerboard and a ChArUco board's corners); a
        ToolError for any other layout (an asymmetric circle grid), which grid-only tools
        (mrcal, aniposelib's boards) cannot describe."""
        obj = self.object_points
        xs, ys = np.unique(np.round(obj[:, 0], 6)), np.unique(np.round(obj[:, 1], 6))
        cols, rows = len(xs), len(ys)
        spacing = float(xs[1] - xs[0]) if cols > 1 else float("nan")
        ok = cols * rows == len(obj) and cols > 1 and rows > 1
        if ok:
            j, i = np.divmod(np.arange(len(obj)), cols)
            expected = np.stack([xs[0] + i * spacing, ys[0] + j * spacing], axis=1)
            ok = np.allclose(obj[:, :2], expected, atol=1e-6) and np.allclose(obj[:, 2], 0)
        if not ok:
            raise ToolError(f"the {self.pattern.kind} board's points are not a square grid "
                            f"numbered row by row; this tool describes only such boards")
        return cols, rows, spacing


@dataclass(eq=False)
class ToolResult:
    """A tool's calibration as read back from its own file (``path``, format ``fmt`` of
    stereo_bench.io): cameras with cam_from_world = cam_from_cam0 in mm, in the session's
    order. ``time_s``: the tool's own work (not the reading back). ``log``: what the tool said
    of itself (its RMS, its settings). ``uncertainty``: see the module notes."""

    cameras: list[Camera]
    path: Path
    fmt: str
    time_s: float
    log: dict = field(default_factory=dict)
    uncertainty: dict = field(default_factory=dict)
    #: For a lens the suite's camera model cannot hold (``cameras`` is then empty):
    #: ``proxy(true_cameras, image_points) -> (cameras, image_points, projection)``, stand-ins
    #: that triangulate as the tool's lens does, the detections as seen through them, and per
    #: camera the projection difference computed through the tool's own projection.
    proxy: object = None


def environment_python(variable: str, folder: str) -> Path:
    """The Python of a tool's own environment: the environment variable ``variable``, else
    .venv/``folder`` beside the project (``make mrcal-env``, ``make multical-env``)."""
    import os

    return Path(os.environ.get(variable) or
                Path(__file__).resolve().parents[2] / ".venv" / folder / "bin" / "python")


def module(name: str):
    """The module of tool ``name`` (ValueError naming the tools for an unknown one)."""
    if name not in MODULES:
        raise ValueError(f"tool {name!r}: expected one of {', '.join(TOOLS)}")
    return importlib.import_module(f"{__name__}.{MODULES[name]}")


def parse_tools(text: str | None) -> list[str]:
    """--tools: comma-separated tool names (default: all), each checked."""
    names = list(TOOLS) if not text else [t.strip() for t in text.split(",") if t.strip()]
    for n in names:
        module(n)
    if len(set(names)) != len(names):
        raise ValueError(f"--tools: a tool is named twice in {text!r}")
    return names


def probe_pixels(width: int, height: int) -> np.ndarray:
    """(9, 2) px where projection uncertainties are compared: the centre, the middles of the
    edges' halves and the corners' halfway points (away from the corners themselves, where
    boards seldom reach)."""
    u = np.array([0.5, 0.25, 0.75]) * (width - 1)
    v = np.array([0.5, 0.25, 0.75]) * (height - 1)
    return np.stack(np.meshgrid(u, v), -1).reshape(-1, 2)


def observations(session: Session, c: int):
    """Camera ``c``'s found views as calibrators take them (evaluate.stage's rule: the finite
    points of each found view, views too small or nearly collinear left out)."""
    from ..detect.dataset import CameraDetections
    from ..evaluate.stage import observations as stage_observations

    det = CameraDetections(camera=session.names[c], pattern=session.pattern.kind, method="given",
                           points=session.image_points[c], found=session.found[c],
                           ids=np.arange(len(session.object_points)))
    obs, _ = stage_observations(det, session.object_points,
                                Camera.from_K(session.names[c], *session.sizes[c], np.eye(3)))
    return obs


def board_poses(results, frames: int) -> tuple[np.ndarray, np.ndarray]:
    """(C, F, 3) rvecs and tvecs, each camera's cam_from_board per frame from its calibration
    (CalibrationResult per camera), NaN where the camera has no view of the frame: what
    multiview.bundle.rig_start takes."""
    rv, tv = np.full((len(results), frames, 3), np.nan), np.full((len(results), frames, 3), np.nan)
    for c, (result, obs) in enumerate(results):
        rv[c, obs.view_ids], tv[c, obs.view_ids] = result.rvecs, result.tvecs
    return rv, tv


def read_back(cameras, out_dir: Path, fmt: str, time_s: float, log: dict,
              uncertainty: dict | None = None, write=None) -> ToolResult:
    """Write a tool's cameras in format ``fmt`` (the file its users write; ``write(cameras,
    out_dir)`` when not the format's default layout) and read them back through the suite's
    reader: what is scored is what the file says."""
    from .. import io

    out_dir = Path(out_dir)
    written = (write or (lambda cams, out: io.export(cams, out, fmt)))(cameras, out_dir)
    written = [written] if isinstance(written, Path) else list(written)
    # One file (one camera's, a rig's) is read as itself: a folder of one camera's file is no
    # layout a reader knows.
    source = written[0] if len(written) == 1 else out_dir
    return ToolResult(io.load(source, fmt), out_dir, fmt, time_s, log, uncertainty or {})
