"""Fit an SMPL body to triangulated joints, as EasyMocap's multi-view fitting does.

EasyMocap (Dong et al., "Fast and robust multi-person 3D pose estimation ...", CVPR 2019 /
TPAMI 2021, the tool behind the paper's Table 5) triangulates keypoints and then fits SMPL to
them: a body's bones cannot change length between frames and its joints cannot bend backwards,
so a fit pulls noisy joints onto a plausible body. Here the fit minimizes, over per-frame pose
(global orientation and 23 joint rotations, axis-angle) and translation and one shape for the
whole sequence, in mm^2:

    sum_tj w_tj rho(|J_tj - target_tj|^2) / sum_tj w_tj                   (data; w = 0 for NaN)
  + pose_weight   * mean_t |body_pose_t|^2                                  (L2 pose prior, rad^2)
  + limit_weight  * mean_t sum (backward bend of knees and elbows, rad)^2  (joint limits)
  + smooth_weight * mean_tj |J_t+1 - 2 J_t + J_t-1|^2                       (temporal smoothness)
  + shape_weight  * |betas|^2

rho(e2) = s^2 e2 / (s^2 + e2) is Geman-McClure's robust error with s = ``robust_mm`` (100 mm),
as in SMPLify (Bogo et al., ECCV 2016) and EasyMocap: near e2 = 0 it is least squares, but a
joint triangulated metres off (a false detection that two views cannot reject) pulls with
bounded force. The smoothness term penalizes acceleration, not velocity, so a body walking at
constant speed is not slowed down; it is per frame, so its weight assumes 30 fps.

Joint positions do not depend on the pose blend shapes (SMPL regresses its rest joints from the
shaped template before posing), so the fit runs smplx's own kinematics
(``smplx.lbs.batch_rodrigues`` and ``batch_rigid_transform``) on the regressed rest joints
instead of the full skinning: the same joints as ``pose_eval.body.forward`` (tested), at 7 ms
instead of 210 ms per forward and backward pass of 10 frames. It starts from a per-frame rigid
alignment of the rest torso to the target torso and runs L-BFGS with a strong-Wolfe line
search, on CPU.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from smplx.lbs import batch_rigid_transform, batch_rodrigues

from stereo_bench.core.poses import matrix_to_rodrigues

from .body import MM_PER_M, NUM_JOINTS, load_body_model
from .metrics import similarity_align
from .motion import JOINT

TRANSL_UNIT_M = 0.1
TORSO = [JOINT[n] for n in ("pelvis", "left_hip", "right_hip", "spine1", "spine2", "spine3",
                            "neck", "left_collar", "right_collar")]
# Hinge joints: (joint, axis of flexion, sign of flexion) in SMPL's rest frame.
HINGES = [(JOINT["left_knee"], 0, 1.0), (JOINT["right_knee"], 0, 1.0),
          (JOINT["left_elbow"], 1, -1.0), (JOINT["right_elbow"], 1, 1.0)]


@dataclass(frozen=True, eq=False)
class SmplFit:
    """The fitted body: joints (T, 24, 3) mm in the targets' frame; SMPL parameters in metres
    (global_orient (T, 3), body_pose (T, 69), transl (T, 3), betas (B,)); the weighted RMS
    distance to the targets (mm) and the L-BFGS iterations run."""

    joints: np.ndarray
    global_orient: np.ndarray
    body_pose: np.ndarray
    transl: np.ndarray
    betas: np.ndarray
    rms_mm: float
    iterations: int


def _initial_pose(rest: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per frame, global_orient (T, 3) and transl (T, 3) m that put the rest torso on the
    target's (frames without 3 torso joints take the nearest frame's).

    A torso joint more than 0.2 m off the rigid fit is dropped (worst first, down to 3 joints):
    two views cannot reject a false detection, whose triangulation may land metres away.
    """
    T = len(target)
    R = np.tile(np.eye(3), (T, 1, 1))
    t = np.zeros((T, 3))
    ok = np.array([np.isfinite(target[f, TORSO]).all(-1).sum() >= 3 for f in range(T)])
    if not ok.any():
        raise ValueError("SMPL fit: no frame has three triangulated torso joints to start from")
    for f in range(T):
        g = f if ok[f] else np.flatnonzero(ok)[np.argmin(np.abs(np.flatnonzero(ok) - f))]
        seen = [j for j in TORSO if np.isfinite(target[g, j]).all()]
        while True:
            _, R[f], t[f] = similarity_align(rest[seen], target[g, seen], scale=False)
            off = np.linalg.norm(rest[seen] @ R[f].T + t[f] - target[g, seen], axis=1)
            if off.max() <= 0.2 or len(seen) == 3:
                break
            seen.pop(int(np.argmax(off)))
    # SMPL rotates about the rest pelvis: R (x - J0) + J0 + transl = R x + t.
    return matrix_to_rodrigues(R), t + R @ rest[0] - rest[0]


