"""Build the open body model: an SMPL-compatible stand-in (not SMPL) on SMPL's 24-joint tree.

SMPL's own files are licence-gated, so SynthCal ships this humanoid instead. It has the
layout of an SMPL model file (Loper et al., SIGGRAPH Asia 2015), so `smplx.SMPL` builds it
and runs its own linear-blend-skinning forward pass on it:

- v_template (V, 3), f (F, 3): a T-pose in metres (y up, facing +z, left = +x, pelvis joint at
  the origin) made of closed tapered elliptic capsules around the bones (each part is a
  watertight surface of revolution; parts overlap at the joints instead of being fused).
- J_regressor (24, V): each joint is the mean of the equator rings of the capsules that end
  at it; a ring is centrally symmetric about its joint, so J_regressor @ v_template = J.
- weights (V, 24): linear-blend-skinning weights from the distance to the bones (inverse
  fourth power), restricted to the part's joint, its parent and its children, at most 4 per
  vertex, rows summing to 1.
- shapedirs (V, 3, 3): stature (+6 % size per unit), girth (+10 % radius around each part's
  axis, leaves the joints in place) and leg length (+8 % below the pelvis).
- posedirs (V, 3, 207): zero (no pose correctives), J (24, 3), kintree_table (2, 24), and
  landmark vertices for the extra keypoints smplx appends (nose, eyes, ears, toes, heels,
  fingertips), under the names of smplx's vertex_ids.

Floats are stored as float32 because smplx casts every model array to float32 on loading.
The file is byte-identical from run to run (fixed zip timestamps).

    python scripts/build_body_model.py [output.npz]
"""

from __future__ import annotations

import io
import sys
import zipfile
from dataclasses import dataclass

import numpy as np
import trimesh

from pose_eval.motion import JOINT_NAMES, PARENTS, STANDIN_MODEL_PATH

# Rest joints (m). Centre line, then the left side (+x); the right side mirrors it.
CENTRE = {"pelvis": (0, 0, 0), "spine1": (0, 0.105, -0.015), "spine2": (0, 0.235, -0.005),
          "spine3": (0, 0.29, 0), "neck": (0, 0.50, -0.02), "head": (0, 0.59, 0.02)}
LEFT = {"hip": (0.088, -0.085, 0), "knee": (0.095, -0.50, 0.01), "ankle": (0.095, -0.875, -0.03),
        "foot": (0.11, -0.925, 0.09), "collar": (0.075, 0.41, -0.01), "shoulder": (0.18, 0.43, -0.015),
        "elbow": (0.44, 0.43, -0.025), "wrist": (0.69, 0.43, -0.02), "hand": (0.775, 0.425, -0.02)}

# Capsules: owner joint, start, end, radius at start and end, cap lengths at start and end,
# depth (second cross-section axis / first). An end is a joint name (its equator ring then
# regresses that joint) or (joint, offset). "L" stands for left_ / right_.
CENTRE_PARTS = [
    ("pelvis", "pelvis", "spine1", 0.15, 0.14, 0.13, 0.03, 0.68),
    ("spine1", "spine1", "spine2", 0.14, 0.145, 0.03, 0.03, 0.65),
    ("spine2", "spine2", "spine3", 0.145, 0.155, 0.03, 0.03, 0.68),
    ("spine3", "spine3", "neck", 0.16, 0.09, 0.04, 0.03, 0.62),
    ("neck", "neck", "head", 0.055, 0.05, 0.03, 0.03, 0.9),
    ("head", "head", ("head", (0, 0.07, 0.015)), 0.08, 0.08, 0.05, 0.10, 1.15),
]
SIDE_PARTS = [
    ("L_collar", "L_collar", "L_shoulder", 0.055, 0.06, 0.04, 0.05, 0.9),
    ("L_shoulder", "L_shoulder", "L_elbow", 0.05, 0.038, 0.04, 0.035, 0.95),
    ("L_elbow", "L_elbow", "L_wrist", 0.038, 0.028, 0.03, 0.025, 0.8),
    ("L_wrist", "L_wrist", "L_hand", 0.032, 0.045, 0.02, 0.02, 0.4),  # flat hand, palm down
    ("L_hand", "L_hand", ("L_hand", (0.08, -0.005, 0)), 0.045, 0.035, 0.02, 0.02, 0.35),
    ("L_hip", "L_hip", "L_knee", 0.085, 0.055, 0.06, 0.05, 0.95),
    ("L_knee", "L_knee", "L_ankle", 0.055, 0.035, 0.04, 0.035, 0.95),
    ("L_ankle", ("L_ankle", (0, -0.05, -0.04)), "L_foot", 0.035, 0.045, 0.03, 0.02, 0.6),  # heel to ball
    ("L_foot", "L_foot", ("L_foot", (0.005, -0.005, 0.055)), 0.045, 0.035, 0.02, 0.025, 0.5),  # toes
]
# Surface points whose nearest vertex becomes each smplx extra keypoint (left side; "r" mirrors).
LANDMARKS = {"nose": (0, 0.63, 0.2), "leye": (0.035, 0.67, 0.2), "lear": (0.2, 0.64, 0.02),
             "LBigToe": (0.09, -0.94, 0.25), "LSmallToe": (0.16, -0.94, 0.2), "LHeel": (0.095, -0.96, -0.2),
             "lthumb": (0.74, 0.41, 0.12), "lindex": (0.9, 0.43, 0.05), "lmiddle": (0.92, 0.43, 0.015),
             "lring": (0.92, 0.43, -0.015), "lpinky": (0.9, 0.43, -0.05)}
