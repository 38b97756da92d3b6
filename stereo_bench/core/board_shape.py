"""The board as made: how a physical board differs from its pattern file.

A pattern (patterns.py) gives the nominal feature points on the plane z = 0. A real board is not
that: its print is scaled by a printer's error, often by a different amount along the paper feed
(x) and across it (y), and it is not flat. ``BoardShape`` maps a nominal board point to where it
physically is, in the board frame (mm)::

    x' = c_x + s_x (x - c_x),  y' = c_y + s_y (y - c_y),
    z' = -(w_x (1 - u^2) + w_y (1 - v^2)),   u = (x - c_x) / a_x,  v = (y - c_y) / a_y

(c, a): centre and half-size of the feature grid's bounding box, so u and v run over [-1, 1]
across the features. The warp is mrcal's two-parameter model of a board deflection (two
axis-aligned parabolas, zero at the grid's edges, strongest at its centre), with ``w`` the
deflection at the centre in mm. Positive ``w`` bows the centre towards a camera facing the
printed side (the board's -z, since +z points away from such a camera).

Scaling about the grid's centre keeps the board frame, and so the trajectory's poses, where they
were: the ground truth (the image points and the 3D points triangulation is scored against) is
the physical points seen from the same poses, while every calibration is given the nominal points,
as a user gives the pattern file. An isotropic scale error is invisible in the images alone (a
larger board further away looks the same) but scales every length of the rig; aspect error and
warp are not absorbed by any pose and show in the reprojection error.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

#: Fixed-point iterations of the ray / warped-surface intersection. Each one shrinks the error by
#: about the surface slope times the ray's obliquity; four take a 3 mm warp seen at 30 degrees to
#: 4e-5 mm (tests/render/test_imaging.py), below 1e-4 px for any board nearer than f px per mm.
_INTERSECTION_ITERATIONS = 4


@dataclass(frozen=True)
class BoardShape:
    """A board's physical shape relative to its pattern (see the module docstring).

    scale: (s_x, s_y), printed size over nominal size (1.002 = 0.2 % larger).
    warp_mm: (w_x, w_y), deflection of the grid's centre in mm.
    centre_mm, half_mm: centre and half-size (a_x, a_y) of the feature grid.
    """

    scale: tuple[float, float] = (1.0, 1.0)
    warp_mm: tuple[float, float] = (0.0, 0.0)
    centre_mm: tuple[float, float] = (0.0, 0.0)
    half_mm: tuple[float, float] = (1.0, 1.0)

    @classmethod
    def for_pattern(cls, pattern, scale_error_pct: float = 0.0, aspect_error_pct: float = 0.0,
                    warp_mm=(0.0, 0.0)) -> "BoardShape":
        """The shape of ``pattern`` printed ``scale_error_pct`` % too large (x and y) and a further
        ``aspect_error_pct`` % in y, with the given warp."""
        sx = 1.0 + scale_error_pct / 100.0
        sy = sx * (1.0 + aspect_error_pct / 100.0)
        grid = cls.of_points(pattern.object_points())
        return cls((sx, sy), (float(warp_mm[0]), float(warp_mm[1])), grid.centre_mm,
                   grid.half_mm)

    @classmethod
    def of_points(cls, points: np.ndarray) -> "BoardShape":
        """The flat, true-to-scale shape whose feature grid spans ``points`` (N, 2 or 3) mm: the
        frame a fitted warp is expressed in."""
        xy = np.asarray(points, dtype=np.float64)[:, :2]
        lo, hi = xy.min(0), xy.max(0)
        return cls(centre_mm=tuple(float(v) for v in (lo + hi) / 2),
                   half_mm=tuple(float(v) for v in np.maximum((hi - lo) / 2, 1e-9)))

    @property
    def is_nominal(self) -> bool:
        return self.scale == (1.0, 1.0) and self.warp_mm == (0.0, 0.0)

    #: What a calibration can fit of a board's shape (refine.py): its warp and the stretch of its
    #: y axis against its x axis (an isotropic scale is not seen: a larger board farther away
    #: makes the same images).
    FIT_NAMES = ("warp_x_mm", "warp_y_mm", "aspect_error_pct")

    @property
    def fit_params(self) -> np.ndarray:
        """(w_x, w_y, aspect error %) of this shape."""
        return np.array([*self.warp_mm, 100.0 * (self.scale[1] / self.scale[0] - 1.0)])

    def with_fit(self, params) -> "BoardShape":
        """This grid with the warp and the aspect error ``params`` (FIT_NAMES), x unscaled."""
        w_x, w_y, aspect = (float(p) for p in params)
        return dataclasses.replace(self, scale=(1.0, 1.0 + aspect / 100.0), warp_mm=(w_x, w_y))

    def fit_jacobian(self, xy: np.ndarray) -> np.ndarray:
        """(N, 3, 3): d points / d FIT_NAMES at nominal xy (N, 2), about an unscaled x."""
        J = np.zeros(xy.shape[:-1] + (3, 3))
        J[..., 2, :2] = self.warp_basis(xy)
        J[..., 1, 2] = (xy[..., 1] - self.centre_mm[1]) / 100.0
        return J

    def warp_basis(self, xy: np.ndarray) -> np.ndarray:
        """(..., 2): d z' / d (w_x, w_y) at nominal board points xy (..., 2); the height is
        linear in the warp (a calibration that fits the warp uses these as its Jacobian)."""
        (cx, cy), (ax, ay) = self.centre_mm, self.half_mm
        u = (xy[..., 0] - cx) / ax
        v = (xy[..., 1] - cy) / ay
        return np.stack([-(1 - u * u), -(1 - v * v)], -1)

    def height(self, xy: np.ndarray) -> np.ndarray:
        """z' (...,) mm of nominal board points xy (..., 2)."""
        return self.warp_basis(xy) @ np.asarray(self.warp_mm, dtype=xy.dtype)

    def points(self, nominal: np.ndarray) -> np.ndarray:
        """Physical board-frame points (N, 3) mm of nominal points (N, 3) on z = 0."""
        nominal = np.asarray(nominal, dtype=np.float64)
        c, s = np.asarray(self.centre_mm), np.asarray(self.scale)
        xy = c + s * (nominal[:, :2] - c)
        return np.column_stack([xy, self.height(nominal[:, :2])])

    def nominal_on_rays(self, xy: np.ndarray, R: np.ndarray, t: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray]:
        """Where the rays (x, y, 1) of normalized coordinates ``xy`` (..., 2) meet the physical
        board at ``cam_from_board = (R, t)``: (nominal board xy (..., 2), depth (...,); the
        point is ``depth * (x, y, 1)``, behind the camera where depth <= 0).

        In the board frame the ray is ``depth * a - b`` with a = R^T (x, y, 1), b = R^T t; the
        surface z' = height(nominal) is met by fixed-point iteration on the depth. Works in the
        dtype of ``xy`` (float32 keeps texel coordinates to 1e-3 texel below 16k texels).
        """
        x, y = xy[..., 0], xy[..., 1]
        a = [x * R[0, k] + y * R[1, k] + R[2, k] for k in range(3)]
        b = R.T @ t
        (cx, cy), (sx, sy) = self.centre_mm, self.scale
        # Rays parallel to the board (a[2] = 0) and a bowed board's iteration on rays that
        # never meet it give inf/NaN depths, which the callers treat as "not on the board".
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            inv_az = 1.0 / a[2]
            z = 0.0
            for _ in range(_INTERSECTION_ITERATIONS if self.warp_mm != (0.0, 0.0) else 1):
                depth = (z + b[2]) * inv_az
                nominal = np.stack([cx + (depth * a[0] - b[0] - cx) / sx,
                                    cy + (depth * a[1] - b[1] - cy) / sy], -1)
                z = self.height(nominal)
        return nominal, depth
