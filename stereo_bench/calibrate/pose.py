"""The pose of a planar board seen by a calibrated camera (intrinsics fixed)."""

from __future__ import annotations


import numpy as np

from .homography import fit_homography
from .refine import CameraModel, refine
from .homography import extrinsics_from_homography
from ..core.camera import Camera
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