N_AROUND, N_CAP, STEP = 16, 4, 0.03  # ring vertices (even: rings are centrally symmetric), cap rings, ring spacing (m)


@dataclass
class Capsule:
    owner: int
    vertices: np.ndarray  # (n, 3)
    faces: np.ndarray  # (m, 3), local indices, outward
    axis_point: np.ndarray  # (n, 3) nearest point of the axis line, for the girth direction
    rings: dict  # joint index -> local indices of the equator ring centred on it
    bone_end: np.ndarray  # far end of the axis (the bone of a leaf joint)


def rest_joints() -> dict[str, np.ndarray]:
    joints = {name: np.array(p, float) for name, p in CENTRE.items()}
    for name, p in LEFT.items():
        joints[f"left_{name}"] = np.array(p, float)
        joints[f"right_{name}"] = np.array(p, float) * [-1, 1, 1]
    return joints


def capsule(owner, a, b, ra, rb, la, lb, depth, a_joint=None, b_joint=None) -> Capsule:
    """A closed surface of revolution from pole to pole along a -> b, elliptic cross-sections."""
    length = np.linalg.norm(b - a)
    d = (b - a) / length
    ref = np.array([0, 0, 1.0]) if abs(d[0]) > 0.9 else np.array([1.0, 0, 0])  # width across x, or z for arms
    u = ref - ref @ d * d
    u /= np.linalg.norm(u)
    w = np.cross(d, u)  # (u, w, d) right-handed, so the faces below point outwards
    alpha = np.pi / 2 * np.arange(1, N_CAP + 1) / N_CAP
    n_len = max(1, int(np.ceil(length / STEP)))
    s = np.arange(1, n_len) / n_len
    axial = np.concatenate([-la * np.cos(alpha), s * length, length + lb * np.cos(alpha[::-1])])
    radius = np.concatenate([ra * np.sin(alpha), ra + (rb - ra) * s, rb * np.sin(alpha[::-1])])
    phi = 2 * np.pi * np.arange(N_AROUND) / N_AROUND
    section = np.cos(phi)[:, None] * u + depth * np.sin(phi)[:, None] * w
    rings = a + axial[:, None, None] * d + radius[:, None, None] * section
    vertices = np.concatenate([[a - la * d], rings.reshape(-1, 3), [b + lb * d]])
    n_rings, k = len(axial), np.arange(N_AROUND)
    idx = 1 + np.arange(n_rings)[:, None] * N_AROUND + k  # (rings, around)
    lo, hi = idx[:-1], idx[1:]
    lo_next, hi_next = np.roll(lo, -1, axis=1), np.roll(hi, -1, axis=1)
    side = np.concatenate([np.stack([lo, lo_next, hi_next], -1).reshape(-1, 3),
                           np.stack([lo, hi_next, hi], -1).reshape(-1, 3)])
    top = len(vertices) - 1
    caps = np.concatenate([np.stack([np.zeros(N_AROUND, int), idx[0][np.roll(k, -1)], idx[0]], -1),
                           np.stack([idx[-1], idx[-1][np.roll(k, -1)], np.full(N_AROUND, top)], -1)])
    t = (vertices - a) @ d
    ring_of = {a_joint: idx[N_CAP - 1], b_joint: idx[N_CAP + n_len - 1]}
    return Capsule(owner, vertices, np.concatenate([side, caps]), a + t[:, None] * d,
                   {j: r for j, r in ring_of.items() if j is not None}, b)


def body_parts(joints: dict[str, np.ndarray]) -> list[Capsule]:
    index = {name: i for i, name in enumerate(JOINT_NAMES)}
    specs = CENTRE_PARTS + [tuple(_side(x, prefix, sign) for x in spec)
                            for prefix, sign in (("left_", 1), ("right_", -1)) for spec in SIDE_PARTS]

    def end(e):
        if isinstance(e, str):
            return joints[e], index[e]
        return joints[e[0]] + e[1], None

    parts = []
    for owner, a, b, *shape in specs:
        (pa, ja), (pb, jb) = end(a), end(b)
        parts.append(capsule(index[owner], pa, pb, *shape, a_joint=ja, b_joint=jb))
    return parts


