"""3D joints from 2D keypoints through the ESTIMATED cameras of a calibration method.

The keypoints were seen through the true cameras; triangulating them through an estimate turns
every error of that estimate (intrinsics, distortion, relative pose) into joint error, which is
what ``pose-eval`` measures. Triangulation is the shared module's (stereo_bench.multiview.triangulate):
the weighted linear DLT followed by the per-point maximum-likelihood refinement of the
reprojection error, with each view weighted by its keypoint's confidence (a view's residual is
scaled by its weight, so an occluded joint with confidence 0.3 and 3x the noise counts as its
noise says). ``robust`` uses the greedy leave-one-view-out rejection of outlier views instead;
it needs three or more views of a joint to drop one, so on a stereo pair it cannot reject
anything.
"""

from __future__ import annotations

import numpy as np

from stereo_bench.core.camera import Camera
from stereo_bench.multiview.triangulate import refine_points, triangulate_dlt, triangulate_robust

from .observe import Keypoints


def triangulate_joints(cameras: list[Camera], keypoints: Keypoints, robust: bool = False,
                       threshold_px: float = 5.0) -> tuple[np.ndarray, int]:
    """Joints (T, 24, 3) mm in the cameras' world, NaN where fewer than two views are left, and
    the number of detections dropped because the estimated camera cannot unproject them.

    threshold_px: the reprojection error above which ``robust`` drops a view.
    """
    pixels = keypoints.pixels.copy()
    weights = keypoints.confidence.copy()
    dropped = 0
    for c, cam in enumerate(cameras):
        bad = (weights[c] > 0) & ~cam.invertible(np.nan_to_num(pixels[c]))
        pixels[c][bad], weights[c][bad] = np.nan, 0.0
        dropped += int(bad.sum())
    if robust:
        return triangulate_robust(cameras, pixels, weights, threshold_px=threshold_px)[0], dropped
    start = triangulate_dlt(cameras, pixels, weights)
    return refine_points(cameras, pixels, start, weights), dropped