def fit_smpl(joints_mm, weights=None, model=None, iterations: int = 200, robust_mm: float = 100.0,
             pose_weight: float = 1.0, limit_weight: float = 1e4, smooth_weight: float = 0.1,
             shape_weight: float = 1.0) -> SmplFit:
    """Fit SMPL to target joints (T, 24, 3) mm (NaN = missing), per-joint weights (T, 24) or None.

    model: an smplx SMPL from pose_eval.body.load_body_model (default: the shipped stand-in).
    iterations: L-BFGS iterations at most. robust_mm: scale of the Geman-McClure data term.
    Weights are in mm^2 per unit of each term (module notes).
    """
    model = model if model is not None else load_body_model()
    target = np.asarray(joints_mm, dtype=np.float64) / MM_PER_M
    if target.ndim != 3 or target.shape[1:] != (NUM_JOINTS, 3):
        raise ValueError(f"joints: expected shape (T, {NUM_JOINTS}, 3), got {target.shape}")
    w = np.ones(target.shape[:2]) if weights is None else np.asarray(weights, dtype=np.float64)
    w = np.where(np.isfinite(target).all(-1), w, 0.0)
    if w.sum() == 0:
        raise ValueError("SMPL fit: no target joint to fit")
    T = len(target)
    dtype = torch.float64
    with torch.no_grad():
        j_template = (model.J_regressor @ model.v_template).to(dtype)  # (24, 3) m
        j_shapedirs = torch.einsum("jv,vkb->jkb", model.J_regressor, model.shapedirs).to(dtype)
    go0, tr0 = _initial_pose(j_template.numpy(), target)

    def param(a):
        return torch.tensor(a, dtype=dtype, requires_grad=True)

    # Translation in units of 0.1 m: a unit step then moves the joints about as far as a unit
    # step of a rotation does (bones are 0.1-0.5 m). L-BFGS starts from a multiple of the
    # identity as its Hessian; with this balance it ends 2.5x to 6x closer after 200 iterations.
    global_orient, transl_dm = param(go0), param(tr0 / TRANSL_UNIT_M)
    body_pose, betas = param(np.zeros((T, 69))), param(np.zeros(model.num_betas))
    tgt = torch.tensor(np.nan_to_num(target) * MM_PER_M, dtype=dtype)
    wt = torch.tensor(w / w.sum(), dtype=dtype)

    def joints():
        rest = (j_template + j_shapedirs @ betas).expand(T, NUM_JOINTS, 3)
        rot = batch_rodrigues(torch.cat([global_orient, body_pose], 1).reshape(-1, 3))
        posed, _ = batch_rigid_transform(rot.reshape(T, NUM_JOINTS, 3, 3), rest, model.parents,
                                         dtype=dtype)
        return (posed + TRANSL_UNIT_M * transl_dm[:, None]) * MM_PER_M

    def loss():
        J = joints()
        e2 = ((J - tgt) ** 2).sum(-1)
        data = (wt * robust_mm**2 * e2 / (robust_mm**2 + e2)).sum()
        pose = body_pose.reshape(T, 23, 3)
        limits = sum(torch.relu(-sign * pose[:, j - 1, axis]) ** 2
                     for j, axis, sign in HINGES).mean()
        smooth = ((J[2:] - 2 * J[1:-1] + J[:-2]) ** 2).sum(-1).mean() if T > 2 else 0.0
        return (data + pose_weight * (body_pose ** 2).sum(1).mean() + limit_weight * limits
                + smooth_weight * smooth + shape_weight * (betas ** 2).sum())

    params = [global_orient, body_pose, transl_dm, betas]
    opt = torch.optim.LBFGS(params, max_iter=iterations, line_search_fn="strong_wolfe",
                            tolerance_grad=1e-9, tolerance_change=1e-12, history_size=50)

    def closure():
        opt.zero_grad()
        value = loss()
        value.backward()
        return value

    opt.step(closure)
    with torch.no_grad():
        J = joints()
        rms = float(torch.sqrt((wt * ((J - tgt) ** 2).sum(-1)).sum()))
    n_iter = int(opt.state[params[0]]["n_iter"])
    return SmplFit(J.numpy(), global_orient.detach().numpy(), body_pose.detach().numpy(),
                   (TRANSL_UNIT_M * transl_dm).detach().numpy(), betas.detach().numpy(), rms,
                   n_iter)
