"""The synthetic studio the rig-reference tests share (test_colmap_ref, test_multiview_ref), built
by the package: ``config.parse_rig`` of a studio, ``rig.Rig.from_config``, its ground truth.

5 cameras (640 x 480, fx ~ 500, distortion; cam2 and cam4 with k3) on a 3.5 m ring at heights
1.8 / 2.0 m looking at the volume's centre, and a checkerboard of 9 x 6 inner corners at 60 mm
carried through the volume for 60 frames of a calibration session (trajectory.kind: session),
turning so that its front faces each camera in turn. A camera sees a frame when every point is
visible in the ground truth (the board's front towards it, inside its image): each camera sees
about half the frames, most frames two or three cameras.
"""

import numpy as np

from stereo_bench.core.poses import matrix_to_rodrigues, rodrigues_to_matrix
from stereo_bench.config.schema import parse_rig
from stereo_bench.scene.rig import Rig
from stereo_bench.core.poses import cam_from_cam0
from stereo_bench.calibrate.pose import planar_pose

FRAMES = 60
LENSES = [
    {"fx": 515.7, "fy": 520.6, "cx": 326.5, "cy": 244.7, "dist": [-0.0226, -0.0011, 6e-4, 1e-4]},
    {"fx": 517.9, "fy": 476.7, "cx": 313.8, "cy": 236.3,
     "dist": [-0.0413, 0.0455, -6e-4, 0.0, 0.01]},
    {"fx": 476.4, "fy": 481.2, "cx": 316.7, "cy": 241.8, "dist": [0.0226, 0.0179, 4e-4, 1e-3]},
    {"fx": 509.3, "fy": 507.5, "cx": 315.0, "cy": 239.0,
     "dist": [-0.0269, 0.0069, -7e-4, -9e-4, 0.01]},
    {"fx": 499.3, "fy": 519.5, "cx": 323.9, "cy": 247.5, "dist": [-0.123, 0.0305, 2e-4, 4e-4]},
]


def studio(lenses=tuple(LENSES)) -> Rig:
    """The studio: rig.cameras the true cameras (cam1 ... cam5), rig.pattern the board;
    ``lenses`` (rig-file lens entries without the image size) in turn."""
    return Rig.from_config(parse_rig({
        "name": "reference_studio",
        "studio": {"layout": "ring", "count": 5, "radius_mm": 3500.0,
                   "height_mm": [1800.0, 2000.0],
                   "lenses": [{"width": 640, "height": 480, **lens} for lens in lenses]},
        "pattern": {"kind": "checkerboard", "squares_x": 10, "squares_y": 7, "square_mm": 60.0},
        "trajectory": {"kind": "session", "frames": FRAMES}}))


def observe(rig: Rig, sigma: float = 0.0, seed: int = 0) -> np.ndarray:
    """Image points (C, F, N, 2) of the views in which every point is visible, plus Gaussian
    noise of ``sigma`` px; NaN elsewhere."""
    gt = rig.ground_truth()
    img = np.where(gt.visible.all(-1)[..., None, None], gt.points, np.nan)
    return img + np.random.default_rng(seed).normal(0, sigma, img.shape)


def true_start(rig: Rig):
    """The true cam_from_cam0 (C,3,3), (C,3) and cam0_from_board rvecs, tvecs (F,3)."""
    R, t = cam_from_cam0(rig.cameras)
    R0b, t0b = rig.cam_from_board(rig.cameras[0])
    return R, t, matrix_to_rodrigues(R0b), t0b


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


def board_poses(cams, obj, img):
    """Each camera's own cam_from_board from its view (pose.planar_pose), as a calibration
    would start it: rvecs, tvecs (C,F,3), NaN where the camera did not see the frame, and
    found (C,F) bool."""
    found = np.all(np.isfinite(img), axis=(-1, -2))
    rv, tv = np.full(img.shape[:2] + (3,), np.nan), np.full(img.shape[:2] + (3,), np.nan)
    for c, f in zip(*np.nonzero(found)):
        rv[c, f], tv[c, f] = planar_pose(cams[c], obj, img[c, f])
    return rv, tv, found


def exact_views(rig: Rig):
    """The noise-free problem: (true cameras, board points, image points, seen (C,F), the true
    start of ``true_start``)."""
    img = observe(rig)
    seen = np.all(np.isfinite(img), axis=(-1, -2))
    return rig.cameras, rig.pattern.object_points(), img, seen, true_start(rig)


def noisy_views(rig: Rig, sigma: float = 0.3, seed: int = 1):
    """``sigma`` px of noise and each camera's own cam_from_board (planar_pose), as a
    calibration starts: (true cameras, board points, image points, rvecs, tvecs, found)."""
    cams, obj = rig.cameras, rig.pattern.object_points()
    img = observe(rig, sigma, seed)
    rv, tv, found = board_poses(cams, obj, img)
    return cams, obj, img, found, rv, tv
