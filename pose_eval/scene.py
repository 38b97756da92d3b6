"""The scene of a pose evaluation: a moving SMPL body in front of a rig, and the rigs that see it.

Placement. A motion lives in SMPL's body frame (metres, y up, facing +z, floor at y = 0). It
enters the rig's world (mm) by one rigid transform: SMPL's up goes to the rig's up (the mean of
the cameras' -y axes), SMPL's +z (the way a body at zero global orientation faces) points back
along the rig's mean optical axis, towards the cameras, and the centre of the volume the body
sweeps over the whole motion lands on that axis at ``distance_mm`` from the mean camera centre.
Centring the swept volume rather than the root alone keeps the whole body in view at the least
distance (a root at mid-height would push the head out of frame for a squat). By default the
distance is the smallest at which every vertex of every frame projects inside every image with
a 5 % margin, found by bisection through the true cameras (exact projection, distortion
included); a walking body therefore fills the narrowest view.

Rigs. A ``stereo-bench`` run directory holds, per trial seed, the true cameras and one
estimated rig per calibration method (read by ``stereo_bench.pipeline.load_run``). An estimated
rig is expressed in its reference camera's frame (cam_from_world = cam_from_cam0). To
triangulate in the true world, :func:`in_true_world` puts the estimate's camera 0 at the TRUE
pose of camera 0: the reference camera's own pose is not something a calibration method
estimates, so only the relative poses and intrinsics it did estimate reach the error. Scale
needs no alignment: the board is metric, so the estimated baseline is in mm.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import ConvexHull

from stereo_bench.camera import Camera, compose, matrix_to_rodrigues, radial_fold_radius
from stereo_bench.config import load_rig
from stereo_bench.rundir import RunPaths

from .body import forward, load_body_model, rest_skeleton, to_mm
from .motion import make_motion

VIEW_MARGIN = 0.05  # fraction of the image size kept free on every side


@dataclass(frozen=True, eq=False)
class Scene:
    """A posed body in the rig's world.

    joints (T, 24, 3) and vertices (T, V, 3) in mm; faces (F, 3) vertex indices;
    world_from_body (R (3, 3), t (3,) mm) maps SMPL's frame, converted to mm, into the world.
    """

    joints: np.ndarray
    vertices: np.ndarray
    faces: np.ndarray
    world_from_body: tuple[np.ndarray, np.ndarray]
    distance_mm: float


def rig_axes(cameras: list[Camera]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(mean camera centre, unit mean optical axis, unit up orthogonal to it), world frame."""
    centre = np.mean([c.center for c in cameras], axis=0)
    axis = np.mean([c.R[2] for c in cameras], axis=0)
    if np.linalg.norm(axis) < 0.5:
        raise ValueError("the cameras do not look the same way (their mean optical axis is "
                         f"{np.linalg.norm(axis):.2f} long): placing a body in front of a rig "
                         "that surrounds it is not supported")
    axis /= np.linalg.norm(axis)
    up = -np.mean([c.R[1] for c in cameras], axis=0)  # OpenCV's image y points down
    up -= (up @ axis) * axis
    return centre, axis, up / np.linalg.norm(up)


