"""Calibration from the body: a studio's extrinsics and its cameras' clock offsets from the 2D
keypoints of people moving in it, the intrinsics being known.

The steps, each a standard tool of structure from motion applied to body joints (a joint of a
person in a frame is one 3D point, seen by every camera that detected it):

1. **Pairs.** For every pair of cameras and every whole-frame shift of one's clock against the
   other's (up to ``max_offset_frames``), the essential matrix of the joints both saw at
   matched times, by Nister's five-point solver in RANSAC (OpenCV's ``findEssentialMat``;
   Nister, "An efficient solution to the five-point relative pose problem", PAMI 2004). The
   shift with the most inliers is the pair's; unsynchronised cameras see a moving body
   inconsistently, so a wrong shift loses inliers.
2. **Join.** A maximum spanning tree over the pairs, weighted by their inliers, sets each
   camera's whole-frame offset from camera 0 (summed along the tree) and the order in which
   cameras join: the root pair's relative pose (``recoverPose``), then each next camera by PnP
   in RANSAC on the joints triangulated so far, which carries the scale of the first pair to
   every camera (relative poses alone would leave one scale per edge).
   A detector that takes a person's back for their front swaps left and right in that view:
   per frame and person, every choice of swaps in cameras 1.. is triangulated and the one of
   least robust reprojection cost is read (:func:`mirror_labels`), then the cameras and tracks
   are fitted again, for as long as the fit improves.
3. **Bundle adjustment** of the cameras' poses, their clock offsets to a fraction of a frame
   and every joint's 3D track, with a robust loss (soft L1, its scale from the residuals' MAD)
   on the reprojection error weighted by the keypoint's confidence. A camera whose clock is
   offset sees a joint between two of camera 0's frames, so with clocks to estimate each
   track is a uniform cubic B-spline with a control point per frame (continuous-time
   trajectories, as in Furgale et al., "Continuous-time batch estimation using temporal basis
   functions", ICRA 2012), whose derivative gives the offset's Jacobian. Each clock starts
   from a scan against the tracks the other cameras triangulate (a moving body's cost against
   time has a minimum per stride, so a descent from a whole frame can stop in the wrong one).
   The analytic Jacobian is sparse and exact (tested against finite differences).
4. **The vertical** from the floor: the feet rest on it while they stand. Each foot joint's
   slowest third of frames are its stances; the plane through them (least squares, then
   without points beyond 3 robust deviations) is parallel to the floor, and its normal points
   up on the side of the heads. A crowd that never walks (feet at a few spots) gives no plane:
   the normal is then the mean direction from the feet to the heads, and ``vertical`` says so.
5. **Scale** from one known quantity: one baseline between two cameras, or the first person's
   height. Height is read off rigid segments, not off the head's height over the floor, which
   drops as the knees bend: the median length of each segment of a chain from the ankles to
   the head (shin, thigh, pelvis to neck, neck to head), summed, times the body model's ratio
   of stature to that chain at rest.

The result is the studio in a floor frame: z up, x along camera 0's view projected on the
floor, the origin on the stance plane below the people's mean position; lengths in mm.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree

from stereo_bench.core.camera import Camera, project_with_jacobians
from stereo_bench.core.poses import matrix_to_rodrigues, rodrigues_to_matrix
from stereo_bench.multiview.triangulate import triangulate_dlt, triangulate_robust

MIN_PAIR_INLIERS = 30  # fewer joints agreeing on a pair's geometry do not join it
MAX_PAIR_POINTS = 4000  # a pair's RANSAC sees at most this many joints (drawn reproducibly)
STANCE_SHARE = 1 / 3  # the slowest share of a foot joint's frames taken as its stances
FLAT_SPREAD = 0.15  # stance points spread less than this (2nd over 1st extent) give no plane
# The cameras and tracks are refitted after each round of left-right swaps (mirror_labels).
MIRROR_ROUNDS = 3
MAX_MIRROR_CAMERAS = 10  # views' swaps are searched over 2^(C-1) choices per frame
MAX_OFFSET_STEP = 1.0  # frames the bundle adjustment may move a clock from its scan
CLOCK_ROUNDS = 3  # scans and adjustments of the clocks, while one is held at its bound
# The tracks' smoothness prior, per px of focal length: a control point's second difference d
# (the first pair's baseline is the unit) costs SMOOTHING * f * d "px". A walking body's joints
# accelerate by about 0.002 baselines per frame^2 (0.2 px here, against 1 px of keypoint noise
# seen by several cameras); an unobserved control point is held by it.
SMOOTHING = 0.1
GAUGE_WEIGHT = 1e3  # px per relative change of the studio's scale in the bundle adjustment


@dataclass(frozen=True)
class Scale:
    """The known quantity that makes the studio metric: ``baseline_mm`` between cameras
    ``cameras`` (two names), or a person's ``height_mm``."""

    baseline_mm: float | None = None
    cameras: tuple[str, str] | None = None
    height_mm: float | None = None

    def __post_init__(self):
        given = (self.baseline_mm is not None) + (self.height_mm is not None)
        if given != 1:
            raise ValueError("scale: give one known quantity, a baseline or a height")
        value = self.baseline_mm if self.baseline_mm is not None else self.height_mm
        if not (np.isfinite(value) and value > 0):
            raise ValueError(f"scale: expected a positive length in mm, got {value!r}")
        if self.baseline_mm is not None and (self.cameras is None or len(self.cameras) != 2
                                             or self.cameras[0] == self.cameras[1]):
            raise ValueError("scale: a baseline needs the names of two different cameras")


