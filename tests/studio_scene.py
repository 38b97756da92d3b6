"""The synthetic studio the rig-reference tests share (test_colmap_ref, test_multiview_ref).

5 cameras (640 x 480, fx ~ 500, distortion; cameras 1 and 3 with k3) on a 3.5 m ring looking at
the centre, and a 9 x 6 board at 60 mm that moves through the volume facing a random horizontal
direction; a camera sees a frame when it faces the board's front (within 70 deg) and every point
is inside its image. Each camera sees about a third of the frames, most frames two or three.
"""

import cv2
import numpy as np

from stereo_bench.camera import Camera, look_at_rotation, matrix_to_rodrigues, rodrigues_to_matrix
from stereo_bench.stereo import cam_from_cam0

FRAMES = 60


def ring(C=5, radius=3500.0, seed=0):
    rng = np.random.default_rng(seed)
    cams = []
    for k in range(C):
        a = 2 * np.pi * k / C
        pos = np.array([radius * np.cos(a), radius * np.sin(a), 1800.0 + 200 * (k % 2)])
        R = look_at_rotation(pos, np.array([0, 0, 1000.0]), np.array([0, 0, 1.0]))
        dist = [rng.uniform(-0.15, 0.05), rng.uniform(-0.02, 0.05), rng.normal(0, 1e-3),
                rng.normal(0, 1e-3), 0.01 * (k % 2), 0, 0, 0]
        cams.append(Camera(f"cam{k}", 640, 480, 500 * rng.uniform(0.95, 1.05),
                           500 * rng.uniform(0.95, 1.05), 320 + rng.normal(0, 5),
                           240 + rng.normal(0, 5), 0.0, dist, matrix_to_rodrigues(R), -R @ pos))
    return cams


def board():
    gx, gy = np.meshgrid(np.arange(9) * 60.0, np.arange(6) * 60.0)
    return np.stack([gx.ravel(), gy.ravel(), np.zeros(54)], -1)


def observe(cams, obj, sigma, seed=0, frames=FRAMES):
    """world_from_board (F,3,3), (F,3) and image points (C,F,N,2), NaN where not seen."""
    rng = np.random.default_rng(seed)
    R_wb = []
    for yaw in rng.uniform(0, 2 * np.pi, frames):
        facing = look_at_rotation(np.zeros(3), [np.cos(yaw), np.sin(yaw), 0], [0, 0, 1.0]).T
        R_wb.append(facing @ rodrigues_to_matrix(rng.normal(0, 0.25, 3)))
    R_wb = np.stack(R_wb)
    centre = np.stack([rng.uniform(-600, 600, frames), rng.uniform(-600, 600, frames),
                       rng.uniform(700, 1500, frames)], -1)
    t_wb = centre - R_wb @ obj.mean(0)
    Xw = np.einsum("fij,nj->fni", R_wb, obj) + t_wb[:, None]
    img = np.full((len(cams), frames, len(obj), 2), np.nan)
    for c, cam in enumerate(cams):
        uv = cam.project(Xw)
        towards = cam.center - centre
        towards /= np.linalg.norm(towards, axis=-1, keepdims=True)
        front = np.einsum("fi,fi->f", R_wb[:, :, 2], towards) < -np.cos(np.radians(70))
        inside = np.all((uv >= 5) & (uv <= [cam.width - 6, cam.height - 6]), axis=(-1, -2))
        ok = front & inside
        img[c, ok] = uv[ok] + rng.normal(0, sigma, uv[ok].shape)
    return R_wb, t_wb, img


def true_start(cams, R_wb, t_wb):
    """The true cam_from_cam0 (C,3,3), (C,3) and cam0_from_board rvecs, tvecs (F,3)."""
    R, t = cam_from_cam0(cams)
    R0 = cams[0].R
    return R, t, matrix_to_rodrigues(R0 @ R_wb), t_wb @ R0.T + cams[0].tvec


def perturbed(R, t, rv, tv, seed=5):
    """A start a few degrees and tens of millimetres off; camera 0 stays the identity."""
    rng = np.random.default_rng(seed)
    turn = rodrigues_to_matrix(rng.normal(0, np.radians(2), (len(R), 3)))
    turn[0] = np.eye(3)
    dt = rng.normal(0, 20, t.shape)
    dt[0] = 0
    rv = matrix_to_rodrigues(rodrigues_to_matrix(rng.normal(0, np.radians(2), rv.shape))
                             @ rodrigues_to_matrix(rv))
    return turn @ R, t + dt, rv, tv + rng.normal(0, 20, tv.shape)


def intrinsics_only(cams):
    return [c.with_params(rvec=np.zeros(3), tvec=np.zeros(3)) for c in cams]


def pnp_board_poses(cams, obj, img):
    """Each camera's own cam_from_board by cv2.solvePnP (IPPE), as a calibration would give it:
    rvecs, tvecs (C,F,3), NaN where the camera did not see the frame, and found (C,F) bool."""
    found = np.all(np.isfinite(img), axis=(-1, -2))
    rv = np.full(img.shape[:2] + (3,), np.nan)
    tv = np.full(img.shape[:2] + (3,), np.nan)
    for c, cam in enumerate(cams):
        for f in np.flatnonzero(found[c]):
            ok, r, t = cv2.solvePnP(obj, img[c, f], cam.K, cam.dist, flags=cv2.SOLVEPNP_IPPE)
            assert ok
            rv[c, f], tv[c, f] = r.ravel(), t.ravel()
    return rv, tv, found
