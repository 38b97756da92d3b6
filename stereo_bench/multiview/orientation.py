"""A symmetric board's views made to agree on which point is which, before a rig is joined.

A board whose layout maps onto itself under an in-plane turn (any checkerboard's corners under
180 degrees, a square one's under 90; a symmetric circle grid) can be found with its points
numbered from another corner. OpenCV's chessboard finder numbers from a corner it picks from the
image, and when both ends of the board look alike (both square counts even, or both odd) nothing
tells them apart. One camera's calibration does not notice: the turned numbering is the same set
of points, and the view's pose absorbs the turn. A rig does: in a frame where two cameras number
the board differently, the two poses are of two different boards, and the relative pose drawn
from that frame is off by the turn (a 180-degree turn in one frame of a real 3-camera capture
made its rig 34.7 px RMS and its board twice its size).

So each view of a camera is checked against the cameras already settled, frame by frame: the
relative rotation each frame gives, under each turn of the view's numbering, against the one
most frames agree on. A view whose numbering is turned is renumbered (its points and its pose);
a view that agrees under no turn (a wrong detection) is left out of the rig. Both are named.
Boards whose points carry their identity (ChArUco's ids) are never renumbered.
"""

from __future__ import annotations

import numpy as np

from ..core.poses import geodesic_distance, matrix_to_rodrigues, rodrigues_to_matrix

#: A view whose relative rotation, under its best numbering, differs from its cameras' consensus
#: by more than this is left out. The turns a layout allows differ by 90 degrees or more, and a
#: view's own planar pose is good to a degree or two.
AGREE_DEG = 20.0


def symmetries(object_points: np.ndarray) -> list[tuple[float, np.ndarray]]:
    """The in-plane turns (degrees) about the board's centre that map its points onto
    themselves, each with its permutation ``perm`` (point k lands on point perm[k])."""
    p = np.asarray(object_points, dtype=np.float64)[:, :2]
    centre = p.mean(axis=0)
    extent = float(np.ptp(p, axis=0).max()) or 1.0
    found = []
    for deg in (90.0, 180.0, 270.0):
        a = np.radians(deg)
        R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        turned = (p - centre) @ R.T + centre
        d = np.linalg.norm(turned[:, None] - p[None], axis=-1)
        perm = d.argmin(axis=1)
        if d[np.arange(len(p)), perm].max() < 1e-6 * extent and len(set(perm)) == len(p):
            found.append((deg, perm))
    return found