@dataclass(frozen=True)
class Skeleton:
    """Which tracks are what: the joint indices of feet and heads (every person's, tracks side
    by side), the first person's height chain as (joint, joint, weight) segments, and the
    body's stature over that chain's weighted length at rest."""

    feet: tuple[int, ...]
    heads: tuple[int, ...]
    chain: tuple[tuple[int, int, float], ...]
    stature_per_chain: float
    mirror: tuple[int, ...] = ()  # the tracks' permutation that swaps left and right (or none)
    joints: int = 24  # tracks per person


@dataclass(frozen=True, eq=False)
class BodyCalibration:
    """cameras: cam_from_world in the floor frame (mm); offsets_frames (C,): each camera's clock
    ahead of camera 0's, in frames; points (T, N, 3) the joints' tracks at camera 0's frames
    (NaN where not reconstructed); rms_px: the reprojection error's RMS over the inliers;
    vertical: 'floor' or 'body axis'; pairs: per camera pair, its shift and inliers; order: the
    cameras in the order they joined; mirrored_views: how many views (camera, frame, person)
    had their left and right swapped back."""

    cameras: list[Camera]
    offsets_frames: np.ndarray
    points: np.ndarray
    rms_px: float
    vertical: str
    pairs: list[dict] = field(default_factory=list)
    order: list[str] = field(default_factory=list)
    mirrored_views: int = 0  # views (camera, frame, person) whose left and right were swapped


# ----------------------------------------------------------------------------------------------
# 1. Pairs
# ----------------------------------------------------------------------------------------------

def _normalized(cameras: list[Camera], pixels: np.ndarray) -> np.ndarray:
    """(C, T, N, 2) undistorted normalized coordinates, NaN where undetected or without a ray."""
    out = np.full(pixels.shape, np.nan)
    for c, cam in enumerate(cameras):
        ok = np.all(np.isfinite(pixels[c]), axis=-1)
        xy, valid = cam.undistorted(pixels[c][ok])
        keep = np.where(valid[:, None], xy, np.nan)
        out[c][ok] = keep
    return out


def shifted(track: np.ndarray, shift: int, segments: np.ndarray) -> np.ndarray:
    """track (T, ...) read ``shift`` frames later: out[f] = track[f + shift], NaN where f + shift
    leaves the sequence or its segment (frames of different recordings are not neighbours)."""
    T = len(track)
    out = np.full(track.shape, np.nan)
    f = np.arange(T)
    g = f + shift
    ok = (g >= 0) & (g < T)
    ok[ok] &= segments[g[ok]] == segments[f[ok]]
    out[f[ok]] = track[g[ok]]
    return out


def _sampson2(E: np.ndarray, pa: np.ndarray, pb: np.ndarray) -> np.ndarray:
    """Squared Sampson distances (normalized units^2) of matches pa -> pb under E."""
    xa = np.column_stack([pa, np.ones(len(pa))])
    xb = np.column_stack([pb, np.ones(len(pb))])
    Ex, Etx = xa @ E.T, xb @ E
    return np.sum(xb * Ex, 1) ** 2 / (Ex[:, 0] ** 2 + Ex[:, 1] ** 2 + Etx[:, 0] ** 2
                                      + Etx[:, 1] ** 2)


def _pair(xa: np.ndarray, xb: np.ndarray, threshold: float, rng_seed: int):
    """RANSAC essential matrix of matched normalized points (T, N, 2) -> (inliers, E, mask,
    points a, points b, MSAC score) or None. The score, the mean over every match of its
    squared Sampson distance capped at 3 thresholds (Torr and Zisserman, "MLESAC", CVIU 2000),
    varies smoothly with the clock shift where an inlier count jumps with RANSAC's draws."""
    both = np.all(np.isfinite(xa), -1) & np.all(np.isfinite(xb), -1)
    pa, pb = xa[both], xb[both]
    if len(pa) < MIN_PAIR_INLIERS:
        return None
    if len(pa) > MAX_PAIR_POINTS:
        pick = np.random.default_rng(rng_seed).choice(len(pa), MAX_PAIR_POINTS, replace=False)
        pa, pb = pa[np.sort(pick)], pb[np.sort(pick)]
    cv2.setRNGSeed(rng_seed)
    E, mask = cv2.findEssentialMat(pa, pb, np.eye(3), method=cv2.RANSAC, prob=0.999,
                                   threshold=threshold)
    if E is None or E.shape != (3, 3):  # several solutions stacked: none is trusted
        return None
    mask = mask.ravel().astype(bool)
    cap = (3 * threshold) ** 2
    score = float(np.mean(np.minimum(_sampson2(E, pa, pb), cap)) / cap)
    return int(mask.sum()), E, mask, pa, pb, score


def pair_geometry(x: np.ndarray, a: int, b: int, max_shift: int, threshold: float,
                  segments: np.ndarray) -> dict | None:
    """The shift d (camera b's clock ahead of a's, whole frames) and b_from_a (R, unit t) at
    that shift; None if no shift gives MIN_PAIR_INLIERS. The shift is the rounded vertex of a
    parabola through the MSAC scores of the best shift and its neighbours (two each side):
    a moving body fits worse the further the shift is from the truth, but a single score is
    noisy, and near a circular walk's degeneracy neighbouring shifts score alike."""
    found = {}
    for d in range(-max_shift, max_shift + 1):
        # b's frame g shows a's time g + d: pair a's frame g + d with b's frame g.
        pair = _pair(shifted(x[a], d, segments), x[b], threshold, 1000 * a + b)
        if pair is not None and pair[0] >= MIN_PAIR_INLIERS:
            found[d] = pair
    if not found:
        return None
    best = min(found, key=lambda d: found[d][5])
    near = [d for d in range(best - 2, best + 3) if d in found]
    if len(near) >= 3:
        c2, c1, _ = np.polyfit(near, [found[d][5] for d in near], 2)
        if c2 > 0:  # a minimum: its vertex, if it falls among the shifts measured
            vertex = int(np.rint(-c1 / (2 * c2)))
            best = vertex if vertex in found and abs(vertex - best) <= 2 else best
    inliers, E, mask, pa, pb, _ = found[best]
    _, R, t, _ = cv2.recoverPose(E, pa, pb, np.eye(3), mask=mask.astype(np.uint8)[:, None])
    return {"shift": best, "inliers": inliers, "R": R, "t": t.ravel()}


