"""The scene of a pose evaluation: a moving SMPL body before a rig, and the rigs that see it.

Two kinds of rig, told apart by their geometry (:func:`rig_axes`): cameras that look the same
way (a stereo pair, a camera bar) and cameras that surround the subject (a motion-capture
studio: Human3.6M's 4 cameras, TotalCapture's 8, Shelf's 5). A rig surrounds the subject when
the point nearest to all its optical axes (least squares) lies in front of every camera and,
seen from above (along the rig's up, onto the ground plane), inside the convex hull of the
camera centres: there are cameras on every side of that point, so the rig has no front to put
a body before. The mean optical axis alone cannot tell: the cameras of a studio tilted down
towards the subject average to a long axis pointing at the floor. A rig with no hull (two
cameras) surrounds when that point is in front of both and their mean axis is too short
(under 0.5) to give a front.

Placement. A motion lives in SMPL's body frame (metres, y up, facing +z, floor at y = 0). It
enters the rig's world (mm) by one rigid transform: SMPL's up goes to the rig's up (the mean of
the cameras' -y axes: OpenCV's image y points down, and the cameras are upright), and the
centre of the volume the body sweeps over the whole motion goes to the rig's anchor:

* cameras that look the same way: SMPL's +z (the way a body at zero global orientation faces)
  points back along the rig's mean optical axis, towards the cameras, and the swept volume's
  centre lands on that axis at ``distance_mm`` from the mean camera centre. By default the
  distance is the smallest at which every vertex of every frame projects inside every image
  with a 5 % margin, found by bisection through the true cameras (exact projection, distortion
  included); a walking body therefore fills the narrowest view.
* a studio: the anchor is the point the cameras look at, and SMPL's +z points horizontally
  towards camera 0. Studio cameras aim at the middle of their capture volume, so the body's
  middle goes there: horizontally the swept volume's centre (a walking motion walks through
  the volume around its centre), vertically half the body's stature, which puts its floor
  (SMPL's y = 0, under its soles) half its stature below the point, whatever the motion. This
  needs nothing from the world's coordinates (no floor at z = 0 is assumed). There is no
  distance to choose; where the body leaves some camera's view, that is warned about, and
  joints seen by fewer than two cameras are not triangulated.

Centring the swept volume rather than the root alone keeps the whole body in view at the least
distance (a root at mid-height would push the head out of frame for a squat).

Rigs. A ``stereo-bench`` run directory holds, per trial seed, the true cameras and one
estimated rig per calibration method (read by ``stereo_bench.run.pipeline.load_run``). An estimated
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
from typing import NamedTuple

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from stereo_bench.core.camera import Camera
from stereo_bench.core.poses import compose, matrix_to_rodrigues
from stereo_bench.config.schema import load_rig
from stereo_bench.scene.rig import ground_axes, volume_centre, world_up
from stereo_bench.io.rundir import RunPaths

from .body import forward, load_body_model, rest_pose_mm, rest_skeleton, to_mm
from .motion import make_motion

VIEW_MARGIN = 0.05  # fraction of the image size kept free on every side
MIN_MEAN_AXIS = 0.5  # below it the cameras of a rig that does not surround do not share a front


@dataclass(frozen=True, eq=False)
class Scene:
    """A posed body in the rig's world.

    joints (T, 24, 3) and vertices (T, V, 3) in mm; faces (F, 3) vertex indices;
    world_from_body (R (3, 3), t (3,) mm) maps SMPL's frame, converted to mm, into the world.
    surrounded: the rig surrounds the body (a studio), which stands at the point the cameras
    look at; distance_mm is then the cameras' mean distance from that point, otherwise the
    distance of the swept volume's centre from the mean camera centre along the mean axis.
    """

    joints: np.ndarray
    vertices: np.ndarray
    faces: np.ndarray
    world_from_body: tuple[np.ndarray, np.ndarray]
    distance_mm: float
    surrounded: bool


class RigAxes(NamedTuple):
    """Where and which way a body meets a rig (world frame, see the module notes).

    centre: the mean camera centre, or for a rig that surrounds, the point the cameras look at;
    axis: unit, the mean optical axis, or for a rig that surrounds, camera 0's horizontal view
    direction towards the centre; up: unit, orthogonal to axis; surrounds: which kind of rig.
    """

    centre: np.ndarray
    axis: np.ndarray
    up: np.ndarray
    surrounds: bool


def _inside_from_above(cameras: list[Camera], point: np.ndarray, up: np.ndarray) -> bool:
    """``point`` is, in the ground plane across ``up``, inside the convex hull of the camera
    centres (on its edge counts: cameras on three sides of it surround it)."""
    e1, e2 = ground_axes(up)
    ground = np.array([[c.center @ e1, c.center @ e2] for c in cameras])
    try:
        hull = ConvexHull(ground)
    except (QhullError, ValueError):  # fewer than 3 cameras, or all in a line seen from above
        return False
    size = np.ptp(ground, axis=0).max()
    return bool((hull.equations[:, :2] @ [point @ e1, point @ e2] + hull.equations[:, 2]
                 <= 1e-9 * size).all())


def rig_axes(cameras: list[Camera]) -> RigAxes:
    """The rig's centre, axis, up and kind (see :class:`RigAxes` and the module notes).

    The cameras surround the subject when the point nearest to their axes is in front of every
    one and, seen from above, inside their convex hull; or when it is in front of every one and
    their mean optical axis is too short to give a front (two cameras far apart, which have no
    hull, looking at one point from 150 deg apart, say).
    """
    up = world_up(cameras)
    axis = np.mean([c.R[2] for c in cameras], axis=0)
    try:
        point = volume_centre(cameras)
    except ValueError:  # (nearly) parallel axes: no point they all look at
        point = None
    looked_at = point is not None and all(c.world_to_cam(point)[2] > 0 for c in cameras)
    if looked_at and (np.linalg.norm(axis) < MIN_MEAN_AXIS
                      or _inside_from_above(cameras, point, up)):
        try:
            towards = ground_axes(up, point - cameras[0].center)[0]
        except ValueError:
            raise ValueError(f"camera {cameras[0].name!r} is straight above or below the point "
                             f"the cameras look at: the body faces camera 0 horizontally, and "
                             f"there is no horizontal direction to it; list another camera "
                             f"first") from None
        return RigAxes(point, towards, up, True)
    if np.linalg.norm(axis) < MIN_MEAN_AXIS:
        raise ValueError(f"the cameras neither look the same way (their mean optical axis is "
                         f"{np.linalg.norm(axis):.2f} long) nor look at a point in front of "
                         f"them all: no place for a body in view of them")
    centre = np.mean([c.center for c in cameras], axis=0)
    axis /= np.linalg.norm(axis)
    up -= (up @ axis) * axis
    return RigAxes(centre, axis, up / np.linalg.norm(up), False)


def in_view(camera: Camera, points: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """(...,) bool: in front of ``camera``, inside its distortion's valid radius, and inside the
    image shrunk by ``margin`` x its size on every side. points (..., 3) world mm."""
    Pc = camera.world_to_cam(points)
    ahead = Pc[..., 2] > 1e-6
    xy = Pc[..., :2] / np.where(ahead, Pc[..., 2], 1.0)[..., None]
    # Beyond the fold a point still projects, but to the wrong place: it is not seen.
    valid = np.linalg.norm(xy, axis=-1) < camera.max_normalized_radius
    uv = camera.normalized_to_pixels(xy)
    mx, my = margin * (camera.width - 1), margin * (camera.height - 1)
    inside = ((uv[..., 0] >= mx) & (uv[..., 0] <= camera.width - 1 - mx)
              & (uv[..., 1] >= my) & (uv[..., 1] <= camera.height - 1 - my))
    return ahead & valid & inside


def place_body(cameras: list[Camera], joints_m: np.ndarray, vertices_m: np.ndarray, faces,
               distance_mm: float | None = None, stature_mm: float | None = None) -> Scene:
    """Put a posed body (SMPL frame, metres, floor y = 0) in view of ``cameras``; see the module
    notes.

    joints_m (T, 24, 3), vertices_m (T, V, 3). distance_mm: from the mean camera centre along the
    mean optical axis; None chooses the smallest at which the body stays in every view. A rig
    that surrounds the body has no such distance: the body stands at the point it looks at,
    its floor ``stature_mm / 2`` below that point (default: the top of the swept volume above
    the floor, the stature while the hands stay below the head).
    """
    centre, axis, up, surrounds = rig_axes(cameras)
    facing = -axis
    R = np.column_stack([np.cross(up, facing), up, facing])  # body x (left), y (up), z (front)
    verts = to_mm(vertices_m)
    lo, hi = verts.reshape(-1, 3).min(0), verts.reshape(-1, 3).max(0)
    anchor = 0.5 * (lo + hi)  # the body point that goes to the rig's centre (+ offset x axis)
    if surrounds:
        # Half the stature, not the swept volume's middle: arms raised overhead would lift that
        # middle and push the feet through the floor (by 200 mm for arm_raise over 2 s).
        anchor[1] = 0.5 * (hi[1] if stature_mm is None else stature_mm)
    # The hull of the swept volume is all the in-view test needs (a few hundred points, not T*V).
    pts = verts.reshape(-1, 3)
    hull = pts[ConvexHull(pts).vertices] - anchor

    def world(p_body, d):
        return p_body @ R.T + centre + d * axis

    def fits(d):
        return all(in_view(cam, world(hull, d), VIEW_MARGIN).all() for cam in cameras)

    if surrounds:
        if distance_mm is not None:
            raise ValueError("distance_mm (--distance-mm): these cameras surround the body, which "
                             "stands at the point they look at; a distance from the rig applies "
                             "only to cameras that look the same way")
        offset, where = 0.0, "at the point the cameras look at"
    elif distance_mm is None:
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
        offset, where = far, ""  # in view by construction
    else:
        offset, where = distance_mm, f"distance_mm={distance_mm:g}"
    if where and not fits(offset):
        out = [c.name for c in cameras if not in_view(c, world(hull, offset), VIEW_MARGIN).all()]
        warnings.warn(f"{where}: the body leaves the view of {out} (with a {VIEW_MARGIN:.0%} "
                      f"margin); joints outside an image are not observed there")
    t = centre + offset * axis - R @ anchor
    if surrounds:  # reported as how far the cameras are, on average
        offset = np.mean([np.linalg.norm(c.center - centre) for c in cameras])
    return Scene(to_mm(joints_m) @ R.T + t, verts @ R.T + t, np.asarray(faces, dtype=np.int64),
                 (R, t), float(offset), surrounds)


def make_scene(cameras: list[Camera], motion: str, frames: int, fps: float = 30.0, model=None,
               distance_mm: float | None = None) -> Scene:
    """The procedural ``motion`` (pose_eval.motion.MOTIONS), written for and posed by ``model``
    (default: the shipped stand-in body), placed in view of ``cameras`` (see the module notes)."""
    model = model if model is not None else load_body_model()
    m = make_motion(motion, frames, fps=fps, skeleton=rest_skeleton(model))
    joints, vertices = forward(model, m.body_pose, m.global_orient, m.transl, m.betas)
    return place_body(cameras, joints, vertices, model.faces, distance_mm,
                      stature_mm=rest_pose_mm(model, m.betas)[2])


@dataclass(frozen=True)
class Person:
    """One person of a scene: a procedural motion (pose_eval.motion.MOTIONS), its seed (None:
    the canonical motion) and the motion's own parameters (walk_circle's ``radius`` in m)."""

    motion: str
    seed: int | None = None
    shape: tuple[tuple[str, float], ...] = ()


def seen_by_clocks(cameras: list[Camera], people: list[Person], frames: int, fps: float = 30.0,
                   model=None, offsets_ms=None) -> list[list[Scene]]:
    """[camera][person] scenes: what each camera sees of each person when its clock runs
    ``offsets_ms[c]`` ms ahead (frame f of camera c is exposed at f / fps + offset).

    The first person is placed as :func:`make_scene` places a body (the rig's anchor), and every
    other person in the same frame: procedural motions share SMPL's origin (walk_circle's
    centre), so people on circles of different radii walk around one another. Each shifted
    view poses the motion at its own times (exact: motions are closed-form in time) and puts it
    in the world by the same placement, so the cameras disagree only about when.
    """
    model = model if model is not None else load_body_model()
    skeleton = rest_skeleton(model)
    offsets = np.zeros(len(cameras)) if offsets_ms is None else np.asarray(offsets_ms, float)
    if offsets.shape != (len(cameras),) or not np.all(np.isfinite(offsets)):
        raise ValueError(f"offsets_ms: expected {len(cameras)} finite offsets, got {offsets_ms!r}")
    stature = rest_pose_mm(model)[2]
    placed = None
    views = [[None] * len(people) for _ in cameras]
    for p, person in enumerate(people):
        posed = {}
        for c, offset in enumerate(offsets):
            if offset not in posed:
                m = make_motion(person.motion, frames, fps=fps, seed=person.seed,
                                skeleton=skeleton, start_s=offset / 1000.0, **dict(person.shape))
                posed[offset] = forward(model, m.body_pose, m.global_orient, m.transl, m.betas)
            joints, vertices = posed[offset]
            if placed is None:  # the first person's unshifted motion fixes the placement
                joints0, vertices0 = posed.get(0.0) or forward(
                    model, *_unshifted(person, frames, fps, skeleton))
                placed = place_body(cameras, joints0, vertices0, model.faces,
                                    stature_mm=stature)
            R, t = placed.world_from_body
            views[c][p] = Scene(to_mm(joints) @ R.T + t, to_mm(vertices) @ R.T + t,
                                placed.faces, placed.world_from_body, placed.distance_mm,
                                placed.surrounded)
    return views


def _unshifted(person: Person, frames: int, fps: float, skeleton):
    m = make_motion(person.motion, frames, fps=fps, seed=person.seed, skeleton=skeleton,
                    **dict(person.shape))
    return m.body_pose, m.global_orient, m.transl, m.betas


# ----------------------------------------------------------------------------------------------
# The estimates of a stereo-bench run
# ----------------------------------------------------------------------------------------------

def run_config(run_dir):
    """The rig configuration of a run's first trial (its dataset/config.yaml), or None."""
    run = RunPaths(Path(run_dir))
    configs = [p for p in (run.trial(s).dataset.config for s in run.trial_seeds()) if p.is_file()]
    return load_rig(configs[0]) if configs else None


def run_description(run_dir) -> tuple[str, str]:
    """(rig name, environment kind) of a run, from its first trial's dataset/config.yaml."""
    cfg = run_config(run_dir)
    if cfg is None:
        return Path(run_dir).name, "unknown"
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
