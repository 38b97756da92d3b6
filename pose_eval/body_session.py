"""A calibration from the body in a studio of known truth, graded against that truth.

People walk around the studio's centre on circles of different radii (so that they pass one
another without meeting), each camera sees them at its own clock (the rig file's
``time_offset_ms``: pose_eval.scene.seen_by_clocks), a detector model draws their keypoints
(Gaussian, or a fitted detector's error), and pose_eval.body_calibration calibrates the studio
from those keypoints alone, the intrinsics being the true ones (a studio's lenses are
calibrated once, its extrinsics every session). The result is graded by
pose_eval.metrics.studio_errors, and placed in the true world (its camera 0 at the true
camera 0) for pose-eval to triangulate through, beside the board calibrations.

The keypoints of one session never serve the pose evaluation: the people walk in the
calibration session, and pose-eval's body moves in its own frames afterwards.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from stereo_bench.core.camera import Camera
from stereo_bench.run.exchange import rebased

from .body import rest_pose_mm
from .body_calibration import BodyCalibration, Scale, Skeleton, calibrate_from_body
from .metrics import studio_errors
from .motion import FOOT_JOINTS, JOINT
from .observe import LAYOUTS, Keypoints, keypoints_at_clocks
from .scene import Person, in_true_world, seen_by_clocks

WALK_RADII_M = (1.5, 0.8, 2.1, 0.4)  # person k walks a circle of radius WALK_RADII_M[k]
MAX_PEOPLE = len(WALK_RADII_M)
FPS = 30.0
SCALES = ("height", "baseline")

#: Keypoints of ``scene`` seen by ``cameras``, drawn with ``rng`` (observe or observe_fitted).
Draw = Callable[[list[Camera], object, np.random.Generator], Keypoints]


@dataclass(frozen=True)
class Session:
    """How the studio is calibrated from the body: ``people`` walking for ``frames`` frames at
    30 fps, the scale from their ``height`` or the ``baseline`` of cameras 0 and 1 (both known
    exactly: the stand-in body's stature, the true distance), clocks searched up to
    ``max_offset_frames`` (0: the cameras are taken as synchronised)."""

    people: int = 1
    frames: int = 300
    scale: str = "height"
    max_offset_frames: int = 10

    def __post_init__(self):
        if not 1 <= self.people <= MAX_PEOPLE:
            raise ValueError(f"people: expected 1..{MAX_PEOPLE}, got {self.people}")
        if not 10 <= self.frames <= 10_000:
            raise ValueError(f"frames: expected 10..10000, got {self.frames}")
        if self.scale not in SCALES:
            raise ValueError(f"scale: expected one of {', '.join(SCALES)}, got {self.scale!r}")
        if not 0 <= self.max_offset_frames <= 300:
            raise ValueError(f"max_offset_frames: expected 0..300, got {self.max_offset_frames}")


def walkers(people: int, seed: int) -> list[Person]:
    """The session's people: walk_circle, each with its own seed (pace, stride, phase)."""
    return [Person("walk_circle", seed * MAX_PEOPLE + k, (("radius", WALK_RADII_M[k]),))
            for k in range(people)]


# The height chain (body_calibration.Skeleton) by layout, as (joint, joint, weight): shins and
# thighs at half weight (two legs), pelvis to neck, neck to head. BODY_25 has no pelvis or head
# joint: its mid-hip and nose stand in for them, with the SMPL body's ratio of stature to the
# chain, an approximation (docs/body_calibration.md gives what it costs).
_CHAIN = (("left_ankle", "left_knee", 0.5), ("left_knee", "left_hip", 0.5),
          ("right_ankle", "right_knee", 0.5), ("right_knee", "right_hip", 0.5),
          ("pelvis", "neck", 1.0), ("neck", "head", 1.0))
BODY25 = {"head": 0, "neck": 1, "pelvis": 8, "right_hip": 9, "right_knee": 10,
          "right_ankle": 11, "left_hip": 12, "left_knee": 13, "left_ankle": 14}
BODY25_PAIRS = ((2, 5), (3, 6), (4, 7), (9, 12), (10, 13), (11, 14), (15, 16), (17, 18),
                (19, 22), (20, 23), (21, 24))  # (right, left)
SMPL_PAIRS = tuple((JOINT[n], JOINT[n.replace("left", "right")]) for n in JOINT
                   if n.startswith("left"))
LAYOUT_JOINTS = {  # per layout: joint index by name, its feet (ankles, toes, heels), its pairs
    "smpl24": (JOINT, FOOT_JOINTS, SMPL_PAIRS),
    "body25": (BODY25, (11, 14, 19, 20, 21, 22, 23, 24), BODY25_PAIRS),
}


def skeleton(layout: str, model, people: int) -> tuple[Skeleton, float]:
    """(the tracks' feet, heads and the first person's height chain for ``people`` bodies of
    ``layout`` side by side, the SMPL body's stature mm at rest, lowest to highest vertex)."""
    joints, _, stature = rest_pose_mm(model)
    rest = sum(w * np.linalg.norm(joints[JOINT[a]] - joints[JOINT[b]]) for a, b, w in _CHAIN)
    index, foot, pairs = LAYOUT_JOINTS[layout]
    J = LAYOUTS[layout]
    chain = tuple((index[a], index[b], w) for a, b, w in _CHAIN)
    feet = tuple(j + J * p for p in range(people) for j in foot)
    heads = tuple(index["head"] + J * p for p in range(people))
    mirror = np.arange(J * people)
    for p in range(people):
        for a, b in pairs:
            mirror[a + J * p], mirror[b + J * p] = b + J * p, a + J * p
    return Skeleton(feet, heads, chain, stature / rest, tuple(mirror.tolist()), J), stature


def session_keypoints(truth: list[Camera], offsets_ms, session: Session, model, draw: Draw,
                      seed) -> tuple[Keypoints, list[list]]:
    """(keypoints (C, T, people x 24) of the session's people seen by the true cameras at their
    clocks, the [camera][person] scenes). seed: the trial's sequence of ints."""
    people = walkers(session.people, int(np.random.default_rng(seed).integers(2**31)))
    views = seen_by_clocks(truth, people, session.frames, FPS, model, offsets_ms)
    return keypoints_at_clocks(truth, views, draw, seed), views


def calibrate_session(truth: list[Camera], offsets_ms, session: Session, model, draw: Draw,
                      seed) -> tuple[BodyCalibration, dict, list[Camera]]:
    """(the calibration, its errors against the truth, its cameras in the true world) of one
    session; ValueError if the method fails (named by its step)."""
    keypoints, views = session_keypoints(truth, offsets_ms, session, model, draw, seed)
    body, stature = skeleton("smpl24", model, session.people)
    if session.scale == "height":
        scale = Scale(height_mm=stature)
    else:
        scale = Scale(baseline_mm=float(np.linalg.norm(truth[0].center - truth[1].center)),
                      cameras=(truth[0].name, truth[1].name))
    result = calibrate_from_body(truth, keypoints.pixels, keypoints.confidence, body, scale,
                                 session.max_offset_frames)
    true_offsets = np.asarray(offsets_ms, float) * FPS / 1000.0
    true_up = views[0][0].world_from_body[0][:, 1]  # SMPL's up in the world: the floor's normal
    errors = studio_errors(result.cameras, truth, result.offsets_frames, true_offsets,
                           np.array([0.0, 0.0, 1.0]), true_up)
    errors["rms_px"] = result.rms_px
    errors["vertical_from_floor"] = float(result.vertical == "floor")
    return result, errors, in_true_world(rebased(result.cameras), truth)
