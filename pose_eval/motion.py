"""Body motions as SMPL pose sequences: procedural ones, and recorded ones from AMASS files.

A motion is what an SMPL-format body model consumes (Loper et al., "SMPL: A Skinned
Multi-Person Linear Model", SIGGRAPH Asia 2015): per frame, axis-angle rotations (T, 24, 3) of
the 24 joints of SMPL's kinematic tree, joint 0 being the global orientation and joints 1..23
(`body_pose`) each relative to its parent in the rest pose's axes, plus `transl` (T, 3) in
metres added after posing. Posing rotates about the rest pelvis, so a body's pelvis lands at
`skeleton.joints[0] + transl`.

Frame of every motion here: SMPL's body frame, metres, y up, floor at y = 0; at zero global
orientation the body faces +z and its left is +x. Placing it in a rig's world (mm) is the
caller's job (`pose_eval.body.to_mm`).

Procedural motions are written for the rest skeleton they will drive (the shipped stand-in's
by default): numpy forward kinematics lifts the root so that, in every frame, the lowest foot
joint sits at its rest height above the floor (plus any jump). The stance foot therefore stays
on y = 0 whatever the body's proportions, and the same seed gives the same arrays.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from stereo_bench.core.poses import matrix_to_rodrigues, rodrigues_to_matrix

JOINT_NAMES = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
    "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar",
    "right_collar", "head", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow",
    "left_wrist", "right_wrist", "left_hand", "right_hand",
)
PARENTS = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21)
JOINT = {name: i for i, name in enumerate(JOINT_NAMES)}
FOOT_JOINTS = (JOINT["left_ankle"], JOINT["right_ankle"], JOINT["left_foot"], JOINT["right_foot"])

# The open stand-in body (built by scripts/build_body_model.py). Its rest skeleton is read here
# with numpy alone so that motions do not need torch; pose_eval.body loads the same file.
STANDIN_MODEL_PATH = Path(__file__).resolve().parents[1] / "assets" / "body_model" / "open_body_neutral.npz"


@dataclass(frozen=True, eq=False)
class Skeleton:
    """Rest joints (24, 3) m in the model frame, the rest floor height (lowest vertex y), parents."""

    joints: np.ndarray
    floor_y: float
    parents: tuple[int, ...] = PARENTS


@functools.cache
def standin_skeleton() -> Skeleton:
    """Rest skeleton of the shipped stand-in body at zero shape."""
    with np.load(STANDIN_MODEL_PATH) as data:
        return Skeleton(data["J"].astype(np.float64), float(data["v_template"][:, 1].min()))


@dataclass(frozen=True, eq=False)
class Motion:
    """poses (T, 24, 3) axis-angle (joint 0 = global orientation), transl (T, 3) m, at fps.

    betas: the recorded subject's shape coefficients (AMASS), None for procedural motions.
    """

    name: str
    poses: np.ndarray
    transl: np.ndarray
    fps: float
    betas: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.poses)

    @property
    def global_orient(self) -> np.ndarray:
        """(T, 3) axis-angle of the root."""
        return self.poses[:, 0]

    @property
    def body_pose(self) -> np.ndarray:
        """(T, 69): joints 1..23 flattened, smplx's `body_pose` layout."""
        return self.poses[:, 1:].reshape(len(self.poses), 69)


def forward_kinematics(poses: np.ndarray, skeleton: Skeleton, transl: np.ndarray | None = None) -> np.ndarray:
    """Posed joints (T, 24, 3) m, the same as the joints of SMPL's forward pass (its lbs).

    poses (T, 24, 3) axis-angle or (T, 24, 3, 3) rotation matrices; transl (T, 3) or None.
    """
    poses = np.asarray(poses, dtype=np.float64)
    rotations = poses if poses.shape[-2:] == (3, 3) else rodrigues_to_matrix(poses)
    rest = skeleton.joints
    world_rot = np.empty_like(rotations)
    joints = np.empty(rotations.shape[:2] + (3,))
    world_rot[:, 0], joints[:, 0] = rotations[:, 0], rest[0]
    for k, p in enumerate(skeleton.parents[1:], start=1):
        world_rot[:, k] = world_rot[:, p] @ rotations[:, k]
        joints[:, k] = joints[:, p] + world_rot[:, p] @ (rest[k] - rest[p])
    return joints if transl is None else joints + np.asarray(transl, dtype=np.float64)[:, None]


# --- procedural motions --------------------------------------------------------------------------

_AXES = {"x": np.array([1.0, 0, 0]), "y": np.array([0, 1.0, 0]), "z": np.array([0, 0, 1.0])}
ARMS_DOWN = np.deg2rad(72.0)  # shoulder adduction from the T-pose to a relaxed stance