# ----------------------------------------------------------------------------------------------
# 2. Join
# ----------------------------------------------------------------------------------------------

def spanning_tree(pairs: dict, n: int, names: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """(order, parent) of a maximum spanning tree over the pairs (weight: inliers) from
    camera 0; ValueError naming the cameras no pair joins."""
    W = np.zeros((n, n))
    for (a, b), p in pairs.items():
        W[a, b] = 1.0 / (1.0 + p["inliers"])  # more inliers, lighter edge
    order, parent = breadth_first_order(minimum_spanning_tree(W), 0, directed=False)
    if len(order) < n:
        lost = [names[c] for c in range(n) if c not in set(order.tolist())]
        raise ValueError(f"cameras {lost} share too few body joints with camera {names[0]!r} "
                         f"(at least {MIN_PAIR_INLIERS} consistent joints per pair): they "
                         f"cannot be joined; are the people in their views?")
    return order, parent


def _edge(pairs: dict, a: int, b: int):
    """(shift of b against a, b_from_a R, t) whichever way the pair was measured."""
    if (a, b) in pairs:
        p = pairs[(a, b)]
        return p["shift"], p["R"], p["t"]
    p = pairs[(b, a)]
    return -p["shift"], p["R"].T, -p["R"].T @ p["t"]


def _posed(camera: Camera, R: np.ndarray, t: np.ndarray) -> Camera:
    return camera.with_params(rvec=matrix_to_rodrigues(R), tvec=np.asarray(t, float))


def _synchronised(x: np.ndarray, shifts: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """Each camera's tracks read at camera 0's frames: camera c's frame f - shift_c."""
    return np.stack([shifted(x[c], -int(s), segments) for c, s in enumerate(shifts)])


def initial_rig(cameras: list[Camera], pixels: np.ndarray, x: np.ndarray, pairs: dict,
                order: np.ndarray, parent: np.ndarray, threshold: float,
                segments: np.ndarray) -> tuple[list[Camera], np.ndarray]:
    """(cameras posed in camera 0's frame at the first pair's scale, whole-frame shifts (C,))."""
    n = len(cameras)
    shifts = np.zeros(n, dtype=int)
    for c in order[1:]:
        shifts[c] = shifts[parent[c]] + _edge(pairs, parent[c], c)[0]
    sync = _synchronised(pixels, shifts, segments)
    xs = _synchronised(x, shifts, segments)
    posed = {0: _posed(cameras[0], np.eye(3), np.zeros(3))}
    first = order[1]
    _, R, t = _edge(pairs, 0, first)  # the tree's first edge leaves the root
    posed[first] = _posed(cameras[first], R, t)
    for c in order[2:]:
        known = sorted(posed)
        X = triangulate_dlt([posed[k] for k in known], sync[known])
        ok = np.all(np.isfinite(X), -1) & np.all(np.isfinite(xs[c]), -1)
        if np.count_nonzero(ok) < MIN_PAIR_INLIERS:
            raise ValueError(f"camera {cameras[c].name!r} sees too few of the joints triangulated "
                             f"by the cameras before it ({np.count_nonzero(ok)})")
        found, rvec, tvec, inl = cv2.solvePnPRansac(
            X[ok].astype(np.float64), xs[c][ok].astype(np.float64), np.eye(3), None,
            reprojectionError=threshold, iterationsCount=1000, confidence=0.999,
            flags=cv2.SOLVEPNP_EPNP)
        if not found or inl is None or len(inl) < MIN_PAIR_INLIERS:
            raise ValueError(f"camera {cameras[c].name!r}: no pose agrees with the joints "
                             f"triangulated by the cameras before it")
        inl = inl.ravel()
        _, rvec, tvec = cv2.solvePnP(X[ok][inl], xs[c][ok][inl], np.eye(3), None, rvec, tvec,
                                     useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
        posed[c] = _posed(cameras[c], rodrigues_to_matrix(rvec.ravel()), tvec.ravel())
    return [posed[c] for c in range(n)], shifts


# ----------------------------------------------------------------------------------------------
# 3. Bundle adjustment
# ----------------------------------------------------------------------------------------------

def cubic_bspline(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weights (M, 4) of the control points at frames i-1, i, i+1, i+2 for the track at i + u,
    and their derivatives in u (M, 4): the uniform cubic B-spline. Unlike an interpolating
    spline its weights' sum of squares hardly depends on u (0.46 to 0.5), so noisy control
    points do not make half frames look better fitted than whole ones: a clock offset read off
    them is not pulled towards half frames."""
    u = np.asarray(u, dtype=np.float64)[:, None]
    u2, u3 = u * u, u * u * u
    w = np.hstack([(1 - u) ** 3, 3 * u3 - 6 * u2 + 4, -3 * u3 + 3 * u2 + 3 * u + 1, u3]) / 6
    dw = np.hstack([-3 * (1 - u) ** 2, 9 * u2 - 12 * u, -9 * u2 + 6 * u + 3, 3 * u2]) / 6
    return w, dw


def on_frames(control: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """Tracks (T, N, 3) at the frames of the B-spline with control points ``control``
    (T, N, 3): (P[f-1] + 4 P[f] + P[f+1]) / 6, NaN where a neighbour is missing."""
    out = np.full(control.shape, np.nan)
    same = (segments[:-2] == segments[1:-1]) & (segments[2:] == segments[1:-1])
    mid = (control[:-2] + 4 * control[1:-1] + control[2:]) / 6
    out[1:-1] = np.where(same[:, None, None], mid, np.nan)
    return out


class _Bundle:
    """The bundle adjustment's problem: parameters [poses of cameras 1.. (rvec, t) | offsets of
    cameras 1.. (frames) if estimated | active points (3 each): the joints at camera 0's
    frames, or with offsets the tracks' B-spline control points]; residuals: the weighted
    reprojection errors (px) of the observations whose spline stencil is all active points.

    Stencils are fixed when the problem is built (from the offsets then); an offset that moves
    by less than a frame stays on its stencil's spline, which extends smoothly past its ends,
    and :func:`bundle_adjust` rebuilds the problem between rounds."""

    def __init__(self, cameras, pixels, weights, points, offsets, estimate_offsets, segments):
        C, T, N = pixels.shape[:3]
        self.cameras, self.C, self.T, self.N = cameras, C, T, N
        self.estimate_offsets = estimate_offsets
        active = np.all(np.isfinite(points), -1)
        self.index = np.full((T, N), -1)
        self.index[active] = np.arange(np.count_nonzero(active))
        self.n_points = int(np.count_nonzero(active))
        self.obs = []  # per camera: (uv (M, 2), w (M,), stencil point indices (M, width), base)
        for c in range(C):
            f, n = np.nonzero(np.all(np.isfinite(pixels[c]), -1) & (weights[c] > 0))
            tau = f + offsets[c]
            if estimate_offsets:
                i = np.floor(tau).astype(int)
                frames = i[:, None] + np.arange(-1, 3)
            else:
                i = np.rint(tau).astype(int)
                frames = i[:, None]
            inside = np.all((frames >= 0) & (frames < T), 1)
            frames, f, n, i = frames[inside], f[inside], n[inside], i[inside]
            same = np.all(segments[frames] == segments[f][:, None], 1)
            stencil = self.index[frames, n[:, None]]
            keep = same & np.all(stencil >= 0, 1)
            self.obs.append((pixels[c][f[keep], n[keep]], weights[c][f[keep], n[keep]],
                             stencil[keep], i[keep] - f[keep]))
        self.n_obs = 2 * sum(len(o[0]) for o in self.obs)
        # B-spline control points: a weak second-difference prior ties each to its neighbours,
        # so that one few observations reach (a track's ends) cannot drift off unbounded.
        triples = np.zeros((0, 3), dtype=int)
        if estimate_offsets:
            mid = np.arange(1, T - 1)
            same = (segments[mid - 1] == segments[mid]) & (segments[mid + 1] == segments[mid])
            idx = np.stack([self.index[mid - 1], self.index[mid], self.index[mid + 1]], -1)
            ok = same[:, None] & np.all(idx >= 0, -1)  # (T-2, N)
            triples = idx[ok]
        self.triples = triples
        self.smoothing = SMOOTHING * float(np.mean([[c.fx, c.fy] for c in cameras]))
        # The gauge: camera 0 is held at the identity, and the distance to the camera farthest
        # from it at its start (a scale for the whole studio; without it the solver may drift
        # along the scale it cannot see until the reconstruction collapses).
        self.gauge = 1 + int(np.argmax([np.linalg.norm(c.tvec) for c in cameras[1:]]))
        self.gauge_mm = float(np.linalg.norm(cameras[self.gauge].tvec))
        self.n_res = self.n_obs + 3 * len(triples) + 1

    def pack(self, cameras, offsets, points) -> np.ndarray:
        poses = [np.concatenate([cam.rvec, cam.tvec]) for cam in cameras[1:]]
        parts = [np.concatenate(poses) if poses else np.zeros(0)]
        if self.estimate_offsets:
            parts.append(np.asarray(offsets[1:], float))
        parts.append(points[self.index >= 0].ravel())
        return np.concatenate(parts)

    def unpack(self, x):
        k = 6 * (self.C - 1)
        poses = x[:k].reshape(-1, 6)
        cams = [self.cameras[0]] + [cam.with_params(rvec=p[:3], tvec=p[3:])
                                    for cam, p in zip(self.cameras[1:], poses)]
        offsets = np.zeros(self.C)
        if self.estimate_offsets:
            offsets[1:] = x[k:k + self.C - 1]
            k += self.C - 1
        return cams, offsets, x[k:].reshape(-1, 3)

    def _point_column(self) -> int:
        return 6 * (self.C - 1) + (self.C - 1 if self.estimate_offsets else 0)

    def _evaluate(self, x, jacobian: bool):
        cams, offsets, P = self.unpack(x)
        res, rows, cols, vals = [], [], [], []
        row = 0
        p0 = self._point_column()
        for c, (uv, w, stencil, base) in enumerate(self.obs):
            M = len(uv)
            if M == 0:
                continue
            cam = cams[c]
            if self.estimate_offsets:
                # tau = f + offset; the stencil starts at frame f + base - 1.
                u = offsets[c] - base
                wts, dwts = cubic_bspline(u)
                Xs = P[stencil]  # (M, 4, 3)
                X = np.einsum("mk,mkd->md", wts, Xs)
            else:
                X = P[stencil[:, 0]]
            proj, J = project_with_jacobians(X, cam.intrinsics, cam.dist, cam.rvec, cam.tvec,
                                             jacobians=jacobian, model=cam.model)
            res.append(((proj - uv) * w[:, None]).ravel())
            if jacobian:
                r = row + np.arange(2 * M).reshape(M, 2)
                Jp = J["point"] * w[:, None, None]  # (M, 2, 3)
                if c > 0:
                    Jpose = J["pose"] * w[:, None, None]
                    rows.append(np.repeat(r[:, :, None], 6, 2).ravel())
                    cols.append(np.broadcast_to(6 * (c - 1) + np.arange(6), (M, 2, 6)).ravel())
                    vals.append(Jpose.ravel())
                    if self.estimate_offsets:
                        dX = np.einsum("mk,mkd->md", dwts, Xs)
                        rows.append(r.ravel())
                        cols.append(np.full(2 * M, 6 * (self.C - 1) + c - 1))
                        vals.append(np.einsum("mij,mj->mi", Jp, dX).ravel())
                weights_k = wts if self.estimate_offsets else np.ones((M, 1))
                for k in range(stencil.shape[1]):
                    rows.append(np.repeat(r[:, :, None], 3, 2).ravel())
                    cols.append((p0 + 3 * stencil[:, k, None, None] + np.arange(3)).repeat(
                        2, 1).ravel())
                    vals.append((Jp * weights_k[:, k, None, None]).ravel())
            row += 2 * M
        if len(self.triples):
            a, b, c3 = (self.triples[:, k] for k in range(3))
            res.append((self.smoothing * (P[a] - 2 * P[b] + P[c3])).ravel())
            if jacobian:
                r = row + np.arange(3 * len(a)).reshape(-1, 3)
                for k, coef in ((a, 1.0), (b, -2.0), (c3, 1.0)):
                    rows.append(r.ravel())
                    cols.append((p0 + 3 * k[:, None] + np.arange(3)).ravel())
                    vals.append(np.full(r.size, coef * self.smoothing))
        t = cams[self.gauge].tvec
        res.append(np.array([GAUGE_WEIGHT * (np.linalg.norm(t) / self.gauge_mm - 1)]))
        if jacobian:
            rows.append(np.full(3, row + 3 * len(self.triples)))
            cols.append(6 * (self.gauge - 1) + 3 + np.arange(3))
            vals.append(GAUGE_WEIGHT * t / (np.linalg.norm(t) * self.gauge_mm))
        r = np.concatenate(res) if res else np.zeros(0)
        if not jacobian:
            return r
        shape = (self.n_res, len(x))
        return r, coo_matrix((np.concatenate(vals), (np.concatenate(rows),
                                                     np.concatenate(cols))), shape).tocsr()

    def residuals(self, x):
        return self._evaluate(x, False)

    def jacobian(self, x):
        return self._evaluate(x, True)[1]


def _offset_bounds(problem: _Bundle, offsets: np.ndarray, start: np.ndarray, n: int
                   ) -> tuple[np.ndarray, ...]:
    """Bounds keeping each offset within half a frame beyond its stencil's middle interval (the
    spline is not trusted further out, and the next round moves the stencil) and within
    MAX_OFFSET_STEP of where the adjustment started (the scan's minimum: a descent that goes
    further has left it for another stride's)."""
    lo, hi = np.full(n, -np.inf), np.full(n, np.inf)
    if problem.estimate_offsets:
        k = 6 * (problem.C - 1)
        here = np.floor(offsets[1:])
        lo[k:k + problem.C - 1] = np.maximum(here - 0.5, start[1:] - MAX_OFFSET_STEP)
        hi[k:k + problem.C - 1] = np.minimum(here + 1.5, start[1:] + MAX_OFFSET_STEP)
    return lo, hi


class Adjusted(NamedTuple):
    """A bundle adjustment's result: cameras, offsets (C,), points (T, N, 3) (with offsets, the
    B-spline's control points), the reprojection RMS over inliers (px), the robust scale (px:
    3 MADs of the residuals) and the mean soft-L1 cost at ``scale_px`` as given (comparable
    between adjustments given the same scale)."""

    cameras: list
    offsets: np.ndarray
    points: np.ndarray
    rms_px: float
    robust_px: float
    cost: float


def bundle_adjust(cameras, pixels, weights, points, offsets, estimate_offsets: bool,
                  segments: np.ndarray, scale_px: float | None = None,
                  max_rounds: int = 6) -> Adjusted:
    """The bundle adjustment (module notes); camera 0 holds the gauge. scale_px: the soft-L1
    scale (default: 3 MADs of the start's residuals). Rounds rebuild the stencils until no
    offset leaves its frame interval (one round when offsets are fixed)."""
    start = np.asarray(offsets, float).copy()
    for _ in range(max_rounds if estimate_offsets else 1):
        problem = _Bundle(cameras, pixels, weights, points, offsets, estimate_offsets, segments)
        x0 = problem.pack(cameras, offsets, points)
        if scale_px is None:  # the soft L1 scale: 3 robust deviations of the start's residuals
            r0 = problem.residuals(x0)[:problem.n_obs]
            scale_px = max(0.5, 3 * 1.4826 * float(np.median(np.abs(r0))))
        sol = least_squares(problem.residuals, x0, jac=problem.jacobian, method="trf",
                            bounds=_offset_bounds(problem, offsets, start, len(x0)),
                            loss="soft_l1", f_scale=scale_px, x_scale="jac",
                            tr_solver="lsmr", max_nfev=50, xtol=1e-10, ftol=1e-8)
        before = np.floor(offsets)
        cameras, offsets, P = problem.unpack(sol.x)
        points = np.full(points.shape, np.nan)
        points[problem.index >= 0] = P
        r = sol.fun[:problem.n_obs]
        if np.array_equal(np.floor(offsets), before):
            break
    robust = max(0.5, 3 * 1.4826 * float(np.median(np.abs(r))))
    e = np.linalg.norm(r.reshape(-1, 2), axis=1)
    inl = e < 2 * robust
    rms = float(np.sqrt(np.mean(e[inl] ** 2))) if inl.any() else float("nan")
    return Adjusted(cameras, offsets, points, rms, robust,
                    float(np.mean(_soft_l1(np.abs(r), scale_px))))


def _soft_l1(e: np.ndarray, scale: float) -> np.ndarray:
    return 2 * (np.sqrt(1 + (e / scale) ** 2) - 1)


def scan_offset(camera: Camera, pixels: np.ndarray, weights: np.ndarray, points: np.ndarray,
                centre: float, scale_px: float, segments: np.ndarray,
                reach: float = 1.5, step: float = 0.02) -> float:
    """The clock offset (frames) of ``camera`` that best fits its keypoints (T, N, 2) to the
    joints' tracks ``points`` (T, N, 3) at camera 0's frames, triangulated without it: the
    least soft-L1 reprojection cost over offsets within ``reach`` frames of ``centre``, the
    tracks taken as the B-spline's control points. A scan, not a descent: the cost of a moving
    body against time has a minimum per stride, and the whole-frame start may be one off."""
    T = len(points)
    f, n = np.nonzero(np.all(np.isfinite(pixels), -1) & (weights > 0))
    best, best_cost = centre, np.inf
    for d in np.arange(centre - reach, centre + reach + step / 2, step):
        tau = f + d
        i = np.floor(tau).astype(int)
        frames = i[:, None] + np.arange(-1, 3)
        ok = np.all((frames >= 0) & (frames < T), 1)
        ok[ok] &= np.all(segments[frames[ok]] == segments[f[ok]][:, None], 1)
        w, _ = cubic_bspline(tau[ok] - i[ok])
        X = np.einsum("mk,mkd->md", w, points[frames[ok], n[ok][:, None]])
        good = np.all(np.isfinite(X), -1)
        if np.count_nonzero(good) < MIN_PAIR_INLIERS:
            continue
        e = np.linalg.norm(camera.project(X[good]) - pixels[f[ok][good], n[ok][good]], axis=-1)
        # A mean over the joints it sees, so that offsets whose stencils lose a few frames at
        # the ends are not favoured or penalised by the count.
        cost = float(np.mean(weights[f[ok][good], n[ok][good]] * _soft_l1(e, scale_px)))
        if cost < best_cost:
            best, best_cost = float(d), cost
    return best


def _robust_start(posed: list[Camera], sync: np.ndarray, threshold_px: float) -> np.ndarray:
    """The joints' tracks (T, N, 3) to start the bundle adjustment: outlier views are left out
    (3+ views); a joint whose views still disagree by far (two views, one an outlier) starts
    as missing rather than as a wrong start."""
    T, N = sync.shape[1:3]
    points, inliers = triangulate_robust(posed, sync, threshold_px=3 * threshold_px,
                                         refine=False)
    err = np.stack([np.linalg.norm(cam.project(points.reshape(-1, 3)).reshape(T, N, 2) - sync[c],
                                   axis=-1) for c, cam in enumerate(posed)])
    err = np.where(inliers & np.isfinite(err), err, 0.0)
    points[err.max(axis=0) > 10 * threshold_px] = np.nan
    # A joint behind a camera that saw it (its view an outlier the DLT was not told of) would
    # start that view's residual at any size, near its pole: missing too.
    seen = np.all(np.isfinite(sync), -1)
    depth = np.stack([cam.world_to_cam(points.reshape(-1, 3))[:, 2].reshape(T, N)
                      for cam in posed])
    points[np.any(seen & ~(depth > 0), axis=0)] = np.nan
    return points


def mirror_labels(posed: list[Camera], sync: np.ndarray, shifts: np.ndarray,
                  segments: np.ndarray, skeleton: Skeleton, threshold_px: float) -> np.ndarray:
    """(C, T, people) bool: which views to read with left and right swapped, camera c's frame f
    being camera 0's f + shift_c; sync (C, T, N, 2): the keypoints as labelled, at camera 0's
    frames.

    Per frame and person, every choice of swaps in cameras 1.. (camera 0 as labelled: swapping
    every view renames the person's sides and changes no geometry) is triangulated, and the
    choice with the least robust reprojection cost (errors capped at 3 thresholds) wins, so a
    view is judged by all cameras together and not by others that may be swapped themselves.
    Needs at most MAX_MIRROR_CAMERAS cameras (2^(C-1) choices); with more, none is swapped."""
    C, T, N = sync.shape[:3]
    J = skeleton.joints
    flips = np.zeros((C, T, N // J), dtype=bool)
    if C > MAX_MIRROR_CAMERAS:
        return flips
    mirror = np.asarray(skeleton.mirror)
    cap = 3 * threshold_px
    choices = np.array([[(k >> (c - 1)) & 1 if c else 0 for c in range(C)]
                        for k in range(2 ** (C - 1))], dtype=bool)
    costs = np.empty((len(choices), T, N // J))
    for k, choice in enumerate(choices):
        read = np.where(choice[:, None, None, None], sync[:, :, mirror], sync)
        X = triangulate_dlt(posed, read)
        e = np.stack([np.linalg.norm(cam.project(X.reshape(-1, 3)).reshape(T, N, 2) - read[c],
                                     axis=-1) for c, cam in enumerate(posed)])
        e = np.minimum(np.where(np.isfinite(e), e, cap), cap) ** 2  # missing: capped, as all
        costs[k] = e.sum(0).reshape(T, N // J, J).sum(-1)
    best = choices[np.argmin(costs, axis=0)]  # (T, people, C)
    for c in range(C):
        own = shifted(best[:, :, c].astype(float), int(shifts[c]), segments)
        flips[c] = np.nan_to_num(own) > 0.5
    return flips


def _flip(pixels: np.ndarray, confidence: np.ndarray, flips: np.ndarray, skeleton: Skeleton):
    """The keypoints with left and right swapped in the views ``flips`` (C, T, people)."""
    pixels, confidence = pixels.copy(), confidence.copy()
    J, mirror = skeleton.joints, np.asarray(skeleton.mirror)
    for c, t, p in zip(*np.nonzero(flips)):
        block = np.arange(p * J, (p + 1) * J)
        pixels[c, t, block] = pixels[c, t, mirror[block]]
        confidence[c, t, block] = confidence[c, t, mirror[block]]
    return pixels, confidence


# ----------------------------------------------------------------------------------------------
# 4-5. Vertical and scale
# ----------------------------------------------------------------------------------------------

def _plane(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(centroid, unit normal, singular values) of the least-squares plane, refitted once
    without the points beyond 3 robust deviations."""
    for _ in range(2):
        centre = points.mean(0)
        _, s, Vt = np.linalg.svd(points - centre, full_matrices=False)
        normal = Vt[2]
        d = (points - centre) @ normal
        mad = 1.4826 * np.median(np.abs(d - np.median(d)))
        keep = np.abs(d - np.median(d)) <= 3 * max(mad, 1e-12)
        if keep.all() or keep.sum() < 10:
            break
        points = points[keep]
    return centre, normal, s


def stances(points: np.ndarray, feet: tuple[int, ...]) -> np.ndarray:
    """(K, 3) the foot joints' positions in the slowest STANCE_SHARE of their frames."""
    out = []
    for n in feet:
        track = points[:, n]
        speed = np.linalg.norm(track[2:] - track[:-2], axis=-1)  # central differences
        ok = np.isfinite(speed)
        if np.count_nonzero(ok) < 6:
            continue
        slow = ok & (speed <= np.quantile(speed[ok], STANCE_SHARE))
        out.append(track[1:-1][slow])
    return np.concatenate(out) if out else np.zeros((0, 3))


def floor_frame(points: np.ndarray, skeleton: Skeleton) -> tuple[np.ndarray, np.ndarray, str]:
    """(world_from_ref R, t, how the vertical was found) of the floor frame (module notes),
    from points (T, N, 3) in camera 0's frame."""
    feet = stances(points, skeleton.feet)
    heads = points[:, list(skeleton.heads)].reshape(-1, 3)
    heads = heads[np.all(np.isfinite(heads), -1)]
    all_feet = points[:, list(skeleton.feet)].reshape(-1, 3)
    all_feet = all_feet[np.all(np.isfinite(all_feet), -1)]
    if len(heads) == 0 or len(all_feet) == 0:
        raise ValueError("no feet or heads were reconstructed: the vertical cannot be found")
    centre, up, s = (_plane(feet) if len(feet) >= 10 else (None, None, np.zeros(3)))
    if up is not None and s[1] > FLAT_SPREAD * s[0]:
        how = "floor"
    else:  # the feet stayed at a few spots: the body's own axis is the vertical
        up = heads.mean(0) - all_feet.mean(0)
        up /= np.linalg.norm(up)
        centre, how = all_feet.mean(0), "body axis"
    if np.dot(heads.mean(0) - all_feet.mean(0), up) < 0:
        up = -up
    view = np.array([0.0, 0.0, 1.0])  # camera 0's optical axis in its own frame
    x = view - np.dot(view, up) * up
    if np.linalg.norm(x) < 1e-6:  # camera 0 looks straight down: its image x instead
        x = np.array([1.0, 0.0, 0.0]) - up[0] * up
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(up, x), up])  # rows: the world axes in camera 0's frame
    finite = points[np.all(np.isfinite(points), -1)]
    middle = finite.mean(0)
    origin = middle - np.dot(middle - centre, up) * up
    return R, -R @ origin, how


def chain_length(points: np.ndarray, skeleton: Skeleton) -> float:
    """The height chain's weighted length, each segment's median over the frames (points'
    units); ValueError if a segment was never reconstructed."""
    total = 0.0
    for a, b, weight in skeleton.chain:
        d = np.linalg.norm(points[:, a] - points[:, b], axis=-1)
        d = d[np.isfinite(d)]
        if len(d) == 0:
            raise ValueError(f"scale: the segment between tracks {a} and {b} of the height chain "
                             f"was never reconstructed; give a baseline instead")
        total += weight * float(np.median(d))
    return total


def _fit_labels(posed, pixels, confidence, shifts, segments, skeleton, threshold_px):
    """(the bundle adjustment at whole-frame shifts, the keypoints as read, their confidence,
    at camera 0's frames, which views were read with left and right swapped): refitted after
    each round of swaps (mirror_labels) for as long as the fit improves, the cost of every
    round at the first round's robust scale."""
    C, T, N = pixels.shape[:3]
    mirrored = bool(skeleton and skeleton.mirror)
    swapped = np.zeros((C, T, N // skeleton.joints), dtype=bool) if skeleton else None
    labelled = pixels, confidence
    best, scale_px = None, None
    for attempt in range(1 + MIRROR_ROUNDS * mirrored):
        sync = _synchronised(pixels, shifts, segments)
        weights = np.where(np.isfinite(pixels[..., 0]), confidence, 0.0)
        fitted = bundle_adjust(posed, pixels, weights, _robust_start(posed, sync, threshold_px),
                               shifts.astype(float), False, segments, scale_px)
        scale_px = scale_px or fitted.robust_px
        if best is not None and not fitted.cost < best[0].cost:
            break  # the swaps did not fit better: the last state stands
        best = fitted, pixels, confidence, sync, swapped
        if attempt == MIRROR_ROUNDS or not mirrored:
            break
        flips = mirror_labels(fitted.cameras, _synchronised(labelled[0], shifts, segments),
                              shifts, segments, skeleton, threshold_px)
        if np.array_equal(flips, swapped):
            break
        swapped = flips
        pixels, confidence = _flip(*labelled, flips, skeleton)
    return best


def _fit_clocks(fitted: Adjusted, pixels, confidence, shifts, segments, threshold_px
                ) -> Adjusted | None:
    """The bundle adjustment with each clock to a fraction of a frame, or None if it does not
    fit the keypoints better than the whole-frame shifts (a short or slow motion says little
    about time). Each clock is scanned against the tracks the others triangulate, then all are
    adjusted together; again from the adjusted cameras while a clock is held at its bound (a
    camera posed with a whole frame wrong biases its first scan towards that frame). Fits are
    judged by their median residual: the spline leaves out observations at a track's ends, so
    their mean costs run over different sets."""
    C = len(pixels)
    weights = np.where(np.isfinite(pixels[..., 0]), confidence, 0.0)
    current, cameras, best = shifts.astype(float), fitted.cameras, None
    for _ in range(CLOCK_ROUNDS):
        scanned = current.copy()
        synced = _synchronised(pixels, np.rint(current).astype(int), segments)
        for c in range(1, C):
            others = [k for k in range(C) if k != c]
            alone = (triangulate_robust([cameras[k] for k in others], synced[others],
                                        threshold_px=3 * threshold_px, refine=False)[0]
                     if len(others) >= 2 else fitted.points)
            scanned[c] = scan_offset(cameras[c], pixels[c], weights[c], alone, current[c],
                                     (best or fitted).robust_px / 3, segments)
        clocked = bundle_adjust(cameras, pixels, weights, fitted.points, scanned, True,
                                segments, fitted.robust_px)
        if not clocked.robust_px < (best or fitted).robust_px:
            break
        best, current, cameras = clocked, clocked.offsets, clocked.cameras
        if np.abs(clocked.offsets - scanned).max() <= MAX_OFFSET_STEP - 0.05:
            break  # no clock held at its bound
    return best


# ----------------------------------------------------------------------------------------------
# The method
# ----------------------------------------------------------------------------------------------

def calibrate_from_body(cameras: list[Camera], pixels: np.ndarray, confidence: np.ndarray,
                        skeleton: Skeleton, scale: Scale, max_offset_frames: int = 0,
                        threshold_px: float = 6.0, segments: np.ndarray | None = None
                        ) -> BodyCalibration:
    """The studio from body keypoints (module notes).

    cameras: the known intrinsics (their poses are ignored); pixels (C, T, N, 2), NaN where
    undetected, and confidence (C, T, N), 0 where undetected: N tracks (every person's joints
    side by side), T frames of each camera's own clock. max_offset_frames: how far the clocks
    may disagree, in whole frames (0: synchronised cameras, offsets not estimated). segments
    (T,): a label per frame; frames of different labels (recordings) are not neighbours.
    threshold_px: the RANSAC inlier bound.
    """
    pixels = np.asarray(pixels, dtype=np.float64)
    confidence = np.asarray(confidence, dtype=np.float64)
    C, T, N = pixels.shape[:3]
    names = [c.name for c in cameras]
    if pixels.shape != (len(cameras), T, N, 2) or confidence.shape != (C, T, N):
        raise ValueError(f"keypoints: expected pixels (C, T, N, 2) and confidence (C, T, N) for "
                         f"{len(cameras)} cameras, got {pixels.shape} and {confidence.shape}")
    if C < 2:
        raise ValueError("calibration from the body needs at least two cameras")
    if scale.cameras is not None and not set(scale.cameras) <= set(names):
        raise ValueError(f"scale: cameras {list(scale.cameras)} are not all among {names}")
    segments = np.zeros(T, dtype=int) if segments is None else np.asarray(segments)
    pixels = np.where((confidence > 0)[..., None], pixels, np.nan)
    x = _normalized(cameras, pixels)
    focal = float(np.mean([[c.fx, c.fy] for c in cameras]))
    threshold = threshold_px / focal
    pairs = {}
    for a in range(C):
        for b in range(a + 1, C):
            found = pair_geometry(x, a, b, max_offset_frames, threshold, segments)
            if found is not None:
                pairs[(a, b)] = found
    order, parent = spanning_tree(pairs, C, names)
    posed, shifts = initial_rig(cameras, pixels, x, pairs, order, parent, threshold, segments)
    fitted, pixels, confidence, sync, swapped = _fit_labels(posed, pixels, confidence, shifts,
                                                            segments, skeleton, threshold_px)
    posed, points, rms = fitted.cameras, fitted.points, fitted.rms_px
    offsets = shifts.astype(float)
    if max_offset_frames > 0:
        clocked = _fit_clocks(fitted, pixels, confidence, shifts, segments, threshold_px)
        if clocked is not None:
            posed, offsets, rms = clocked.cameras, clocked.offsets, clocked.rms_px
            points = on_frames(clocked.points, segments)
    R, t, how = floor_frame(points, skeleton)
    if scale.baseline_mm is not None:
        a, b = (names.index(n) for n in scale.cameras)
        s = scale.baseline_mm / np.linalg.norm(posed[a].center - posed[b].center)
    else:
        s = scale.height_mm / (skeleton.stature_per_chain * chain_length(points, skeleton))
    world = []
    for cam in posed:  # cam_from_world = cam_from_ref o ref_from_world, ref scaled by s
        Rc = cam.R @ R.T
        world.append(_posed(cam, Rc, s * cam.tvec - Rc @ (s * t)))
    world_points = s * (points @ R.T + t)
    return BodyCalibration(
        world, offsets, world_points, rms, how,
        [{"cameras": [names[a], names[b]], "shift": p["shift"], "inliers": p["inliers"]}
         for (a, b), p in sorted(pairs.items())],
        [names[c] for c in order], int(swapped.sum()) if swapped is not None else 0)
