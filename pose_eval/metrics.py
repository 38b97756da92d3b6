"""Pose errors against the exact 3D joints: MPJPE two ways, PA-MPJPE, per joint.

Standard MPJPE (Ionescu et al., "Human3.6M", TPAMI 2014): the mean over frames and joints of
the Euclidean distance between estimated and true joint, in mm.

The paper's formula (SynthCal, Sec. 4, Table 5) sums the SQUARED errors over the J joints of a
frame before the square root, and averages that over the N frames:

    standard:  (1 / N J) sum_i sum_j |P_ij - P_ij^GT|
    paper:     (1 / N) sum_i sqrt( sum_j |P_ij - P_ij^GT|^2 )

The paper's value is sqrt(J) times a per-frame RMS joint error, about 4.9x the standard MPJPE for
J = 24 joints with equal errors; both are reported, side by side, so neither is mistaken for the
other. A joint that could not be reconstructed (NaN) is excluded and counted; in the paper's
formula a frame's sum then runs over its valid joints and is scaled by J / J_valid (the missing
joints are given the frame's mean squared error), so that missing joints do not lower it.

The cost of a calibration (:func:`excess_mpjpe`) is paired: the same keypoints triangulated
through the estimated and through the true cameras, compared joint by joint on the joints both
reconstructed, so the keypoint noise common to both cancels and a joint one of them lost does
not move the other's mean. Without missing joints it is MPJPE(estimate) - MPJPE(reference).

PA-MPJPE: the standard MPJPE after aligning each estimated frame to the truth by the similarity
transform (scale, rotation, translation) that minimizes the squared error (Umeyama, "Least-
squares estimation of transformation parameters between two point patterns", TPAMI 1991). It
removes global scale and placement errors and leaves the articulation: a calibration error that
only moves or scales the whole body is invisible to it.
"""

from __future__ import annotations

import numpy as np

from stereo_bench.multiview.bundle import aligned_rig_errors

from .motion import JOINT_NAMES


def joint_errors(estimate, truth) -> np.ndarray:
    """(T, J) Euclidean errors (mm), NaN where the estimate is missing."""
    est, gt = np.asarray(estimate, dtype=np.float64), np.asarray(truth, dtype=np.float64)
    if est.shape != gt.shape or est.shape[-1] != 3:
        raise ValueError(f"estimate {est.shape} and truth {gt.shape}: expected equal shapes "
                         f"(T, J, 3)")
    return np.linalg.norm(est - gt, axis=-1)


def mpjpe(estimate, truth) -> float:
    """Mean over frames and joints of the joint error (mm), missing joints excluded."""
    e = joint_errors(estimate, truth)
    return float(e[np.isfinite(e)].mean()) if np.isfinite(e).any() else float("nan")


def excess_mpjpe(estimate, reference, truth) -> float:
    """The paired cost (mm): mean over the joints finite in both of |estimate - truth| minus
    |reference - truth|; NaN when no joint is. Exactly 0 when estimate equals reference."""
    e, r = joint_errors(estimate, truth), joint_errors(reference, truth)
    both = np.isfinite(e) & np.isfinite(r)
    return float((e[both] - r[both]).mean()) if both.any() else float("nan")


def paper_mpjpe(estimate, truth) -> float:
    """The paper's (1/N) sum_i sqrt(sum_j |e_ij|^2) (mm); missing joints: see the module notes."""
    e2 = joint_errors(estimate, truth) ** 2
    valid = np.isfinite(e2)
    n = valid.sum(axis=1)
    frames = n > 0
    per_frame = np.sqrt(np.nansum(e2, axis=1)[frames] * e2.shape[1] / n[frames])
    return float(per_frame.mean()) if per_frame.size else float("nan")