def _rot(axis: str, angle) -> np.ndarray:
    """(T, 3, 3) rotations about a body axis by angle(s) (T,) rad; right-handed."""
    return rodrigues_to_matrix(_AXES[axis] * np.atleast_1d(np.asarray(angle, dtype=np.float64))[:, None])


@dataclass(frozen=True)
class _Variation:
    """Per-seed changes of a motion: amplitude and speed factors, phase in cycles."""

    amp: float = 1.0
    speed: float = 1.0
    phase: float = 0.0


def _clock(frames: int, fps: float, seed: int | None, start_s: float = 0.0):
    """Frame times (T,) s from ``start_s`` and the variation drawn from the seed (none without a
    seed). A camera whose clock runs ``start_s`` ahead sees the motion at these times: every
    motion is a closed-form function of time, so a shifted camera's truth is exact."""
    if int(frames) != frames or frames < 1:
        raise ValueError(f"frames must be a positive integer, got {frames!r}")
    if not fps > 0:
        raise ValueError(f"fps must be positive, got {fps!r}")
    if not np.isfinite(start_s):
        raise ValueError(f"start_s must be finite, got {start_s!r}")
    t = start_s + np.arange(int(frames)) / float(fps)
    if seed is None:
        return t, _Variation()
    rng = np.random.default_rng(seed)
    return t, _Variation(*rng.uniform([0.85, 0.9, 0.0], [1.15, 1.1, 1.0]))


def _standing(t: np.ndarray) -> np.ndarray:
    """(T, 24, 3, 3) rotations of a relaxed stance: T-pose with the arms lowered."""
    rot = np.broadcast_to(np.eye(3), (len(t), 24, 3, 3)).copy()
    rot[:, JOINT["left_shoulder"]] = _rot("z", np.full(len(t), -ARMS_DOWN))
    rot[:, JOINT["right_shoulder"]] = _rot("z", np.full(len(t), ARMS_DOWN))
    return rot


def _grounded(name, rotations, root_xz, lift, fps, skeleton: Skeleton | None) -> Motion:
    """Motion whose lowest foot joint stands at its rest height above y = 0, plus lift (T,) m."""
    skeleton = skeleton or standin_skeleton()
    rel = forward_kinematics(rotations, skeleton)[:, FOOT_JOINTS, 1] - skeleton.joints[0, 1]
    rest_height = skeleton.joints[FOOT_JOINTS, 1] - skeleton.floor_y
    pelvis_y = (rest_height - rel).max(axis=1) + lift
    pelvis = np.column_stack([root_xz[:, 0], pelvis_y, root_xz[:, 1]])
    return Motion(name, matrix_to_rodrigues(rotations), pelvis - skeleton.joints[0], float(fps))


def walk_circle(frames: int, fps: float = 30.0, seed: int | None = None,
                skeleton: Skeleton | None = None, start_s: float = 0.0,
                radius: float = 1.5) -> Motion:
    """Walking counter-clockwise (seen from +y) around a circle of `radius` m about the origin.

    1.1 m/s with 0.9 strides/s; legs, arms and pelvis swing in the sagittal plane, the arms
    against the legs.
    """
    t, v = _clock(frames, fps, seed, start_s)
    speed, a = 1.1 * v.speed, v.amp
    gait = 2 * np.pi * (0.9 * v.speed * t + v.phase)
    path = speed * t / radius + 2 * np.pi * v.phase
    rot = _standing(t)
    for side, sign, phase in (("left", 1, 0.0), ("right", -1, np.pi)):
        g = gait + phase
        swing = np.maximum(0, np.cos(g + np.pi / 4)) ** 2  # peaks mid-swing
        hip, knee = -np.deg2rad(25 * a) * np.sin(g), np.deg2rad(5 + 55 * a * swing)  # -x rotation = flexion
        rot[:, JOINT[f"{side}_hip"]] = _rot("x", hip)
        rot[:, JOINT[f"{side}_knee"]] = _rot("x", knee)
        # sagittal angles add up: cancelling them keeps the sole level; the toe rises in swing
        rot[:, JOINT[f"{side}_ankle"]] = _rot("x", -(hip + knee) - np.deg2rad(10) * swing)
        arm_swing = np.deg2rad(15 * a) * np.sin(g + np.pi)
        rot[:, JOINT[f"{side}_shoulder"]] = _rot("x", -arm_swing) @ rot[:, JOINT[f"{side}_shoulder"]]
        rot[:, JOINT[f"{side}_elbow"]] = _rot("y", -sign * np.deg2rad(15 + 10 * np.sin(g + np.pi)))
    rot[:, JOINT["spine1"]] = _rot("y", -np.deg2rad(4 * a) * np.sin(gait))  # torso counter-twist
    heading = path + np.pi / 2  # direction of travel of (r sin(path), r cos(path))
    rot[:, 0] = _rot("y", heading) @ _rot("y", np.deg2rad(5 * a) * np.sin(gait))
    root_xz = radius * np.column_stack([np.sin(path), np.cos(path)])
    return _grounded("walk_circle", rot, root_xz, np.zeros(len(t)), fps, skeleton)