def in_view(camera: Camera, points: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """(...,) bool: in front of ``camera``, inside its distortion's valid radius, and inside the
    image shrunk by ``margin`` x its size on every side. points (..., 3) world mm."""
    Pc = camera.world_to_cam(points)
    ahead = Pc[..., 2] > 1e-6
    xy = Pc[..., :2] / np.where(ahead, Pc[..., 2], 1.0)[..., None]
    # Beyond the fold a point still projects, but to the wrong place: it is not seen.
    valid = np.linalg.norm(xy, axis=-1) < radial_fold_radius(camera.dist)
    uv = camera.normalized_to_pixels(xy)
    mx, my = margin * (camera.width - 1), margin * (camera.height - 1)
    inside = ((uv[..., 0] >= mx) & (uv[..., 0] <= camera.width - 1 - mx)
              & (uv[..., 1] >= my) & (uv[..., 1] <= camera.height - 1 - my))
    return ahead & valid & inside


def place_body(cameras: list[Camera], joints_m: np.ndarray, vertices_m: np.ndarray, faces,
               distance_mm: float | None = None) -> Scene:
    """Put a posed body (SMPL frame, metres) in front of ``cameras``; see the module notes.

    joints_m (T, 24, 3), vertices_m (T, V, 3). distance_mm: from the mean camera centre along the
    mean optical axis; None chooses the smallest at which the body stays in every view.
    """
    centre, axis, up = rig_axes(cameras)
    facing = -axis
    R = np.column_stack([np.cross(up, facing), up, facing])  # body x (left), y (up), z (front)
    verts = to_mm(vertices_m)
    lo, hi = verts.reshape(-1, 3).min(0), verts.reshape(-1, 3).max(0)
    swept_centre = 0.5 * (lo + hi)
    # The hull of the swept volume is all the in-view test needs (a few hundred points, not T*V).
    pts = verts.reshape(-1, 3)
    hull = pts[ConvexHull(pts).vertices] - swept_centre

    def world(p_body, d):
        return p_body @ R.T + centre + d * axis

    def fits(d):
        return all(in_view(cam, world(hull, d), VIEW_MARGIN).all() for cam in cameras)

    if distance_mm is None:
        near = 0.5 * np.linalg.norm(hi - lo)  # nearer, the body would surround the rig
        far = 2.0 * near
        while not fits(far):
            far *= 1.5
            if far > 1e6:
                raise ValueError("cannot fit the body in every camera's view within 1 km: do the "
                                 "cameras share a field of view? (check look_at_mm in the rig)")
        while far - near > 1.0:  # bisection to 1 mm
            mid = 0.5 * (near + far)
            near, far = (near, mid) if fits(mid) else (mid, far)
        distance_mm = far
    elif not fits(distance_mm):
        out = [c.name for c in cameras
               if not in_view(c, world(hull, distance_mm), VIEW_MARGIN).all()]
        warnings.warn(f"distance_mm={distance_mm:g}: the body leaves the view of {out} (with a "
                      f"{VIEW_MARGIN:.0%} margin); joints outside an image are not observed there")
    t = centre + distance_mm * axis - R @ swept_centre
    return Scene(to_mm(joints_m) @ R.T + t, verts @ R.T + t, np.asarray(faces, dtype=np.int64),
                 (R, t), float(distance_mm))


def make_scene(cameras: list[Camera], motion: str, frames: int, fps: float = 30.0, model=None,
               distance_mm: float | None = None) -> Scene:
    """The procedural ``motion`` (pose_eval.motion.MOTIONS), written for and posed by ``model``
    (default: the shipped stand-in body), placed in front of ``cameras``."""
    model = model if model is not None else load_body_model()
    m = make_motion(motion, frames, fps=fps, skeleton=rest_skeleton(model))
    joints, vertices = forward(model, m.body_pose, m.global_orient, m.transl, m.betas)
    return place_body(cameras, joints, vertices, model.faces, distance_mm)


# ----------------------------------------------------------------------------------------------
# The estimates of a stereo-bench run
# ----------------------------------------------------------------------------------------------

def run_description(run_dir) -> tuple[str, str]:
    """(rig name, environment kind) of a run, from its first trial's dataset/config.yaml."""
    run = RunPaths(Path(run_dir))
    configs = [p for p in (run.trial(s).dataset.config for s in run.trial_seeds()) if p.is_file()]
    if not configs:
        return Path(run_dir).name, "unknown"
    cfg = load_rig(configs[0])
    return cfg.name, cfg.environment.kind


def in_true_world(estimate: list[Camera], truth: list[Camera]) -> list[Camera]:
    """The estimated cameras (cam_from_cam0) re-expressed in the true world, with the estimate's
    camera 0 at the true camera 0's pose: cam_from_world = cam_from_cam0 (estimated) o
    cam0_from_world (true). Cameras are matched by position in the list; names must agree."""
    names = [c.name for c in estimate], [c.name for c in truth]
    if names[0] != names[1]:
        raise ValueError(f"estimated rig cameras {names[0]} do not match the true cameras "
                         f"{names[1]} (same names, same order expected)")
    R0, t0 = truth[0].R, truth[0].tvec
    placed = []
    for cam in estimate:
        R, t = compose(cam.R, cam.tvec, R0, t0)
        placed.append(cam.with_params(rvec=matrix_to_rodrigues(R), tvec=t))
    return placed
