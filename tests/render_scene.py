"""The cameras, board, poses and detector the renderer's tests share (test_render,
test_imaging); the ``rays`` fixture that caches each camera's PixelRays is in conftest.py."""

import cv2
import numpy as np

from stereo_bench.core.camera import Camera
from stereo_bench.core.poses import rodrigues_to_matrix
from stereo_bench.core.patterns import Checkerboard

WIDE = Camera("wide", 640, 480, 600, 450, 320, 240, 0,
              np.array([0.5, 0.1, 0.03, 0, 0, 0, 0, 0]))
# The paper's rectilinear camera (4096 x 3072, f = 3000, c = (2048, 1536)) scaled by 1/4: the
# same field of view and distortion; its full-size rays take ~15 s to precompute.
RECT_QUARTER = Camera("rect_quarter", 1024, 768, 750, 750, 511.625, 383.625, 0,
                      np.array([0.05, 0.02, 0.001, 0, 0, 0, 0, 0]))
PINHOLE = Camera("pinhole", 640, 480, 600, 600, 320, 240)
BOARD = Checkerboard()  # 9 x 12 squares of 15 mm, 8 x 11 inner corners
OBJ = BOARD.object_points()
CENTRE = 0.5 * (OBJ.min(0) + OBJ.max(0))
SUBPIX = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 200, 1e-6)


def tilted_poses(cam, n, seed):
    """cam_from_board poses: board tilted 15-45 degrees, rolled, filling 50-75 % of the height."""
    rng = np.random.default_rng(seed)
    z0 = BOARD.size_mm[1] * cam.fy / (0.75 * cam.height)
    poses = []
    for _ in range(n):
        axis = rng.uniform(0, 2 * np.pi)
        tilt = np.radians(rng.uniform(15, 45)) * np.array([np.cos(axis), np.sin(axis), 0])
        R = rodrigues_to_matrix(tilt) @ rodrigues_to_matrix([0, 0, rng.uniform(-0.4, 0.4)])
        centre = np.array([rng.uniform(-0.1, 0.1) * z0, rng.uniform(-0.1, 0.1) * z0,
                           rng.uniform(1.0, 1.5) * z0])
        poses.append((R, centre - R @ CENTRE))
    return poses


def detect(img, truth):
    """findChessboardCorners + cornerSubPix (5 x 5 window), in the order closest to truth
    (the detector may return the 180-degree rotated order)."""
    ok, corners = cv2.findChessboardCorners(img, BOARD.pattern_size)
    assert ok, "checkerboard not detected"
    c = cv2.cornerSubPix(img, corners, (5, 5), (-1, -1), SUBPIX).reshape(-1, 2)
    c = c.astype(np.float64)
    return min((c, c[::-1]), key=lambda k: np.abs(k - truth).mean())