def arm_raise(frames: int, fps: float = 30.0, seed: int | None = None,
              skeleton: Skeleton | None = None, start_s: float = 0.0) -> Motion:
    """Standing still, both arms rise sideways from the hips to overhead and back every 4 s."""
    t, v = _clock(frames, fps, seed, start_s)
    s = (1 - np.cos(2 * np.pi * (v.speed * t / 4.0 + v.phase))) / 2
    rot = _standing(t)
    lift_angle = np.minimum(np.deg2rad(150 * v.amp) * s, np.deg2rad(160))
    for side, sign in (("left", 1), ("right", -1)):
        rot[:, JOINT[f"{side}_shoulder"]] = _rot("z", sign * (lift_angle - ARMS_DOWN))  # +z raises the left arm
        rot[:, JOINT[f"{side}_collar"]] = _rot("z", sign * np.deg2rad(15) * s)  # shrug as the arm passes horizontal
    return _grounded("arm_raise", rot, np.zeros((len(t), 2)), np.zeros(len(t)), fps, skeleton)


def squat(frames: int, fps: float = 30.0, seed: int | None = None,
          skeleton: Skeleton | None = None, start_s: float = 0.0) -> Motion:
    """Squats every 3 s with the feet flat, torso leaning forward and the arms reaching forward.

    All sagittal angles are about x, so they add: pelvis tilt + hip + knee + ankle = 0 keeps
    the feet flat; the thigh reaches -70 deg and the shin +30 deg at full depth.
    """
    t, v = _clock(frames, fps, seed, start_s)
    s = np.minimum(v.amp * (1 - np.cos(2 * np.pi * (v.speed * t / 3.0 + v.phase))) / 2, 1.0)
    tilt, hip, knee, ankle = (np.deg2rad(d) * s for d in (25, -95, 100, -30))
    rot = _standing(t)
    rot[:, 0] = _rot("x", tilt)
    for side in ("left", "right"):
        rot[:, JOINT[f"{side}_hip"]] = _rot("x", hip)
        rot[:, JOINT[f"{side}_knee"]] = _rot("x", knee)
        rot[:, JOINT[f"{side}_ankle"]] = _rot("x", ankle)
        rot[:, JOINT[f"{side}_shoulder"]] = _rot("x", -np.deg2rad(95) * s) @ rot[:, JOINT[f"{side}_shoulder"]]
    return _grounded("squat", rot, np.zeros((len(t), 2)), np.zeros(len(t)), fps, skeleton)


def jumping_jacks(frames: int, fps: float = 30.0, seed: int | None = None,
                  skeleton: Skeleton | None = None, start_s: float = 0.0) -> Motion:
    """Jumping jacks every 1.2 s: arms sideways to overhead and legs apart, hopping 7 cm."""
    t, v = _clock(frames, fps, seed, start_s)
    cycle = 2 * np.pi * (v.speed * t / 1.2 + v.phase)
    s = (1 - np.cos(cycle)) / 2
    rot = _standing(t)
    for side, sign in (("left", 1), ("right", -1)):
        spread = sign * np.deg2rad(15 * v.amp) * s  # +z moves the left leg outwards
        rot[:, JOINT[f"{side}_hip"]] = _rot("z", spread)
        rot[:, JOINT[f"{side}_ankle"]] = _rot("z", -spread)  # keeps the sole level
        rot[:, JOINT[f"{side}_shoulder"]] = _rot("z", sign * (np.deg2rad(150) * s - ARMS_DOWN))
    # airborne through the middle third of each change between the closed and open stances
    lift = 0.07 * v.amp * np.maximum(0, np.abs(np.sin(cycle)) - 0.5) / 0.5
    return _grounded("jumping_jacks", rot, np.zeros((len(t), 2)), lift, fps, skeleton)


