"""Detection over a dataset or a capture: ``CameraDetections`` per camera (points, found
frames, the reason of every frame not found), saved and reloaded as plain arrays, and the
detections' error against the truth.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from ..core.files import read_arrays, write_npz
from .boards import Detection, detect, failed_detection, resolve_method


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


class DatasetDetections:
    """Detections of a dataset's images, taken one image at a time: from its files
    (``detect_dataset``) or from the renderer as each image is made (``write_dataset``'s
    ``detections``: the same 8-bit pixels the lossless PNG holds, without reading it back).
    ``seconds``: the time spent detecting (summed over processes when merged)."""

    def __init__(self, pattern, method: str | None = None):
        self.pattern = pattern
        self.method = resolve_method(pattern, method)
        self._frames: dict[tuple[int, int], Detection] = {}
        self.seconds = 0.0

    def add(self, camera: int, frame: int, image) -> None:
        """Detect in ``image`` (8-bit), or record ``image``'s loading error (an OSError or
        ValueError instance) as the frame's reason."""
        start = time.perf_counter()
        try:
            if isinstance(image, Exception):
                raise image
            previous = self._frames.get((camera, frame - 1))
            det = detect(image, self.pattern, self.method,
                         in_view=previous is None or previous.found)
        except (OSError, ValueError) as e:  # FileNotFoundError is an OSError
            det = failed_detection(self.pattern, str(e))
        self._frames[camera, frame] = det
        self.seconds += time.perf_counter() - start

    def merge(self, other: "DatasetDetections") -> None:
        """Take ``other``'s images (those it was given in another process) and its time."""
        if other.method != self.method:
            raise ValueError(f"detections by {other.method!r} merged into {self.method!r}")
        self._frames.update(other._frames)
        self.seconds += other.seconds

    def result(self, cameras: list[str], frames: int) -> list[CameraDetections]:
        """One ``CameraDetections`` per camera; ValueError if an image was not given."""
        missing = [(c, f) for c in range(len(cameras)) for f in range(frames)
                   if (c, f) not in self._frames]
        if missing:
            c, f = missing[0]
            raise ValueError(f"no detection of camera {cameras[c]!r} frame {f} "
                             f"({len(missing)} images missing)")
        out = []
        for c, name in enumerate(cameras):
            dets = [self._frames[c, f] for f in range(frames)]
            out.append(CameraDetections(
                name, self.pattern.kind, self.method, np.stack([d.points for d in dets]),
                np.array([d.found for d in dets], dtype=bool), self.pattern.ids(),
                {f: d.error for f, d in enumerate(dets) if not d.found}))
        return out


def detect_dataset(dataset, method: str | None = None,
                   progress: Callable[[int, int], None] | None = None) -> list[CameraDetections]:
    """Detect the board in every image of a ``Dataset``; one ``CameraDetections`` per camera.

    A frame that fails (board not found, image missing or unreadable) is recorded with its reason
    and the sweep goes on.  ``progress(done, total)`` is called after each image.
    """
    frames = dataset.frames
    found = DatasetDetections(dataset.pattern, method)
    total, done = len(dataset.cameras) * frames, 0
    for c in range(len(dataset.cameras)):
        for f in range(frames):
            try:
                image = dataset.image(c, f)
            except (OSError, ValueError) as e:  # FileNotFoundError is an OSError
                image = e
            found.add(c, f, image)
            done += 1
            if progress:
                progress(done, total)
    return found.result([c.name for c in dataset.cameras], frames)


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