def _turn(deg: float, centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The board-frame motion p -> R p + t of the in-plane turn by ``deg`` about ``centre``."""
    a = np.radians(deg)
    R = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    return R, centre - R @ centre


def agree(object_points, image_points, rvecs, tvecs, found, names, identified: bool = False):
    """Views renumbered and dropped so that every frame's cameras number the board alike.

    image_points (C, F, N, 2); rvecs, tvecs (C, F, 3) each camera's cam_from_board (NaN where
    not found); found (C, F). Returns copies (image_points, rvecs, tvecs, found) and the list of
    what was done, each {"camera", "frame", "turn_deg"} (renumbered) or {"camera", "frame",
    "disagreement_deg"} (left out). Camera 0's numbering is kept; the others are settled in
    order of the frames they share with the settled ones. ``identified``: the points carry their
    identity (nothing is changed)."""
    pts, rv, tv = (np.array(a, dtype=np.float64) for a in (image_points, rvecs, tvecs))
    found = np.array(found, dtype=bool)
    obj = np.asarray(object_points, dtype=np.float64)
    turns = [] if identified else symmetries(obj)
    if not turns:
        return pts, rv, tv, found, []
    centre = np.append(obj[:, :2].mean(axis=0), 0.0)
    sees = found & np.isfinite(rv).all(-1) & np.isfinite(tv).all(-1)
    C, F = sees.shape
    R = np.full((C, F, 3, 3), np.nan)
    for c, f in zip(*np.nonzero(sees)):
        R[c, f] = rodrigues_to_matrix(rv[c, f])
    options = [(0.0, np.arange(len(obj)))] + turns
    settled, changes = [0], []
    while True:
        rest = [c for c in range(C) if c not in settled]
        shared = {c: sum(int((sees[c] & sees[s]).sum()) for s in settled) for c in rest}
        if not rest or max(shared.values()) == 0:
            break
        j = max(rest, key=lambda c: shared[c])
        resolved = np.zeros(F, dtype=bool)
        for i in sorted(settled, key=lambda s: -int((sees[j] & sees[s]).sum())):
            frames = np.flatnonzero(sees[j] & sees[i] & ~resolved)
            if len(frames) == 0:
                continue
            # cam_j_from_cam_i of every frame (axis 0) under every numbering of camera j's
            # view (axis 1); the consensus is the candidate most frames agree with under some
            # numbering.
            Q = np.stack([[R[j, f] @ _turn(deg, centre)[0].T @ R[i, f].T for deg, _ in options]
                          for f in frames])
            flat = Q.reshape(-1, 3, 3)
            apart = np.degrees(geodesic_distance(flat[:, None], flat[None])).reshape(
                len(flat), len(frames), len(options))
            consensus = flat[int(((apart.min(axis=2)) < AGREE_DEG).sum(axis=1).argmax())]
            for k, f in enumerate(frames):
                off = np.degrees(geodesic_distance(consensus, Q[k]))
                best, deg = min((float(off[o]), d) for o, (d, _) in enumerate(options))
                resolved[f] = True
                if best > AGREE_DEG:
                    pts[j, f], rv[j, f], tv[j, f] = np.nan, np.nan, np.nan
                    found[j, f], sees[j, f] = False, False
                    changes.append({"camera": names[j], "frame": int(f),
                                    "disagreement_deg": round(best, 1)})
                elif deg:
                    perm = dict(options)[deg]
                    renumbered = np.full_like(pts[j, f], np.nan)
                    renumbered[perm] = pts[j, f]
                    pts[j, f] = renumbered
                    Rt, tt = _turn(deg, centre)
                    Rj = R[j, f] @ Rt.T
                    tv[j, f] = tv[j, f] - Rj @ tt
                    rv[j, f] = matrix_to_rodrigues(Rj)
                    R[j, f] = Rj
                    changes.append({"camera": names[j], "frame": int(f), "turn_deg": deg})
        settled.append(j)
    return pts, rv, tv, found, changes


def described(changes: list[dict], frame_name=str) -> list[str]:
    """The changes of :func:`agree` in words, one line per camera."""
    lines = []
    for cam in dict.fromkeys(c["camera"] for c in changes):
        turned = [c for c in changes if c["camera"] == cam and "turn_deg" in c]
        dropped = [c for c in changes if c["camera"] == cam and "disagreement_deg" in c]
        if turned:
            degrees = ", ".join(sorted({f"{c['turn_deg']:g}" for c in turned}))
            lines.append(
                f"camera {cam!r}: the board was found numbered from another corner (turned "
                f"{degrees} degrees: its layout is symmetric) in {len(turned)} frame(s), "
                f"{', '.join(frame_name(c['frame']) for c in turned)}; renumbered for the rig")
        if dropped:
            lines.append(
                f"camera {cam!r}: {len(dropped)} view(s) left out of the rig, whose pose "
                f"disagrees with the other cameras' by more than {AGREE_DEG:g} degrees under "
                f"any numbering: " + ", ".join(f"{frame_name(c['frame'])} "
                                                f"({c['disagreement_deg']:g} deg)"
                                                for c in dropped))
    return lines


def numbered_like(points: np.ndarray, truth: np.ndarray, object_points: np.ndarray
                  ) -> np.ndarray:
    """``points`` (F, N, D) renumbered, frame by frame, by the layout's turn that brings them
    nearest ``truth`` (F, N, D): for scoring against the truth, where which corner of a
    symmetric board comes first is a convention (the views of a frame already agree,
    :func:`agree`, so a frame turns as a whole)."""
    out = np.array(points, dtype=np.float64)
    turns = symmetries(object_points)
    for f in range(len(out)):
        best, chosen = np.inf, out[f]
        for perm in [np.arange(out.shape[1])] + [p for _, p in turns]:
            renumbered = np.full_like(out[f], np.nan)
            renumbered[perm] = out[f]
            d = np.linalg.norm(renumbered - truth[f], axis=-1)
            d = d[np.isfinite(d)]
            if len(d) and d.mean() < best:
                best, chosen = d.mean(), renumbered
        out[f] = chosen
    return out