def turn_in_place(frames: int, fps: float = 30.0, seed: int | None = None,
                  skeleton: Skeleton | None = None, start_s: float = 0.0) -> Motion:
    """Turning on the spot at 90 deg/s, stepping once per leg per second."""
    t, v = _clock(frames, fps, seed, start_s)
    step = 2 * np.pi * (v.speed * t + v.phase)
    rot = _standing(t)
    for side, phase in (("left", 0.0), ("right", np.pi)):
        up = np.maximum(0, np.sin(step + phase))
        hip, knee = -np.deg2rad(20 * v.amp) * up, np.deg2rad(40 * v.amp) * up
        rot[:, JOINT[f"{side}_hip"]] = _rot("x", hip)
        rot[:, JOINT[f"{side}_knee"]] = _rot("x", knee)
        rot[:, JOINT[f"{side}_ankle"]] = _rot("x", -(hip + knee))  # sole stays level
    rot[:, 0] = _rot("y", np.pi / 2 * v.speed * t + 2 * np.pi * v.phase)
    return _grounded("turn_in_place", rot, np.zeros((len(t), 2)), np.zeros(len(t)), fps, skeleton)


MOTIONS = {f.__name__: f for f in (walk_circle, arm_raise, squat, jumping_jacks, turn_in_place)}


def make_motion(name: str, frames: int, fps: float = 30.0, seed: int | None = None,
                skeleton: Skeleton | None = None, start_s: float = 0.0, **shape) -> Motion:
    """The procedural motion `name` (a key of MOTIONS).

    seed: None gives the canonical motion; an int or numpy Generator varies amplitude (+-15 %),
    speed (+-10 %) and phase, reproducibly. start_s: the time of the first frame (a camera
    whose clock is offset). shape: the motion's own parameters (walk_circle's radius).
    """
    if name not in MOTIONS:
        raise ValueError(f"unknown motion {name!r}; expected one of {', '.join(MOTIONS)}")
    return MOTIONS[name](frames, fps=fps, seed=seed, skeleton=skeleton, start_s=start_s, **shape)


# --- recorded motions ----------------------------------------------------------------------------

# AMASS stores z-up worlds; this rotation (-90 deg about x) maps them to SMPL's y-up frame.
Y_UP_FROM_Z_UP = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])


def load_amass(path, z_up: bool = True, skeleton: Skeleton | None = None) -> Motion:
    """An AMASS-style .npz (Mahmood et al., "AMASS", ICCV 2019) as an SMPL motion in metres.

    Keys: poses (T, >=72) axis-angle, trans (T, 3) m, mocap_framerate (or SMPL-X AMASS's
    mocap_frame_rate), betas (optional). The SMPL body is the first 22 joints (66 values) in
    every layout; values 66..72 are SMPL's two hand joints only when the file has exactly 72
    (in SMPL-H's 156 they are the first left-finger joint and in SMPL-X's 165 the jaw), so wider
    files keep the hand joints at rest.

    z_up: rotate the recording from AMASS's z-up world into the y-up frame of these motions.
    Posing rotates about the rest pelvis J0, so the exact change of frame is
    R0' = C R0, transl' = C transl + (C - I) J0, with J0 from `skeleton` (the stand-in's by default).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"AMASS file {path} does not exist; expected an .npz with poses, trans, mocap_framerate")
    with np.load(path) as data:
        rate_key = next((k for k in ("mocap_framerate", "mocap_frame_rate") if k in data), None)
        missing = [k for k in ("poses", "trans") if k not in data] + ([] if rate_key else ["mocap_framerate"])
        if missing:
            raise KeyError(f"{path}: missing key(s) {missing}; an AMASS .npz has poses, trans, mocap_framerate, betas "
                           f"(found {sorted(data.files)})")
        poses, trans = data["poses"].astype(np.float64), data["trans"].astype(np.float64)
        fps = float(data[rate_key])
        betas = data["betas"].astype(np.float64) if "betas" in data else None
    if poses.ndim != 2 or poses.shape[1] < 72:
        raise ValueError(f"{path}: 'poses' has shape {poses.shape}; expected (T, 72) or wider (SMPL-H 156, SMPL-X 165)")
    if trans.shape != (len(poses), 3):
        raise ValueError(f"{path}: 'trans' has shape {trans.shape}; expected ({len(poses)}, 3) to match 'poses'")
    smpl = np.zeros((len(poses), 24, 3))
    width = 72 if poses.shape[1] == 72 else 66
    smpl.reshape(len(poses), 72)[:, :width] = poses[:, :width]
    if z_up:
        C = Y_UP_FROM_Z_UP
        pelvis = (skeleton or standin_skeleton()).joints[0]
        smpl[:, 0] = matrix_to_rodrigues(C @ rodrigues_to_matrix(smpl[:, 0]))
        trans = trans @ C.T + (C - np.eye(3)) @ pelvis
    return Motion(path.stem, smpl, trans, fps, betas)
