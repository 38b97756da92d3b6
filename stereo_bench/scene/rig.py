"""A rig in motion: true cameras, the board, and its trajectory.

Two trajectories. The paper's conical spring, for rigs whose cameras look the same way: the
board centre follows a helix around the rig's viewing axis whose radius grows linearly with
depth (paper Sec. 2), with the board always facing the rig's centre and tilted by a fixed angle
about an axis that turns at a different rate than the helix, plus an in-plane roll, so that the
views span the orientations planar calibration needs (Zhang 2000: views must not be parallel).
And a calibration session, for studios that surround the volume: the board carried through the
volume and turned about the vertical so that it faces each camera in turn (a camera sees only
the frames in which the board's printed front faces it), then optionally waved close in front
of each camera in turn (that camera's own conical spring), as studios do for intrinsics.
Ground truth: per camera and frame, the true image positions of the board's feature points and
whether each one is seen.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.board_shape import BoardShape
from ..core.camera import Camera
from ..core.poses import matrix_to_rodrigues, rodrigues_to_matrix
from ..config.schema import RigConfig, TrajectoryConfig
from ..core.patterns import pattern_from_config


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


WIDE_HALF_FOV_DEG = 60.0


def half_fov(cameras: list[Camera]) -> tuple[float, float]:
    """tan of the half field of view, horizontal and vertical, of the narrowest camera
    (from the undistorted rays of the image's edge midpoints)."""
    tans = []
    for cam in cameras:
        w, h = cam.width - 1, cam.height - 1
        edges = np.array([[0, h / 2], [w, h / 2], [w / 2, 0], [w / 2, h]])
        if cam.model == "opencv":
            xy = np.abs(cam.unproject(edges))
        else:
            # A wide lens: the edges' rays (the image circle's where an edge lies beyond it),
            # capped at WIDE_HALF_FOV_DEG, past which a flat board is seen too edge-on to help.
            rays = cam.unproject_rays(cam.within_image_circle(edges))
            angle = np.minimum(np.arccos(np.clip(rays[:, 2], -1, 1)),
                               np.radians(WIDE_HALF_FOV_DEG))
            xy = np.tan(angle)[:, None] * np.ones((1, 2))
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
    rig_centre, axis, right, down = _rig_frame(cameras)
    (d0, d1), (r0, r1) = spring_extent(cameras, board_radius, cfg)
    s = np.linspace(0.0, 1.0, cfg.frames)
    phi = 2 * np.pi * cfg.turns * s
    depth = d0 + (d1 - d0) * s
    semi = np.asarray(r0) + np.outer(s, np.subtract(r1, r0))  # (F, 2) horizontal, vertical
    p = (rig_centre + depth[:, None] * axis + (semi[:, :1] * np.cos(phi)[:, None]) * right
         + (semi[:, 1:] * np.sin(phi)[:, None]) * down)

    return _facing(p, rig_centre, right, phi, board_centre, cfg)


def _rig_frame(cameras: list[Camera]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(centre, viewing axis, right, down) of a rig that looks one way: the mean camera centre,
    the mean optical axis, and the cameras' mean image right and down orthogonal to it."""
    centres = np.stack([c.center for c in cameras])
    axis = np.stack([c.R[2] for c in cameras]).mean(0)
    if np.linalg.norm(axis) < 0.3:
        raise ValueError("cameras: their optical axes point in opposing directions (mean axis "
                         f"length {np.linalg.norm(axis):.2f}); the conical spring is built along "
                         "the rig's common viewing direction, which such a rig does not have: "
                         "for a studio that surrounds the volume, use trajectory.kind: session")
    axis /= np.linalg.norm(axis)
    # Image "right" of the rig, orthogonal to the axis: keeps the board upright in the images.
    right = np.stack([c.R[0] for c in cameras]).mean(0)
    right -= (right @ axis) * axis
    right /= np.linalg.norm(right)
    return centres.mean(0), axis, right, np.cross(axis, right)


def _facing(p: np.ndarray, rig_centre: np.ndarray, right: np.ndarray, phi: np.ndarray,
            board_centre: np.ndarray, cfg: TrajectoryConfig) -> Trajectory:
    """world_from_board poses with the board centre at ``p`` (F, 3) facing ``rig_centre``,
    upright along ``right``, tilted and rolled at rates set by the phase ``phi`` (F,)."""
    # Facing frame: z from the rig centre through the board centre (OpenCV boards have +z
    # pointing away from a camera that sees their front), x as close to the rig's right as can be.
    z = p - rig_centre
    z /= np.linalg.norm(z, axis=1, keepdims=True)
    x = right - (z @ right)[:, None] * z
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    y = np.cross(z, x)
    facing = np.stack([x, y, z], axis=-1)  # columns: board axes in world

    # Tilt about an in-plane axis turning 2.7x faster than phi (incommensurate, so the tilt
    # directions do not repeat with the path), then roll about the board normal.
    psi = 2.7 * phi
    tilt_axis = np.stack([np.cos(psi), np.sin(psi), np.zeros_like(psi)], -1)
    tilt = _axis_angle(tilt_axis, np.full_like(psi, np.radians(cfg.tilt_deg)))
    roll = _axis_angle(np.array([0.0, 0.0, 1.0]), np.radians(cfg.roll_deg) * np.sin(1.3 * phi))
    R = facing @ tilt @ roll
    t = p - R @ board_centre
    return Trajectory(matrix_to_rodrigues(R), t)


DOME_NEAR_HALF_ANGLE_DEG = 20.0  # a dome's near board spans 40 degrees of the lens by default


def lens_reach_deg(cameras: list[Camera]) -> float:
    """How far off axis (degrees) the narrowest camera sees toward its image edges: the least
    angle of the rays of its edges' midpoints (pulled inside a circular fisheye's image
    circle). Past 90 degrees for a wide lens that sees behind its plane."""
    reach = []
    for cam in cameras:
        w, h = cam.width - 1, cam.height - 1
        edges = np.array([[0, h / 2], [w, h / 2], [w / 2, 0], [w / 2, h]])
        rays = cam.unproject_rays(cam.within_image_circle(edges))
        reach.append(np.degrees(np.arccos(np.clip(rays[:, 2], -1, 1))).min())
    return float(min(reach))


def dome(cameras: list[Camera], board_centre: np.ndarray, board_radius: float,
         cfg: TrajectoryConfig) -> Trajectory:
    """world_from_board poses over the whole field of a wide lens: the board centre on
    directions spread evenly over the cap up to ``max_angle_deg`` off the rig's viewing axis
    (default: the lens's reach toward its image edges, less the board's own angular radius),
    past 90 degrees for a lens that sees behind its plane, at depths alternating over
    ``depth_mm`` (default: near enough that the board spans 40 degrees, and twice that), each
    facing the rig, tilted and rolled as the spring's boards are.

    Directions follow the golden-angle spiral (frame i at polar angle max * sqrt((i + 0.5) /
    F), azimuth i * 137.5 degrees): an even cover of the cap for any number of frames."""
    rig_centre, axis, right, down = _rig_frame(cameras)
    near = board_radius / np.tan(np.radians(DOME_NEAR_HALF_ANGLE_DEG))
    d0, d1 = cfg.depth_mm or (near, 2.0 * near)
    F = cfg.frames
    i = np.arange(F)
    depth = d0 + (d1 - d0) * ((i * 0.6180339887) % 1.0)
    if cfg.max_angle_deg is not None:
        top = np.full(F, np.radians(cfg.max_angle_deg))
    else:
        # The board's whole outline inside the lens's reach at each frame's depth.
        top = np.radians(lens_reach_deg(cameras)) - np.arctan(board_radius / depth)
    if (top <= 0).any():
        raise ValueError(f"trajectory.depth_mm: a board of radius {board_radius:.0f} mm at "
                         f"{depth.min():.0f} mm fills more than the lens's field")
    polar = top * np.sqrt((i + 0.5) / F)
    phi = i * np.radians(137.50776405)
    direction = (np.cos(polar)[:, None] * axis
                 + np.sin(polar)[:, None] * (np.cos(phi)[:, None] * right
                                             + np.sin(phi)[:, None] * down))
    return _facing(rig_centre + depth[:, None] * direction, rig_centre, right, phi,
                   board_centre, cfg)


def world_up(cameras: list[Camera]) -> np.ndarray:
    """The world's up direction seen by upright cameras (unit, (3,)).

    An upright camera's image x axis is horizontal however far it looks down, so up is the
    normal of the plane the cameras' x axes span (the least eigenvector of sum x x^T), on the
    side of their image -y axes. The mean of the -y axes alone tilts towards where cameras
    that look down look (7 degrees on a half ring). When the x axes span no clear plane (nearly
    parallel, as for a pair looking one way), the mean -y axis is all there is.
    """
    x = np.stack([c.R[0] for c in cameras])
    mean_up = -np.stack([c.R[1] for c in cameras]).mean(0)
    if np.linalg.norm(mean_up) < 0.3:
        raise ValueError("cameras: their image 'up' directions disagree (e.g. a camera rolled "
                         "by 180 degrees), so the vertical is unknown; give every camera the "
                         "same up")
    mean_up /= np.linalg.norm(mean_up)
    w, v = np.linalg.eigh(x.T @ x)
    normal = v[:, 0] * np.sign(v[:, 0] @ mean_up)
    # Nearly parallel x axes (a pair, a bar) span a plane that any roll tilts: its normal may
    # then lie anywhere near the optical axis, so keep the mean up unless the plane is clear.
    if w[1] < 0.1 * len(cameras) or normal @ mean_up < 0.5:
        return mean_up
    return normal


def ground_axes(up: np.ndarray, towards: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (e1, e2 = up x e1) spanning the ground plane across the unit ``up``:
    e1 along ``towards`` projected onto it (default: the world axis most orthogonal to up).
    ValueError when ``towards`` is (nearly) vertical."""
    if towards is None:
        towards = np.eye(3)[np.argmin(np.abs(up))]
    e1 = towards - (towards @ up) * up
    if np.linalg.norm(e1) < 1e-6 * np.linalg.norm(towards):
        raise ValueError("the direction is vertical: it has no horizontal part")
    e1 = e1 / np.linalg.norm(e1)
    return e1, np.cross(up, e1)


def volume_centre(cameras: list[Camera]) -> np.ndarray:
    """The point nearest to every camera's optical axis (least squares), (3,) mm: for cameras
    that all look at one point, that point. Raises ValueError when the axes are (nearly)
    parallel, as for a stereo pair: such a rig has no centre to surround."""
    A, b = np.zeros((3, 3)), np.zeros(3)
    for c in cameras:
        P = np.eye(3) - np.outer(c.R[2], c.R[2])  # projects out the axis direction
        A += P
        b += P @ c.center
    w = np.linalg.eigvalsh(A)
    if w[0] < 0.05 * len(cameras):
        axes = np.stack([c.R[2] for c in cameras])
        if (axes @ axes[0]).min() < 0:  # some look back along the same line
            raise ValueError("cameras: their optical axes lie (nearly) on one line, facing each "
                             "other, so no single point is nearest to them: put the cameras at "
                             "different heights or add a camera off that line")
        raise ValueError("cameras: their optical axes are nearly parallel, so they do not meet "
                         "around a capture volume; a session trajectory needs cameras that "
                         "surround it (use trajectory.kind: spring for a rig that looks one way)")
    return np.linalg.solve(A, b)


def _rotation_about(axis_index: int, angle: np.ndarray) -> np.ndarray:
    axis = np.zeros(3)
    axis[axis_index] = 1.0
    return _axis_angle(axis, angle)


def session(cameras: list[Camera], board_centre: np.ndarray, board_radius: float,
            cfg: TrajectoryConfig, rng: np.random.Generator) -> tuple[Trajectory, np.ndarray]:
    """world_from_board poses of a studio calibration session, and per frame the index of the
    camera whose close-up it is (-1 for the walk). See the module notes and TrajectoryConfig.

    The walk: the board centre follows a 3:2 Lissajous curve of radius ``walk_radius_mm``
    (default: 35 % of the nearest camera's horizontal distance) around the volume's centre,
    while its height oscillates over ``height_mm`` (default: the centre +- 500 mm, at most 15 %
    of that distance) at an incommensurate rate; its printed front faces the horizontal
    direction psi, which turns ``turns`` times, starting towards the first camera; it is tilted
    about its own x and y axes (up to ``tilt_deg``) and rolled (up to ``roll_deg``) at rates
    incommensurate with the turn, so that each camera sees it from varied angles. No operator
    walks the same path twice: the phases of every oscillation and the start of the turn
    (within half the angle between neighbouring cameras) are drawn from ``rng`` (the rig's
    seed), so that trials of a clean studio differ too.
    """
    centre, up = volume_centre(cameras), world_up(cameras)
    try:
        e1, e2 = ground_axes(up, cameras[0].center - centre)
    except ValueError:
        raise ValueError(f"camera {cameras[0].name!r}: directly above or below the volume's "
                         "centre; a session needs it to stand around the volume") from None
    horizontal = []
    for c in cameras:
        v = c.center - centre
        horizontal.append(np.linalg.norm(v - (v @ up) * up))
    reach = min(horizontal)
    r = cfg.walk_radius_mm if cfg.walk_radius_mm is not None else 0.35 * reach
    half = min(500.0, 0.15 * reach)
    lo, hi = cfg.height_mm if cfg.height_mm is not None else (
        centre @ up - half, centre @ up + half)

    s = np.linspace(0.0, 1.0, cfg.frames)
    tau = 2 * np.pi * s
    phase = rng.uniform(0.0, 2 * np.pi, 6)
    height = 0.5 * (lo + hi) + 0.5 * (hi - lo) * np.sin(5.3 * tau + phase[0])
    p = (centre - (centre @ up) * up + height[:, None] * up
         + r * np.sin(3 * tau + phase[1])[:, None] * e1
         + r * np.sin(2 * tau + phase[2])[:, None] * e2)
    psi = cfg.turns * tau + rng.uniform(-0.5, 0.5) * np.pi / len(cameras)
    facing_dir = np.cos(psi)[:, None] * e1 + np.sin(psi)[:, None] * e2  # towards the viewers
    z = -facing_dir  # OpenCV boards: +z points away from a camera that sees the front
    y = np.broadcast_to(-up, z.shape)  # the board's y runs down, as in an upright camera
    x = np.cross(y, z)
    facing = np.stack([x, y, z], axis=-1)
    tilt = np.radians(cfg.tilt_deg)
    R = (facing @ _rotation_about(0, tilt * np.sin(3.7 * tau + phase[3]))
         @ _rotation_about(1, tilt * np.sin(2.3 * tau + phase[4]))
         @ _rotation_about(2, np.radians(cfg.roll_deg) * np.sin(1.7 * tau + phase[5])))
    rvecs, tvecs = [matrix_to_rodrigues(R)], [p - R @ board_centre]
    closeup_of = [np.full(cfg.frames, -1)]
    if cfg.closeups:
        # Each camera's own spring: the board waved in front of it alone, near enough to fill
        # much of its image (spring_extent's defaults), two turns of the helix.
        spring = cfg.model_copy(update={"kind": "spring", "frames": cfg.closeups, "turns": 2.0})
        for i, cam in enumerate(cameras):
            tr = conical_spring([cam], board_centre, board_radius, spring)
            rvecs.append(tr.rvecs)
            tvecs.append(tr.tvecs)
            closeup_of.append(np.full(cfg.closeups, i))
    return (Trajectory(np.concatenate(rvecs), np.concatenate(tvecs)),
            np.concatenate(closeup_of))


@dataclass(frozen=True, eq=False)
class GroundTruth:
    """Exact image positions of the feature points.

    points: (C, F, N, 2) px, OpenCV pixel centres; visible: (C, F, N) bool — seen by the lens (in
    front of the camera and inside the distortion's valid radius, or past 90 degrees where a
    wide lens sees), on the board's front side and inside the image.
    """

    points: np.ndarray
    visible: np.ndarray


def board_as_made(cfg: RigConfig, pattern) -> BoardShape:
    """The board of a rig file as made (environment.board: its print's scale and its warp)."""
    b = cfg.environment.board
    return BoardShape.for_pattern(pattern, b.scale_error_pct, b.aspect_error_pct, b.warp_mm)


@dataclass(frozen=True, eq=False)
class Rig:
    """Everything a render needs: the true cameras, the board and its trajectory.

    closeup_of: (F,) int, per frame the index of the camera whose close-up it is (a session's
    close-ups), -1 for every other frame.
    board: the board as made (its print's scale errors and warp); the poses place the board's
    frame, the ground truth is its physical points.
    """

    name: str
    seed: int
    cameras: list[Camera]
    pattern: object
    trajectory: Trajectory
    closeup_of: np.ndarray
    board: BoardShape = BoardShape()

    @classmethod
    def from_config(cls, cfg: RigConfig) -> "Rig":
        cameras = cfg.cameras_true()
        for cam in cameras:
            cam.check_invertible(step=max(cam.width // 64, 4))
        pattern = pattern_from_config(cfg.pattern.kind, **cfg.pattern.overrides())
        obj = pattern.object_points()
        centre = 0.5 * (obj.min(0) + obj.max(0))
        radius = 0.5 * np.hypot(*pattern.size_mm)
        if cfg.trajectory.kind == "session":
            try:
                # A stream of its own: a spawn key no image's noise ([seed, camera, frame],
                # whose shorter forms numpy pads with zeros) can equal.
                rng = np.random.default_rng(np.random.SeedSequence(cfg.seed, spawn_key=(1,)))
                trajectory, closeup_of = session(cameras, centre, radius, cfg.trajectory, rng)
            except ValueError as e:
                raise ValueError(f"trajectory.kind session: {e}") from None
        elif cfg.trajectory.kind == "poses":
            given = np.array(cfg.trajectory.poses, dtype=np.float64).reshape(-1, 6)
            trajectory = Trajectory(given[:, :3], given[:, 3:])
            closeup_of = np.full(len(trajectory), -1)
        else:
            build = dome if cfg.trajectory.kind == "dome" else conical_spring
            trajectory = build(cameras, centre, radius, cfg.trajectory)
            closeup_of = np.full(len(trajectory), -1)
        return cls(cfg.name, cfg.seed, cameras, pattern, trajectory, closeup_of,
                   board_as_made(cfg, pattern))

    def board_points_world(self) -> np.ndarray:
        """The physical board's feature points in the world per frame, (F, N, 3) mm."""
        obj = self.board.points(self.pattern.object_points())
        R = self.trajectory.rotations
        return np.einsum("fij,nj->fni", R, obj) + self.trajectory.tvecs[:, None, :]

    def cam_from_board(self, cam: Camera) -> tuple[np.ndarray, np.ndarray]:
        """Per-frame cam_from_board as (R (F,3,3), t (F,3))."""
        Rwb = self.trajectory.rotations
        R = cam.R @ Rwb
        t = (cam.R @ self.trajectory.tvecs.T).T + cam.tvec
        return R, t

    @property
    def board_centre(self) -> np.ndarray:
        """The centre of the board's outline in its frame, (3,) mm (what it turns about)."""
        return np.append(self.pattern.outline_centre_mm, 0.0)

    def board_velocity(self, cam: Camera, speed_mm_s: float, along_trajectory: bool = False
                       ) -> tuple[np.ndarray, np.ndarray]:
        """Per frame, the board's motion in ``cam``'s frame: (omega (F, 3) rad/s about the
        board's centre, v (F, 3) mm/s of its centre), moving along the trajectory with its
        fastest outline corner at ``speed_mm_s`` (a hand turning a board moves its corners
        faster than its centre). The direction is the step to the next frame of the same
        sequence (the previous one at a sequence's end; a session's walk and each close-up
        are sequences); a frame alone in its sequence, or one the board does not move from,
        is still.

        ``along_trajectory``: the frames are evenly spaced in time, as frames taken from a
        video are, so the hand moves fastest where the steps are longest: ``speed_mm_s`` is
        the sequence's mean speed and each frame moves at it times its step over the
        sequence's mean step (the same for every frame of an evenly spaced trajectory)."""
        R, tv = self.trajectory.rotations, self.trajectory.tvecs
        centre = R @ self.board_centre + tv
        corners = np.einsum("fij,kj->fki", R[:, :, :2], self.pattern.outline_mm()) + tv[:, None]
        F = len(R)
        seq = self.closeup_of
        steps = np.full(F, -1, dtype=int)  # the frame each frame steps to or from
        for f in range(F):
            if f + 1 < F and seq[f + 1] == seq[f]:
                steps[f] = f + 1
            elif f > 0 and seq[f - 1] == seq[f]:
                steps[f] = f - 1
        a, b = np.arange(F), steps
        dist = np.where(b >= 0, np.linalg.norm(corners[np.maximum(b, 0)] - corners, axis=2)
                        .max(axis=1), 0.0)
        speed = np.full(F, float(speed_mm_s))
        if along_trajectory:
            for s in np.unique(seq):
                mine = (seq == s) & (dist > 1e-9)
                if mine.any():
                    speed[mine] *= dist[mine] / dist[mine].mean()
        omega, v = np.zeros((F, 3)), np.zeros((F, 3))
        for f in np.flatnonzero((b >= 0) & (dist > 1e-9)):
            lo, hi = (a[f], b[f]) if b[f] > a[f] else (b[f], a[f])
            rotvec = matrix_to_rodrigues(R[hi] @ R[lo].T)
            omega[f] = rotvec * speed[f] / dist[f]
            v[f] = (centre[hi] - centre[lo]) * speed[f] / dist[f]
        return omega @ cam.R.T, v @ cam.R.T

    def median_depth(self, cam: Camera) -> float:
        """Median depth (mm, along the optical axis) of the board's centre over the frames in
        which it is in front of ``cam``: where a user focuses the lens."""
        R, t = self.cam_from_board(cam)
        z = (R @ self.board_centre + t)[:, 2]
        return float(np.median(z[z > 0])) if np.any(z > 0) else 1000.0

    def ground_truth(self) -> GroundTruth:
        Xw = self.board_points_world()
        F, N, _ = Xw.shape
        pts = np.zeros((len(self.cameras), F, N, 2))
        vis = np.zeros((len(self.cameras), F, N), dtype=bool)
        for c, cam in enumerate(self.cameras):
            Pc = cam.world_to_cam(Xw)
            R, _ = self.cam_from_board(cam)
            # Front side: the board's +z points away from the camera (either side of a
            # two-sided board carries the corners).
            normal_cam = R[:, :, 2]
            front = np.einsum("fi,fni->fn", normal_cam, Pc) > 0
            if self.pattern.two_sided:
                front = np.ones_like(front)
            if cam.model == "opencv":
                z = Pc[..., 2]
                ahead = z > 1e-6
                xy = Pc[..., :2] / np.where(ahead, z, 1.0)[..., None]
                seen = ahead & (np.linalg.norm(xy, axis=-1) < cam.max_normalized_radius)
                uv = cam.normalized_to_pixels(xy)
            else:  # a wide lens sees past 90 degrees (a board behind its plane) where it can
                seen = cam.sees(Pc)
                with np.errstate(invalid="ignore", divide="ignore"):
                    uv = cam.project_cam(Pc)
            inside = ((uv[..., 0] >= 0) & (uv[..., 0] <= cam.width - 1)
                      & (uv[..., 1] >= 0) & (uv[..., 1] <= cam.height - 1))
            pts[c] = uv
            vis[c] = front & seen & inside
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


def coverage_warnings(coverage: dict[str, dict], frames: int,
                      partial_by_design: bool = False) -> tuple[list[str], list[str]]:
    """(warnings, unusable cameras) for a dataset's coverage (``Rig.coverage``).
    ``partial_by_design``: a session, in which each camera sees the board only part of the time
    by design; frames out of view are then no warning (the report counts them per pair)."""
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
        elif partial_by_design:
            continue
        elif c["frames_partly_out"]:
            warnings.append(f"camera {name!r}: the board is partly out of view in "
                            f"{len(c['frames_partly_out'])} of {frames} frames")
        if c["frames_in_view"] and c["frames_in_view"] < frames:
            warnings.append(f"camera {name!r}: the board is out of view in "
                            f"{frames - c['frames_in_view']} of {frames} frames")
    return warnings, unusable
