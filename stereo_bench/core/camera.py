"""The camera model: the single source of truth for projection in SynthCal.

Pinhole camera with OpenCV's distortion model and conventions:

* pixel coordinates put the centre of the top-left pixel at (0, 0);
* ``cam_from_world`` maps world points into the camera frame, ``p_cam = R @ p_world + t``,
  with ``R`` stored as a Rodrigues vector ``rvec`` and ``t`` as ``tvec`` (millimetres);
* distortion coefficients in OpenCV's order ``[k1, k2, p1, p2, k3, k4, k5, k6]``, applied to
  normalized undistorted coordinates (x, y) = (X/Z, Y/Z)::

      r2 = x^2 + y^2
      radial = (1 + k1 r2 + k2 r2^2 + k3 r2^3) / (1 + k4 r2 + k5 r2^2 + k6 r2^3)
      xd = x radial + 2 p1 x y + p2 (r2 + 2 x^2)
      yd = y radial + p1 (r2 + 2 y^2) + 2 p2 x y
      u = fx xd + skew yd + cx,   v = fy yd + cy

or, with ``model`` set, a fisheye or omnidirectional lens of lens.py in place of the distortion,
followed by the same (fx, fy, cx, cy, skew).

Every projection function has its analytic Jacobian beside it (tested against finite
differences). Unprojection inverts the distortion by Newton's method to 1e-10 px and refuses
distortions that are not invertible over the image (a fold of the radial map inside it).
"""

from __future__ import annotations


import math
from dataclasses import dataclass, field, replace

import numpy as np

from .files import read_json, write_json
from .distortion import (DistortionNotInvertibleError, distort, distort_with_jacobians,
                         radial_fold_radius, undistort_to)
from .lens import DIST_NAMES, kb_max_theta, lens_model, lens_parameters
from .poses import rodrigues_to_matrix, rotate_jacobian

INTRINSIC_NAMES = ("fx", "fy", "cx", "cy", "skew")
POSE_NAMES = ("rx", "ry", "rz", "tx", "ty", "tz")


# ----------------------------------------------------------------------------------------------
# Rotations (Rodrigues vectors)
# ----------------------------------------------------------------------------------------------


# ----------------------------------------------------------------------------------------------
# Distortion
# ----------------------------------------------------------------------------------------------


# ----------------------------------------------------------------------------------------------
# Projection with Jacobians
# ----------------------------------------------------------------------------------------------

def project_points(
    points: np.ndarray,
    intrinsics: np.ndarray,
    dist: np.ndarray,
    rvec: np.ndarray,
    tvec: np.ndarray,
    model: str = "opencv",
) -> np.ndarray:
    """Project 3D points (N,3) through pose (rvec, tvec) and intrinsics [fx, fy, cx, cy, skew]."""
    return project_with_jacobians(points, intrinsics, dist, rvec, tvec, jacobians=False,
                                  model=model)[0]


def _lens_project_cam(Pc, intrinsics, params, jacobians, model):
    """project_cam_with_jacobians for a lens model of lens.py other than OpenCV's."""
    fx, fy, cx, cy, s = np.asarray(intrinsics, dtype=np.float64)
    m, _, Jm, Jp = lens_model(model).project(Pc, np.asarray(params, dtype=np.float64), jacobians)
    uv = np.stack([fx * m[:, 0] + s * m[:, 1] + cx, fy * m[:, 1] + cy], -1)
    if not jacobians:
        return uv, None
    Ji = np.zeros((len(Pc), 2, 5))
    Ji[:, 0, 0], Ji[:, 1, 1], Ji[:, 0, 2], Ji[:, 1, 3], Ji[:, 0, 4] = m[:, 0], m[:, 1], 1, 1, m[:, 1]
    KJ = np.array([[fx, s], [0.0, fy]])
    return uv, {"point": KJ @ Jm, "intrinsics": Ji, "dist": KJ @ Jp}