def similarity_align(source: np.ndarray, target: np.ndarray, scale: bool = True):
    """s, R, t minimizing sum |s R source + t - target|^2 over points (N, 3) (Umeyama 1991);
    ``scale=False`` holds s = 1 (the rigid fit, Kabsch)."""
    ms, mt = source.mean(0), target.mean(0)
    xs, xt = source - ms, target - mt
    U, S, Vt = np.linalg.svd(xt.T @ xs / len(source))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U) * np.linalg.det(Vt))])
    R = U @ D @ Vt
    s = np.trace(np.diag(S) @ D) / (xs ** 2).sum(axis=1).mean() if scale else 1.0
    return s, R, mt - s * R @ ms


def pa_mpjpe(estimate, truth) -> float:
    """MPJPE after a per-frame similarity alignment of the estimate to the truth (mm).

    Each frame is aligned on its valid joints; frames with fewer than 3 are left out.
    """
    est, gt = np.asarray(estimate, dtype=np.float64), np.asarray(truth, dtype=np.float64)
    errors = []
    for e, g in zip(est, gt):
        ok = np.isfinite(e).all(axis=1)
        if ok.sum() >= 3:
            s, R, t = similarity_align(e[ok], g[ok])
            errors.append(np.linalg.norm(s * e[ok] @ R.T + t - g[ok], axis=1))
    return float(np.concatenate(errors).mean()) if errors else float("nan")


def pose_metrics(estimate, truth) -> dict:
    """Every figure of a reconstruction against the truth (T, 24, 3) mm, as plain floats.

    mpjpe_mm, paper_mpjpe_mm, pa_mpjpe_mm; per_joint_mm {joint name: mean error}; missing_joints
    (count of NaN joints) out of total_joints.
    """
    e = joint_errors(estimate, truth)
    names = JOINT_NAMES if e.shape[1] == len(JOINT_NAMES) else [str(j) for j in range(e.shape[1])]
    per_joint = [float(col[np.isfinite(col)].mean()) if np.isfinite(col).any() else float("nan")
                 for col in e.T]
    return {
        "mpjpe_mm": mpjpe(estimate, truth),
        "paper_mpjpe_mm": paper_mpjpe(estimate, truth),
        "pa_mpjpe_mm": pa_mpjpe(estimate, truth),
        "per_joint_mm": dict(zip(names, per_joint)),
        "missing_joints": int(np.isnan(e).sum()),
        "total_joints": int(e.size),
    }


def studio_errors(estimate, truth, offsets_frames, true_offsets_frames, up, true_up) -> dict:
    """A studio calibrated without a board against its truth (pose_eval.body_calibration).

    estimate, truth: cameras (cam_from_world) in any two worlds; offsets (C,): each camera's
    clock ahead of camera 0's, frames; up, true_up: the world's vertical in each world. After
    the similarity that best maps the estimated camera centres onto the true ones: the cameras'
    rotation (deg) and centre (mm) errors, mean and worst over cameras; the scale error, % (the
    estimate's size over the truth's, minus 1: what the known quantity got wrong); the worst
    clock error, frames; the vertical's error, deg (camera 0's view of it, so no alignment
    enters).
    """
    e = aligned_rig_errors(estimate, truth)
    offsets = np.asarray(offsets_frames, float) - offsets_frames[0]
    true_offsets = np.asarray(true_offsets_frames, float) - true_offsets_frames[0]
    up_c0 = estimate[0].R @ np.asarray(up, float)
    true_up_c0 = truth[0].R @ np.asarray(true_up, float)
    cos = np.dot(up_c0, true_up_c0) / np.linalg.norm(up_c0) / np.linalg.norm(true_up_c0)
    return {"rotation_deg": float(np.mean(e["rotation_deg"])),
            "rotation_deg_max": float(np.max(e["rotation_deg"])),
            "centre_mm": float(np.mean(e["centre_mm"])),
            "centre_mm_max": float(np.max(e["centre_mm"])),
            "scale_pct": float(100 * (1 / e["scale"] - 1)),
            "offset_frames": float(np.max(np.abs(offsets - true_offsets))),
            "vertical_deg": float(np.degrees(np.arccos(np.clip(cos, -1, 1))))}
