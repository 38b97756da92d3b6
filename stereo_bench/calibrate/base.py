"""What every calibration method consumes and produces.

``Observations`` are one camera's views of a planar board (object points on z = 0, in mm; image
points in OpenCV pixel centres). A ``Calibrator`` turns them into a ``CalibrationResult``: the
estimated ``Camera`` (cam_from_world = identity, since a single camera defines its own frame), one
cam_from_board pose per view, and a log of how the estimate was reached.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from ..core.board_shape import BoardShape
from ..core.camera import Camera

MIN_POINTS_PER_VIEW = 4  # a plane-to-image homography needs four correspondences


@dataclass(frozen=True)
class Observations:
    """One camera's views of a planar board.

    object_points: per view (N_i, 3) board points in mm with z = 0.
    image_points:  per view (N_i, 2) detected pixels (OpenCV: top-left pixel centre at (0, 0)).
    image_size:    (width, height) in pixels.
    view_ids:      frame index of each view (to pair views with ground truth or other cameras).
    """

    object_points: list[np.ndarray]
    image_points: list[np.ndarray]
    image_size: tuple[int, int]
    view_ids: list[int]
    camera_name: str = "camera"

    def __post_init__(self):
        n = len(self.object_points)
        if n == 0:
            raise ValueError(f"observations of {self.camera_name!r}: no views")
        if len(self.image_points) != n or len(self.view_ids) != n:
            raise ValueError(
                f"observations of {self.camera_name!r}: {n} object_points, "
                f"{len(self.image_points)} image_points and {len(self.view_ids)} view_ids; "
                f"expected one of each per view")
        obj, img = [], []
        for i, (o, p) in enumerate(zip(self.object_points, self.image_points)):
            o = np.asarray(o, dtype=np.float64).reshape(-1, 3)
            p = np.asarray(p, dtype=np.float64).reshape(-1, 2)
            where = f"observations of {self.camera_name!r}, view {self.view_ids[i]}"
            if len(o) != len(p) or len(o) < MIN_POINTS_PER_VIEW:
                raise ValueError(f"{where}: {len(o)} object and {len(p)} image points; expected "
                                 f"equal counts of at least {MIN_POINTS_PER_VIEW}")
            if not (np.all(np.isfinite(o)) and np.all(np.isfinite(p))):
                raise ValueError(f"{where}: non-finite coordinates")
            if np.any(np.abs(o[:, 2]) > 1e-9 * max(1.0, np.abs(o).max())):
                raise ValueError(f"{where}: object points must lie on the board plane z = 0")
            obj.append(o)
            img.append(p)
        w, h = (int(s) for s in self.image_size)
        if w <= 0 or h <= 0:
            raise ValueError(f"observations of {self.camera_name!r}: image_size must be "
                             f"(width, height) > 0, got {self.image_size}")
        object.__setattr__(self, "object_points", obj)
        object.__setattr__(self, "image_points", img)
        object.__setattr__(self, "image_size", (w, h))
        object.__setattr__(self, "view_ids", [int(v) for v in self.view_ids])

    @property
    def n_views(self) -> int:
        return len(self.object_points)

    @property
    def n_points(self) -> int:
        return sum(len(p) for p in self.image_points)


@dataclass(frozen=True)
class CalibrationResult:
    """An estimated camera plus the board poses found with it.

    rvecs, tvecs: (V, 3) cam_from_board per view, in the order of ``Observations.view_ids``.
    log: method, iterations, initial/final cost, rms_px, time_s, notes and, when the method ends
    with refine.py, per-parameter standard deviations and the rank of the intrinsic block (and
    ``board_warp_mm``, ``board_aspect_error_pct`` when it fitted the board's shape).
    """

    camera: Camera
    rvecs: np.ndarray
    tvecs: np.ndarray
    log: dict = field(default_factory=dict)

    def board_points(self, obs: "Observations") -> list[np.ndarray]:
        """Each view's board points (N_i, 3) as the calibration saw the board: the nominal
        ones, or shaped by the warp and aspect error it fitted (``log["board_warp_mm"]``)."""
        shape = fitted_shape(np.concatenate(obs.object_points), [self.log])
        if shape is None:
            return list(obs.object_points)
        return [shape.points(o) for o in obs.object_points]


class Calibrator(Protocol):
    """``model_parameters``: the parameters of the camera core's OpenCV model (camera.py's
    INTRINSIC_NAMES + DIST_NAMES) that the method estimates, which a rig's bundle adjustment
    may refine with it; None when the method's own model is not a subset of OpenCV's.
    ``lens_models``: the models of lens_models.py the method can fit (as ``BASE-MODEL``, passed
    to its constructor as ``lens_model``); empty when it fits only its own. ``own_model``: what
    plain ``BASE`` fits, in a few words (for messages)."""

    name: str
    model_parameters: tuple[str, ...] | None
    lens_models: tuple[str, ...]
    own_model: str

    def calibrate(self, obs: Observations) -> CalibrationResult: ...


def fitted_shape(object_points: np.ndarray, logs) -> BoardShape | None:
    """The board's shape (its grid from ``object_points``) as calibrations fitted it: the mean
    of the warps and aspect errors in their ``logs``; None when none fitted it."""
    logs = [log for log in logs if "board_warp_mm" in log]
    if not logs:
        return None
    fits = [[*log["board_warp_mm"], log.get("board_aspect_error_pct", 0.0)] for log in logs]
    grid = logs[0].get("board_grid_mm")  # the grid the fit is about (a subset's, in a fold)
    shape = (BoardShape.of_points(object_points) if grid is None else
             BoardShape(centre_mm=tuple(grid[:2]), half_mm=tuple(grid[2:])))
    return shape.with_fit(np.mean(fits, axis=0))