def _side(x, prefix, sign):
    """Resolve 'L_' names to one side and mirror offsets for the right side."""
    if isinstance(x, str):
        return x.replace("L_", prefix)
    if isinstance(x, tuple):
        return (x[0].replace("L_", prefix), np.array(x[1], float) * [sign, 1, 1])
    return x


def segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ab = b - a
    t = np.clip((p - a) @ ab / (ab @ ab), 0, 1)
    return np.linalg.norm(p - (a + t[:, None] * ab), axis=1)


def skinning_weights(parts: list[Capsule], J: np.ndarray) -> np.ndarray:
    """(V, 24): inverse fourth power of the distance to each joint's bones, among the part's
    owner, its parent and children (so a limb never pulls on its neighbour), top 4, normalized."""
    children = {k: [c for c, p in enumerate(PARENTS) if p == k] for k in range(24)}
    leaf_end = {part.owner: part.bone_end for part in parts if not children[part.owner]}
    weights = []
    for part in parts:
        v = part.vertices
        dist = np.full((len(v), 24), np.inf)
        for k in {part.owner, PARENTS[part.owner], *children[part.owner]} - {-1}:
            ends = [J[c] for c in children[k]] or [leaf_end[k]]
            dist[:, k] = np.min([segment_distance(v, J[k], e) for e in ends], axis=0)
        w = np.maximum(dist, 1e-4) ** -4.0
        w[w < np.sort(w, axis=1)[:, -4:-3]] = 0  # keep the 4 largest
        weights.append(w / w.sum(axis=1, keepdims=True))
    return np.concatenate(weights)


def build() -> dict[str, np.ndarray]:
    named = rest_joints()
    J = np.stack([named[n] for n in JOINT_NAMES])
    parts = body_parts(named)
    for part in parts:  # every capsule must be a closed, outward-facing surface
        mesh = trimesh.Trimesh(part.vertices, part.faces, process=False)
        assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    offsets = np.cumsum([0] + [len(p.vertices) for p in parts])
    v = np.concatenate([p.vertices for p in parts])
    faces = np.concatenate([p.faces + o for p, o in zip(parts, offsets)])

    regressor = np.zeros((24, len(v)))
    for part, o in zip(parts, offsets):
        for j, ring in part.rings.items():
            regressor[j, ring + o] = 1.0
    regressor /= regressor.sum(axis=1, keepdims=True)
    assert np.abs(regressor @ v - J).max() < 1e-12

    axis_point = np.concatenate([p.axis_point for p in parts])
    shapedirs = np.stack([0.06 * v,                                          # stature
                          0.10 * (v - axis_point),                           # girth
                          0.08 * np.minimum(v, 0) * [0, 1, 0]], axis=-1)     # leg length

    landmarks = {}
    for name, p in LANDMARKS.items():
        landmarks[name] = int(np.argmin(np.linalg.norm(v - p, axis=1)))
        if name[0] in "lL":
            mirrored = ("r" if name[0] == "l" else "R") + name[1:]
            landmarks[mirrored] = int(np.argmin(np.linalg.norm(v - np.array(p) * [-1, 1, 1], axis=1)))

    f32 = np.float32
    return {
        "v_template": v.astype(f32),
        "f": faces.astype(np.uint32),
        "shapedirs": shapedirs.astype(f32),
        "posedirs": np.zeros((len(v), 3, 207), f32),
        "J_regressor": regressor.astype(f32),
        "weights": skinning_weights(parts, J).astype(f32),
        "kintree_table": np.stack([PARENTS, np.arange(24)]).astype(np.int64),
        "J": J,
        "joint_names": np.array(JOINT_NAMES),
        "shape_names": np.array(["stature", "girth", "leg_length"]),
        "landmark_names": np.array(list(landmarks)),
        "landmark_vertex_ids": np.array(list(landmarks.values()), np.int64),
        "description": np.array("SynthCal open body model: an SMPL-compatible stand-in, not SMPL. "
                                "Built by scripts/build_body_model.py. MIT licence."),
    }


def save_npz(path, arrays: dict[str, np.ndarray]) -> None:
    """np.savez_compressed, but with fixed zip timestamps so that rebuilds are byte-identical."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive:
        for name, array in arrays.items():
            buffer = io.BytesIO()
            np.lib.format.write_array(buffer, np.ascontiguousarray(array), allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            archive.writestr(info, buffer.getvalue(), compresslevel=9)


def main(argv: list[str]) -> None:
    out = argv[1] if len(argv) > 1 else STANDIN_MODEL_PATH
    model = build()
    save_npz(out, model)
    v = model["v_template"]
    print(f"{out}: {len(v)} vertices, {len(model['f'])} faces, "
          f"height {v[:, 1].max() - v[:, 1].min():.3f} m")


if __name__ == "__main__":
    main(sys.argv)