def project_cam_with_jacobians(points_cam: np.ndarray, intrinsics: np.ndarray, dist: np.ndarray,
                               jacobians: bool = True, model: str = "opencv"):
    """Project points already in the camera frame (N,3): pixels (N,2) plus, if asked, a dict of
    Jacobians ``point`` (N,2,3) over the camera-frame point, ``intrinsics`` (N,2,5) and ``dist``
    (N,2,k) over the lens model's k parameters (lens.py; OpenCV's 8 by default). What a
    calibration's inner loop needs (its board points are put in the camera frame by its own pose
    step); ``project_with_jacobians`` adds the pose. For OpenCV's model, the 2x2 and 2x3
    products are written out entry by entry: small broadcast matrix products cost more than the
    math, and it is the model of every hot loop."""
    Pc = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
    if model != "opencv":
        return _lens_project_cam(Pc, intrinsics, dist, jacobians, model)
    fx, fy, cx, cy, s = np.asarray(intrinsics, dtype=np.float64)
    inv_z = 1.0 / Pc[:, 2]
    xy = Pc[:, :2] * inv_z[:, None]
    xd, Jxy, Jdist = distort_with_jacobians(xy, dist, wrt_dist=jacobians)
    uv = np.stack([fx * xd[:, 0] + s * xd[:, 1] + cx, fy * xd[:, 1] + cy], -1)
    if not jacobians:
        return uv, None
    N = len(Pc)
    Ji = np.zeros((N, 2, 5))
    Ji[:, 0, 0] = xd[:, 0]
    Ji[:, 1, 1] = xd[:, 1]
    Ji[:, 0, 2] = 1.0
    Ji[:, 1, 3] = 1.0
    Ji[:, 0, 4] = xd[:, 1]
    # d xd / d Pc = Jxy @ [[1/z, 0, -x/z], [0, 1/z, -y/z]], then d uv / d xd = [[fx, s], [0, fy]].
    M = np.empty((N, 2, 3))
    M[:, :, 0] = Jxy[:, :, 0] * inv_z[:, None]
    M[:, :, 1] = Jxy[:, :, 1] * inv_z[:, None]
    M[:, :, 2] = -(M[:, :, 0] * xy[:, 0, None] + M[:, :, 1] * xy[:, 1, None])
    J_point = np.empty((N, 2, 3))
    J_point[:, 0] = fx * M[:, 0] + s * M[:, 1]
    J_point[:, 1] = fy * M[:, 1]
    J_dist = np.empty((N, 2, 8))
    J_dist[:, 0] = fx * Jdist[:, 0] + s * Jdist[:, 1]
    J_dist[:, 1] = fy * Jdist[:, 1]
    return uv, {"point": J_point, "intrinsics": Ji, "dist": J_dist}


def project_with_jacobians(
    points: np.ndarray,
    intrinsics: np.ndarray,
    dist: np.ndarray,
    rvec: np.ndarray,
    tvec: np.ndarray,
    jacobians: bool = True,
    model: str = "opencv",
):
    """Project points (N,3) and return pixels (N,2) plus, if asked, a dict of Jacobians.

    Jacobians: ``point`` (N,2,3), ``intrinsics`` (N,2,5) over [fx, fy, cx, cy, skew],
    ``dist`` (N,2,k) over the lens model's parameters, ``pose`` (N,2,6) over [rvec, tvec].
    """
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    R = rodrigues_to_matrix(rvec)
    Pc = P @ R.T + np.asarray(tvec, dtype=np.float64)
    uv, J = project_cam_with_jacobians(Pc, intrinsics, dist, jacobians, model)
    if not jacobians:
        return uv, None
    J_uv_Pc = J["point"]
    J["pose"] = np.concatenate([J_uv_Pc @ rotate_jacobian(rvec, P), J_uv_Pc], axis=-1)
    J["point"] = J_uv_Pc @ R
    return uv, J


# ----------------------------------------------------------------------------------------------
# The Camera
# ----------------------------------------------------------------------------------------------

def _vec(values, n: int, name: str) -> np.ndarray:
    a = np.asarray(values, dtype=np.float64).reshape(-1)
    if a.shape != (n,) or not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: expected {n} finite numbers, got {values!r}")
    return a


