"""The pose of a planar board seen by a calibrated camera (intrinsics fixed)."""

from __future__ import annotations


import numpy as np

from .homography import fit_homography
from .refine import CameraModel, refine
from .homography import extrinsics_from_homography
from ..core.camera import Camera
from ..core.poses import matrix_to_rodrigues, rodrigues_to_matrix, view_toward
from ..core.distortion import DistortionNotInvertibleError


def planar_pose(camera: Camera, object_points: np.ndarray, image_points: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """cam_from_board (rvec, tvec) of a planar board (z = 0) seen by a calibrated camera: the
    homography from the board to the undistorted normalized image, decomposed as Zhang's
    section 3.1 does with K = I, then refined to the pixel reprojection error's minimum with
    the intrinsics fixed (refine.py; the homography's algebraic fit in normalized coordinates
    left the rig's start at 13 px RMS on a noisy studio). Starts the rig's adjustment for the
    frames a camera's own calibration did not use, and every held-out view of
    diagnostics.heldout.

    Where the estimate's distortion has no unique ray at some of the points (an overfitted
    model folds inside the image, TRAPS.md), the homography starts from the pixels with the
    distortion left out: the refinement only projects, so the pose is still the one that best
    fits the view through the estimate as it is, and its residuals show what the fold costs."""
    rvec, tvec = _wide_start(camera, object_points, image_points) if camera.model != "opencv" \
        else (None, None)
    if rvec is None:
        try:
            xy = camera.unproject(image_points)
        except DistortionNotInvertibleError:
            xy = camera.pixels_to_distorted_normalized(image_points)
        H = fit_homography(object_points[:, :2], xy)
        rvec, tvec = extrinsics_from_homography(np.eye(3), H)
    model = CameraModel(camera.model)
    params = model.params_of(camera)
    res = refine(model, params, np.zeros(len(params), bool), [object_points], [image_points],
                 rvec[None], tvec[None], max_iter=20)
    return res.rvecs[0], res.tvecs[0]


def _wide_start(camera: Camera, object_points, image_points):
    """A wide lens's start (rvec, tvec), or (None, None) with fewer than 4 points that have a
    ray: the homography in the view turned toward the points' mean ray (poses.view_toward), so
    that a board seen past 90 degrees (behind the camera's plane) has normalized coordinates,
    taken back to the camera's frame."""
    rays, ok = camera.rays(image_points)
    if ok.sum() < 4:
        return None, None
    Q = view_toward(rays[ok].mean(0))
    v = rays[ok] @ Q.T
    ahead = v[:, 2] > 0.1  # a board wider than ~170 degrees leaves its edge out of the start
    if ahead.sum() < 4:
        return None, None
    H = fit_homography(object_points[ok][ahead, :2], v[ahead, :2] / v[ahead, 2:])
    rvec, tvec = extrinsics_from_homography(np.eye(3), H)
    return matrix_to_rodrigues(Q.T @ rodrigues_to_matrix(rvec)), Q.T @ tvec
