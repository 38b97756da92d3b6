"""A rig in motion: true cameras, the board, and the paper's conical-spring trajectory.

The board centre follows a helix around the rig's viewing axis whose radius grows linearly with
depth (a conical spring, paper Sec. 2), with the board always facing the rig's centre and
tilted by a fixed angle about an axis that turns at a different rate than the helix, plus an
in-plane roll, so that the views span the orientations planar calibration needs (Zhang 2000:
views must not be parallel). Ground truth: per camera and frame, the true image positions of
the board's feature points and whether each one is seen.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .camera import Camera, matrix_to_rodrigues, radial_fold_radius, rodrigues_to_matrix
from .config import RigConfig, TrajectoryConfig
from .patterns import pattern_from_config


@dataclass(frozen=True, eq=False)
class Trajectory:
    """world_from_board per frame: rotations as Rodrigues vectors (F,3), translations (F,3) mm."""

    rvecs: np.ndarray
    tvecs: np.ndarray

    def __len__(self) -> int:
        return len(self.rvecs)

    @property
    def rotations(self) -> np.ndarray:
        return rodrigues_to_matrix(self.rvecs)


def _axis_angle(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    return rodrigues_to_matrix(axis * angle[..., None])


def half_fov(cameras: list[Camera]) -> tuple[float, float]:
    """tan of the half field of view, horizontal and vertical, of the narrowest camera
    (from the undistorted rays of the image's edge midpoints)."""
    tans = []
    for cam in cameras:
        w, h = cam.width - 1, cam.height - 1
        xy = np.abs(cam.unproject(np.array([[0, h / 2], [w, h / 2], [w / 2, 0], [w / 2, h]])))
        tans.append((min(xy[0, 0], xy[1, 0]), min(xy[2, 1], xy[3, 1])))
    return tuple(np.min(tans, axis=0))


def spring_extent(cameras: list[Camera], board_radius: float, cfg: TrajectoryConfig):
    """(near, far) depth and, per depth end, the helix's (horizontal, vertical) semi-axes, in mm.

    Unset values keep the board in view while covering as much of the images as that allows:
    at the near end the board's circumscribed circle spans 90 % of the narrower half field of
    view, the far end is twice as deep, and the helix is an ellipse that uses 85 % of the room
    each field of view leaves around the board at that depth (wider images give a wider helix,
    so the board reaches the image corners, which constrain the distortion). A configured
    ``radius_mm`` makes the helix circular. Frames where part of the board still leaves an image
    are reported, not hidden.
    """
    tan_h, tan_v = half_fov(cameras)
    near = board_radius / (0.9 * min(tan_h, tan_v))
    depth = cfg.depth_mm or (near, 2.0 * near)
    if cfg.radius_mm:
        return depth, [(r, r) for r in cfg.radius_mm]
    return depth, [(max(0.0, 0.85 * (tan_h * d - board_radius)),
                    max(0.0, 0.85 * (tan_v * d - board_radius))) for d in depth]


def conical_spring(
    cameras: list[Camera], board_centre: np.ndarray, board_radius: float, cfg: TrajectoryConfig
) -> Trajectory:
    """world_from_board poses along the conical spring in front of ``cameras``.

    ``board_centre`` (3,) is the board-frame point that travels on the spring (the middle of the
    feature points), ``board_radius`` the radius (mm) of the board outline around it. Depth is
    measured along the rig's mean optical axis from the mean camera centre.
    """
    centres = np.stack([c.center for c in cameras])
    rig_centre = centres.mean(0)
    axis = np.stack([c.R[2] for c in cameras]).mean(0)
    if np.linalg.norm(axis) < 0.3:
        raise ValueError("cameras: their optical axes point in opposing directions (mean axis "
                         f"length {np.linalg.norm(axis):.2f}); the conical spring is built along "
                         "the rig's common viewing direction, which such a rig does not have")
    axis /= np.linalg.norm(axis)
    # Image "right" of the rig, orthogonal to the axis: keeps the board upright in the images.
    right = np.stack([c.R[0] for c in cameras]).mean(0)
    right -= (right @ axis) * axis
    right /= np.linalg.norm(right)
    down = np.cross(axis, right)

    (d0, d1), (r0, r1) = spring_extent(cameras, board_radius, cfg)
    s = np.linspace(0.0, 1.0, cfg.frames)
    phi = 2 * np.pi * cfg.turns * s
    depth = d0 + (d1 - d0) * s
    semi = np.asarray(r0) + np.outer(s, np.subtract(r1, r0))  # (F, 2) horizontal, vertical
    p = (rig_centre + depth[:, None] * axis + (semi[:, :1] * np.cos(phi)[:, None]) * right
         + (semi[:, 1:] * np.sin(phi)[:, None]) * down)

    # Facing frame: z from the rig centre through the board centre (OpenCV boards have +z
    # pointing away from a camera that sees their front), x as close to the rig's right as can be.
    z = p - rig_centre
    z /= np.linalg.norm(z, axis=1, keepdims=True)
    x = right - (z @ right)[:, None] * z
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    y = np.cross(z, x)
    facing = np.stack([x, y, z], axis=-1)  # columns: board axes in world

    # Tilt about an in-plane axis turning 2.7x faster than the helix (incommensurate, so the
    # tilt directions do not repeat with the spring), then roll about the board normal.
    psi = 2.7 * phi
    tilt_axis = np.stack([np.cos(psi), np.sin(psi), np.zeros_like(psi)], -1)
    tilt = _axis_angle(tilt_axis, np.full_like(psi, np.radians(cfg.tilt_deg)))
    roll = _axis_angle(np.array([0.0, 0.0, 1.0]), np.radians(cfg.roll_deg) * np.sin(1.3 * phi))
    R = facing @ tilt @ roll
    t = p - R @ board_centre
    return Trajectory(matrix_to_rodrigues(R), t)


@dataclass(frozen=True, eq=False)
class GroundTruth:
    """Exact image positions of the feature points.

    points: (C, F, N, 2) px, OpenCV pixel centres; visible: (C, F, N) bool — in front of the
    camera, on the board's front side, inside the image and inside the distortion's valid radius.
    """

    points: np.ndarray
    visible: np.ndarray


@dataclass(frozen=True, eq=False)
class Rig:
    """Everything a render needs: the true cameras, the board and its trajectory."""

    name: str
    seed: int
    cameras: list[Camera]
    pattern: object
    trajectory: Trajectory

    @classmethod
    def from_config(cls, cfg: RigConfig) -> "Rig":
        cameras = cfg.cameras_true()
        for cam in cameras:
            cam.check_invertible(step=max(cam.width // 64, 4))
        pattern = pattern_from_config(cfg.pattern.kind, **cfg.pattern.overrides())
        obj = pattern.object_points()
        centre = 0.5 * (obj.min(0) + obj.max(0))
        w, h = pattern.size_mm
        return cls(cfg.name, cfg.seed, cameras, pattern,
                   conical_spring(cameras, centre, 0.5 * np.hypot(w, h), cfg.trajectory))

    def board_points_world(self) -> np.ndarray:
        """Feature points in the world per frame, (F, N, 3) mm."""
        obj = self.pattern.object_points()
        R = self.trajectory.rotations
        return np.einsum("fij,nj->fni", R, obj) + self.trajectory.tvecs[:, None, :]

    def cam_from_board(self, cam: Camera) -> tuple[np.ndarray, np.ndarray]:
        """Per-frame cam_from_board as (R (F,3,3), t (F,3))."""
        Rwb = self.trajectory.rotations
        R = cam.R @ Rwb
        t = (cam.R @ self.trajectory.tvecs.T).T + cam.tvec
        return R, t

    def ground_truth(self) -> GroundTruth:
        Xw = self.board_points_world()
        F, N, _ = Xw.shape
        pts = np.zeros((len(self.cameras), F, N, 2))
        vis = np.zeros((len(self.cameras), F, N), dtype=bool)
        for c, cam in enumerate(self.cameras):
            Pc = cam.world_to_cam(Xw)
            R, _ = self.cam_from_board(cam)
            # Front side: the board's +z points away from the camera.
            normal_cam = R[:, :, 2]
            front = np.einsum("fi,fni->fn", normal_cam, Pc) > 0
            z = Pc[..., 2]
            ahead = z > 1e-6
            xy = Pc[..., :2] / np.where(ahead, z, 1.0)[..., None]
            valid = np.linalg.norm(xy, axis=-1) < radial_fold_radius(cam.dist)
            uv = cam.normalized_to_pixels(xy)
            inside = ((uv[..., 0] >= 0) & (uv[..., 0] <= cam.width - 1)
                      & (uv[..., 1] >= 0) & (uv[..., 1] <= cam.height - 1))
            pts[c] = uv
            vis[c] = front & ahead & valid & inside
        return GroundTruth(pts, vis)

    def coverage(self, gt: GroundTruth | None = None) -> dict[str, dict]:
        """Per camera, how the board is seen: ``frames_in_view`` (some feature visible),
        ``frames_partly_out`` (some but not all visible: the frame indices), and ``span_px``,
        the largest extent (bounding-box diagonal) of the visible features over all frames."""
        gt = gt or self.ground_truth()
        out = {}
        for c, cam in enumerate(self.cameras):
            vis = gt.visible[c]
            some, every = vis.any(axis=1), vis.all(axis=1)
            span = 0.0
            for f in np.flatnonzero(some):
                p = gt.points[c, f][vis[f]]
                span = max(span, float(np.linalg.norm(p.max(0) - p.min(0))))
            out[cam.name] = {"frames_in_view": int(some.sum()),
                             "frames_partly_out": np.flatnonzero(some & ~every).tolist(),
                             "span_px": span}
        return out


#: Below this extent in an image, no detector finds a board (a 9x12 checkerboard's squares would
#: be 2 px wide); a camera that never sees it larger cannot be calibrated.
MIN_BOARD_SPAN_PX = 20.0


def coverage_warnings(coverage: dict[str, dict], frames: int) -> tuple[list[str], list[str]]:
    """(warnings, unusable cameras) for a dataset's coverage (``Rig.coverage``)."""
    warnings, unusable = [], []
    for name, c in coverage.items():
        if c["frames_in_view"] == 0:
            warnings.append(f"camera {name!r}: the board is never in view")
            unusable.append(name)
        elif c["span_px"] < MIN_BOARD_SPAN_PX:
            warnings.append(f"camera {name!r}: the board spans at most {c['span_px']:.1f} px "
                            f"(below {MIN_BOARD_SPAN_PX:.0f} px no detector finds it): check "
                            f"the camera's focal length and trajectory.depth_mm")
            unusable.append(name)
        elif c["frames_partly_out"]:
            warnings.append(f"camera {name!r}: the board is partly out of view in "
                            f"{len(c['frames_partly_out'])} of {frames} frames")
        if c["frames_in_view"] and c["frames_in_view"] < frames:
            warnings.append(f"camera {name!r}: the board is out of view in "
                            f"{frames - c['frames_in_view']} of {frames} frames")
    return warnings, unusable