@dataclass(frozen=True, eq=False)
class Camera:
    """A calibrated camera: image size, intrinsics, lens and cam_from_world.

    ``dist`` holds the parameters of the lens ``model`` (lens.py), OpenCV's 8 coefficients by
    default; every projection and unprojection goes through the model."""

    name: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    skew: float = 0.0
    dist: np.ndarray = field(default_factory=lambda: np.zeros(8))
    rvec: np.ndarray = field(default_factory=lambda: np.zeros(3))  # cam_from_world rotation
    tvec: np.ndarray = field(default_factory=lambda: np.zeros(3))  # cam_from_world translation, mm
    model: str = "opencv"

    def __post_init__(self):
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(f"camera {self.name!r}: image size must be positive, got "
                             f"{self.width}x{self.height}")
        if not (self.fx > 0 and self.fy > 0):
            raise ValueError(f"camera {self.name!r}: fx and fy must be positive, got "
                             f"{self.fx}, {self.fy}")
        d = np.asarray(self.dist, dtype=np.float64).reshape(-1)
        if self.model == "opencv" and d.size > 8:
            raise ValueError(f"camera {self.name!r}: dist has {d.size} coefficients, expected "
                             f"at most 8 {list(DIST_NAMES)}")
        object.__setattr__(self, "dist", lens_parameters(self.model, d, f"camera {self.name!r}"))
        object.__setattr__(self, "rvec", _vec(self.rvec, 3, f"camera {self.name!r}: rvec"))
        object.__setattr__(self, "tvec", _vec(self.tvec, 3, f"camera {self.name!r}: tvec"))
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        for k in ("fx", "fy", "cx", "cy", "skew"):
            object.__setattr__(self, k, float(getattr(self, k)))

    # --- parameter views --------------------------------------------------------------------
    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, self.skew, self.cx], [0.0, self.fy, self.cy], [0, 0, 1.0]])

    @property
    def intrinsics(self) -> np.ndarray:
        """[fx, fy, cx, cy, skew]."""
        return np.array([self.fx, self.fy, self.cx, self.cy, self.skew])

    @property
    def R(self) -> np.ndarray:
        """Rotation of cam_from_world."""
        return rodrigues_to_matrix(self.rvec)

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates (mm)."""
        return -self.R.T @ self.tvec

    @property
    def size(self) -> tuple[int, int]:
        return (self.width, self.height)

    @property
    def dist_names(self) -> tuple[str, ...]:
        """The names of the lens model's parameters, in the order of ``dist``."""
        return lens_model(self.model).param_names

    @property
    def max_normalized_radius(self) -> float:
        """Radius of (X/Z, Y/Z) beyond which a ray in front of the camera has no unique pixel
        (OpenCV's radial fold; a fisheye's field of view when under 180 degrees); inf where
        the model's limit is not a cone about the axis (the omnidirectional models say per
        ray)."""
        if self.model == "opencv":
            return radial_fold_radius(self.dist)
        if self.model == "kannala_brandt":
            theta = kb_max_theta(tuple(self.dist.tolist()))
            return math.tan(theta) if theta < math.pi / 2 else math.inf
        return math.inf

    def with_params(self, **changes) -> "Camera":
        return replace(self, **changes)

    @classmethod
    def from_K(cls, name, width, height, K, dist=(), rvec=(0, 0, 0), tvec=(0, 0, 0),
               model="opencv"):
        K = np.asarray(K, dtype=np.float64)
        return cls(name, width, height, K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1],
                   np.asarray(dist, dtype=np.float64), np.asarray(rvec), np.asarray(tvec), model)

    # --- geometry ---------------------------------------------------------------------------
    def world_to_cam(self, points: np.ndarray) -> np.ndarray:
        """World points (..., 3) -> camera-frame points (..., 3)."""
        return np.asarray(points, dtype=np.float64) @ self.R.T + self.tvec

    def project(self, points_world: np.ndarray) -> np.ndarray:
        """World points (..., 3) -> pixels (..., 2), with distortion."""
        P = np.asarray(points_world, dtype=np.float64)
        uv = project_points(P.reshape(-1, 3), self.intrinsics, self.dist, self.rvec, self.tvec,
                            self.model)
        return uv.reshape(P.shape[:-1] + (2,))

    def project_cam(self, points_cam: np.ndarray) -> np.ndarray:
        """Camera-frame points (..., 3) -> pixels (..., 2)."""
        P = np.asarray(points_cam, dtype=np.float64)
        if self.model != "opencv":
            uv = project_cam_with_jacobians(P.reshape(-1, 3), self.intrinsics, self.dist, False,
                                            self.model)[0]
            return uv.reshape(P.shape[:-1] + (2,))
        return self.normalized_to_pixels(P[..., :2] / P[..., 2:3])

    def sees(self, points_cam: np.ndarray) -> np.ndarray:
        """(...,) bool: the camera-frame points (..., 3) lie where the lens projects one to
        one (in front of a pinhole camera inside its fold; inside a fisheye's field of view)."""
        P = np.asarray(points_cam, dtype=np.float64)
        flat = P.reshape(-1, 3)
        valid = lens_model(self.model).project(flat, self.dist, False)[1]
        return valid.reshape(P.shape[:-1])

    def normalized_to_pixels(self, xy: np.ndarray) -> np.ndarray:
        """Undistorted normalized coordinates (..., 2) (the ray (x, y, 1)) -> pixels (..., 2)."""
        xy = np.asarray(xy, dtype=np.float64)
        if self.model != "opencv":
            return self.project_cam(np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], -1))
        xd = distort(xy, self.dist)
        return np.stack([self.fx * xd[..., 0] + self.skew * xd[..., 1] + self.cx,
                         self.fy * xd[..., 1] + self.cy], -1)

    def normalized_jacobian(self, xy: np.ndarray) -> np.ndarray:
        """d pixels / d (x, y) (N, 2, 2) at undistorted normalized coordinates xy (N, 2)."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        if self.model == "opencv":
            return self.K[:2, :2] @ distort_with_jacobians(xy, self.dist, wrt_dist=False)[1]
        P = np.concatenate([xy, np.ones((len(xy), 1))], -1)
        J = project_cam_with_jacobians(P, self.intrinsics, self.dist, True, self.model)[1]
        return J["point"][:, :, :2]

    def pixels_to_distorted_normalized(self, uv: np.ndarray) -> np.ndarray:
        uv = np.asarray(uv, dtype=np.float64)
        yd = (uv[..., 1] - self.cy) / self.fy
        xd = (uv[..., 0] - self.cx - self.skew * yd) / self.fx
        return np.stack([xd, yd], -1)

    def undistorted(self, uv: np.ndarray, tol_px: float = 1e-10) -> tuple[np.ndarray, np.ndarray]:
        """(undistorted normalized xy (..., 2), valid (...)): valid where Newton's iteration
        converged inside the radial fold, i.e. where the pixel has exactly one ray (for other
        lens models, a ray in front of the camera's plane)."""
        if self.model == "opencv":
            return undistort_to(uv, self.dist, tol_px / max(self.fx, self.fy), 50,
                                self.pixels_to_distorted_normalized, radial_fold_radius(self.dist))
        rays, valid = self.rays(uv)
        valid &= rays[..., 2] > 0
        with np.errstate(divide="ignore", invalid="ignore"):
            return rays[..., :2] / rays[..., 2:], valid

    def rays(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(unit rays (..., 3), valid (...)) of pixels (..., 2) through the lens model."""
        uv = np.asarray(uv, dtype=np.float64)
        m = self.pixels_to_distorted_normalized(uv.reshape(-1, 2))
        rays, valid = lens_model(self.model).unproject(m, self.dist)
        return rays.reshape(uv.shape[:-1] + (3,)), valid.reshape(uv.shape[:-1])

    def within_image_circle(self, uv: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) moved toward the principal point, in 1 % steps, until they have a ray:
        a wide lens's image corners that lie beyond its image circle land on its edge."""
        uv = np.asarray(uv, dtype=np.float64)
        centre = np.array([self.cx, self.cy])
        inner = centre + (uv - centre) * np.linspace(1, 0, 101)[:, None, None]
        return inner[np.argmax(self.has_ray(inner), axis=0), np.arange(len(uv))]

    def has_ray(self, uv: np.ndarray) -> np.ndarray:
        """(...,) bool: the pixel (..., 2) sees along one ray (outside a circular fisheye's
        image circle, or beyond a fold, it does not)."""
        return self.rays(uv)[1]

    def invertible(self, uv: np.ndarray, tol_px: float = 1e-10) -> np.ndarray:
        """(...,) bool: the pixel (..., 2) has a unique ray (an estimated distortion can fold
        or have a pole inside the image, TRAPS.md; a wide lens has none beyond its image
        circle)."""
        if self.model != "opencv":
            return self.has_ray(uv)
        return self.undistorted(uv, tol_px)[1]

    def unproject(self, uv: np.ndarray, tol_px: float = 1e-10) -> np.ndarray:
        """Pixels (..., 2) -> undistorted normalized coordinates (..., 2) (rays (x, y, 1)).

        Newton's iteration to ``tol_px`` in pixels. Raises DistortionNotInvertibleError when a
        pixel lies beyond the fold of the radial distortion or the iteration does not converge.
        """
        xy, valid = self.undistorted(uv, tol_px)
        if not np.all(valid) and self.model != "opencv":
            where = np.asarray(uv)[~valid][0]
            raise DistortionNotInvertibleError(
                f"camera {self.name!r}: pixel ({where[0]:.1f}, {where[1]:.1f}) has no ray in "
                f"front of the camera through the {self.model} lens {self.dist.tolist()} "
                f"({int((~valid).sum())} pixels)")
        if not np.all(valid):
            bad = ~valid
            where = np.asarray(uv)[bad][0]
            raise DistortionNotInvertibleError(
                f"camera {self.name!r}: distortion {self.dist.tolist()} is not invertible at "
                f"pixel ({where[0]:.1f}, {where[1]:.1f}) ({int(bad.sum())} pixels): the radial "
                f"map folds at normalized radius {radial_fold_radius(self.dist):.4g}; reduce "
                f"|k| or the image size")
        return xy

    def unproject_rays(self, uv: np.ndarray) -> np.ndarray:
        """Pixels (..., 2) -> unit ray directions in the camera frame (..., 3); beyond 90
        degrees off axis for the lens models that see there."""
        if self.model != "opencv":
            rays, valid = self.rays(uv)
            if not np.all(valid):
                where = np.asarray(uv)[~valid][0]
                raise DistortionNotInvertibleError(
                    f"camera {self.name!r}: pixel ({where[0]:.1f}, {where[1]:.1f}) has no ray "
                    f"through the {self.model} lens {self.dist.tolist()} "
                    f"({int((~valid).sum())} pixels)")
            return rays
        xy = self.unproject(uv)
        d = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], -1)
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def pixel_grid(self, step: int = 1) -> np.ndarray:
        """Pixel centres (H', W', 2) on a regular grid covering the image (OpenCV centres)."""
        u = np.arange(0, self.width, step, dtype=np.float64)
        v = np.arange(0, self.height, step, dtype=np.float64)
        return np.stack(np.meshgrid(u, v), -1)

    def check_invertible(self, step: int = 8) -> None:
        """Raise DistortionNotInvertibleError if any pixel (on a grid plus the border) has no ray."""
        border = np.concatenate([
            np.stack([np.arange(self.width), np.zeros(self.width)], -1),
            np.stack([np.arange(self.width), np.full(self.width, self.height - 1)], -1),
            np.stack([np.zeros(self.height), np.arange(self.height)], -1),
            np.stack([np.full(self.height, self.width - 1), np.arange(self.height)], -1),
        ])
        uv = np.concatenate([self.pixel_grid(step).reshape(-1, 2), border])
        if self.model != "opencv":
            # A wide lens ends at its image circle: pixels beyond it see nothing (black, as the
            # renderer paints them), and no pixel inside has two rays (lens.py's valid region).
            return
        self.unproject(uv)

    # --- serialization ----------------------------------------------------------------------
    def to_dict(self) -> dict:
        lens = {} if self.model == "opencv" else {"model": self.model}
        return {
            "name": self.name, "width": self.width, "height": self.height,
            "fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy, "skew": self.skew,
            **lens, "dist": dict(zip(self.dist_names, self.dist.tolist())),
            "cam_from_world": {"rvec": self.rvec.tolist(), "tvec_mm": self.tvec.tolist()},
        }

    @classmethod
    def from_dict(cls, d: dict, source: str = "camera") -> "Camera":
        try:
            model = str(d.get("model", "opencv"))
            names = lens_model(model).param_names
            dist = d.get("dist", {})
            if isinstance(dist, dict):
                unknown = set(dist) - set(names)
                if unknown:
                    raise ValueError(f"unknown coefficients {sorted(unknown)} of the {model} "
                                     f"lens; expected {list(names)}")
                dist = [float(dist.get(k, 0.0)) for k in names]
            pose = d.get("cam_from_world", {})
            return cls(str(d["name"]), int(d["width"]), int(d["height"]), float(d["fx"]),
                       float(d["fy"]), float(d["cx"]), float(d["cy"]), float(d.get("skew", 0.0)),
                       np.asarray(dist, dtype=np.float64), pose.get("rvec", [0, 0, 0]),
                       pose.get("tvec_mm", [0, 0, 0]), model)
        except KeyError as e:
            raise ValueError(f"{source}: missing field {e.args[0]!r}") from None
        except (TypeError, ValueError) as e:
            raise ValueError(f"{source}: {e}") from None

    def save_json(self, path) -> None:
        write_json(path, self.to_dict())

    @classmethod
    def load_json(cls, path) -> "Camera":
        try:
            d = read_json(path)
        except OSError as e:
            raise ValueError(f"{path}: cannot read camera JSON ({e})") from None
        return cls.from_dict(d, source=str(path))
