"""Detection over a dataset or a capture: ``CameraDetections`` per camera (points, found
frames, the reason of every frame not found), saved and reloaded as plain arrays, and the
detections' error against the truth.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from ..core.files import read_arrays, write_npz
from .boards import detect, failed_detection, resolve_method


# ----------------------------------------------------------------------------- datasets
@dataclass(frozen=True, eq=False)
class CameraDetections:
    """One camera's detections over a dataset: ``points`` (F, N, 2) px (NaN where not seen),
    ``found`` (F,) bool, ``ids`` (N,), and ``errors`` {frame: reason} for every frame not found."""

    camera: str
    pattern: str
    method: str
    points: np.ndarray
    found: np.ndarray
    ids: np.ndarray
    errors: dict[int, str] = field(default_factory=dict)

    def save(self, path: str | Path) -> Path:
        """Write a .npz (plain arrays, no pickles) and return its path."""
        path = Path(path)
        frames = sorted(self.errors)
        path = path if path.suffix == ".npz" else path.with_name(path.name + ".npz")
        write_npz(path, camera=self.camera, pattern=self.pattern, method=self.method,
                  points=self.points, found=self.found, ids=self.ids,
                  error_frames=np.array(frames, dtype=np.int64),
                  error_messages=np.array([self.errors[f] for f in frames], dtype=str),
                  opencv_version=cv2.__version__)
        return path

    @classmethod
    def load(cls, path: str | Path) -> "CameraDetections":
        try:
            z = read_arrays(path, "a detections file")
            return cls(str(z["camera"]), str(z["pattern"]), str(z["method"]), z["points"],
                       z["found"], z["ids"],
                       {int(f): str(m) for f, m in zip(z["error_frames"], z["error_messages"])})
        except (FileNotFoundError, TypeError, KeyError, ValueError) as e:
            raise ValueError(f"{path}: not a detections file written by CameraDetections.save "
                             f"({e})") from None


def detect_dataset(dataset, method: str | None = None,
                   progress: Callable[[int, int], None] | None = None) -> list[CameraDetections]:
    """Detect the board in every image of a ``Dataset``; one ``CameraDetections`` per camera.

    A frame that fails (board not found, image missing or unreadable) is recorded with its reason
    and the sweep goes on.  ``progress(done, total)`` is called after each image.
    """
    pattern = dataset.pattern
    method = resolve_method(pattern, method)
    n, frames = len(pattern.ids()), dataset.frames
    total, done = len(dataset.cameras) * frames, 0
    result = []
    for c, camera in enumerate(dataset.cameras):
        points = np.full((frames, n, 2), np.nan)
        found = np.zeros(frames, dtype=bool)
        errors = {}
        for f in range(frames):
            try:
                det = detect(dataset.image(c, f), pattern, method)
            except (OSError, ValueError) as e:  # FileNotFoundError is an OSError
                det = failed_detection(pattern, str(e))
            points[f], found[f] = det.points, det.found
            if not det.found:
                errors[f] = det.error
            done += 1
            if progress:
                progress(done, total)
        result.append(CameraDetections(camera.name, pattern.kind, method, points, found,
                                       pattern.ids(), errors))
    return result


def detection_errors(det: CameraDetections, gt_points: np.ndarray,
                     gt_visible: np.ndarray) -> dict:
    """Accuracy of one camera's detections against the truth (``gt_points`` (F, N, 2),
    ``gt_visible`` (F, N)).

    A found frame is *flipped* when its points, reversed, fit the truth better than as returned
    (a 180-degree orientation error).  Flipped frames are counted and listed, not repaired, and are
    left out of the distance statistics (their errors are board-sized and would swamp them).
    Distances are over the visible, detected points of the other found frames; ``mean_dx_px`` and
    ``mean_dy_px`` are the signed mean of detected - true.
    """
    gt_points, gt_visible = np.asarray(gt_points), np.asarray(gt_visible, dtype=bool)
    if gt_points.shape != det.points.shape or gt_visible.shape != det.points.shape[:2]:
        raise ValueError(f"detection_errors: detections {det.points.shape} do not match ground "
                         f"truth points {gt_points.shape} / visible {gt_visible.shape}")
    seen = np.isfinite(det.points).all(-1) & det.found[:, None]
    flipped = []
    for f in np.flatnonzero(det.found):
        as_is = _mean_distance(det.points[f], gt_points[f], seen[f] & gt_visible[f])
        reversed_ = _mean_distance(det.points[f, ::-1], gt_points[f],
                                   seen[f, ::-1] & gt_visible[f])
        if reversed_ < as_is:
            flipped.append(int(f))
    use = seen & gt_visible
    use[flipped] = False
    diff = det.points[use] - gt_points[use]
    dist = np.linalg.norm(diff, axis=-1)
    if len(dist):
        stats = dict(mean_px=dist.mean(), rms_px=np.sqrt((dist**2).mean()), max_px=dist.max(),
                     mean_dx_px=diff[:, 0].mean(), mean_dy_px=diff[:, 1].mean())
    else:
        stats = dict.fromkeys(("mean_px", "rms_px", "max_px", "mean_dx_px", "mean_dy_px"), math.nan)
    return {
        "frames": len(det.found),
        "found": int(det.found.sum()),
        "detection_rate": float(det.found.mean()),
        "point_detection_rate": float((seen & gt_visible).sum() / max(gt_visible.sum(), 1)),
        "points": int(use.sum()),
        **{k: float(v) for k, v in stats.items()},
        "flips": len(flipped),
        "flipped_frames": flipped,
    }


def _mean_distance(points: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> float:
    if not mask.any():
        return math.inf
    return float(np.linalg.norm(points[mask] - truth[mask], axis=-1).mean())
