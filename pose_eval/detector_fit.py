"""A real detector's error as a model: fitted to its keypoints on rendered bodies, replayed on
any scene, so a study without Blender gets the detector's floor.

A 2D detector's keypoint is off the projected true joint for two reasons, and they triangulate
differently:

* **Definition**: its joints are not the body model's (BlazePose's hip landmarks lie outside
  SMPL's hip centres, the midpoint of its shoulders below SMPL's neck). The offset is the same
  from every camera, so it moves the triangulated joint, by the same amount whatever the
  calibration. It is fitted per joint as one 3D offset in the body's own frame
  (:func:`body_frames`: x from the right hip to the left, y up the spine, z forward), the
  offset that minimizes the reprojection error over every view (a robust loss, 5 px).
* **Noise**: what is left scatters from view to view. A detector works on the body's image at
  its size, so its scatter is a fixed length on the body, not a fixed number of pixels: it is
  fitted in mm at the joint (pixels times depth over the focal length), and replayed in pixels
  through each camera at the joint's depth. Per joint and per visibility (seen, or hidden
  behind the body: :func:`pose_eval.observe.scene_occlusion`): the robust standard deviation
  (1.4826 MAD, per coordinate), the share of gross errors (beyond 4 of them) and their median
  size, the share of views the detector missed while the joint was in the image, and its mean
  confidence. Joints it never reports (BlazePose has no spine or collars) stay undetected.

:func:`fit_detector` fits it from a detector's :class:`~pose_eval.observe.Keypoints` on one or
more rendered scenes; :func:`observe_fitted` draws synthetic detections from it;
``DetectorFit.to_dict`` / ``from_dict`` carry it in JSON (the shipped
``pose_eval/data/blazepose_fit.json`` was fitted by ``scripts/fit_detector.py`` on Blender renders
of the Human3.6M-like studio).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

from stereo_bench.core.camera import Camera
from stereo_bench.core.files import read_json

from .body import NUM_JOINTS
from .motion import JOINT, JOINT_NAMES
from .observe import Keypoints, scene_occlusion
from .scene import Scene, in_view

SHIPPED = Path(__file__).parent / "data" / "blazepose_fit.json"
GROSS_SIGMAS = 4.0     # a residual beyond this many robust sigmas is a gross error
ROBUST_SCALE_PX = 5.0  # soft-L1 scale of the offset fit
MIN_VIEWS = 8          # fewer views of a joint (in a visibility class) fit nothing


def body_frames(joints: np.ndarray) -> np.ndarray:
    """(T, 3, 3) world_from_body rotations of the body's own frame, from its joints (T, 24, 3):
    x from the right hip to the left, y up from the pelvis to the neck (made orthogonal to x),
    z = x cross y (forward)."""
    x = joints[:, JOINT["left_hip"]] - joints[:, JOINT["right_hip"]]
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    y = joints[:, JOINT["neck"]] - joints[:, JOINT["pelvis"]]
    y -= np.sum(y * x, axis=1, keepdims=True) * x
    y /= np.linalg.norm(y, axis=1, keepdims=True)
    return np.stack([x, y, np.cross(x, y)], axis=2)


@dataclass(frozen=True, eq=False)
class DetectorFit:
    """Per joint (24, SMPL's order): ``offset_mm`` (3,) in the body frame; and per visibility
    (index 0 seen, 1 hidden) ``sigma_mm`` (per coordinate), ``gross_rate``, ``gross_mm``,
    ``miss_rate``, ``confidence``. NaN rows: a joint the detector does not report."""

    name: str
    offset_mm: np.ndarray    # (24, 3)
    sigma_mm: np.ndarray     # (24, 2)
    gross_rate: np.ndarray   # (24, 2)
    gross_mm: np.ndarray     # (24, 2)
    miss_rate: np.ndarray    # (24, 2)
    confidence: np.ndarray   # (24, 2)
    source: dict = field(default_factory=dict)

    @property
    def reported(self) -> np.ndarray:
        """(24,) bool: the joints the detector reports."""
        return np.isfinite(self.offset_mm).all(axis=1)

    _ARRAYS = ("offset_mm", "sigma_mm", "gross_rate", "gross_mm", "miss_rate", "confidence")

    def to_dict(self) -> dict:
        joints = {}
        for j, name in enumerate(JOINT_NAMES):
            if self.reported[j]:
                joints[name] = {k: np.round(getattr(self, k)[j], 6).tolist()
                                for k in self._ARRAYS}
        return {"name": self.name, "source": self.source, "joints": joints}

    @classmethod
    def from_dict(cls, data: dict, where: str = "detector model") -> DetectorFit:
        try:
            if not isinstance(data, dict) or not isinstance(data.get("joints"), dict):
                raise ValueError("expected a mapping with 'joints': {joint name: figures}")
            arrays = {k: np.full((NUM_JOINTS, 3 if k == "offset_mm" else 2), np.nan)
                      for k in cls._ARRAYS}
            for name, values in data["joints"].items():
                if not isinstance(values, dict):
                    raise ValueError(f"joints.{name}: expected a mapping of its figures")
                if name not in JOINT:
                    raise ValueError(f"joints.{name}: not one of SMPL's joints")
                for k in cls._ARRAYS:
                    v = np.asarray(values[k], np.float64)
                    if v.shape != arrays[k].shape[1:] or not np.all(np.isfinite(v)):
                        raise ValueError(f"joints.{name}.{k}: expected "
                                         f"{arrays[k].shape[1]} finite numbers")
                    arrays[k][JOINT[name]] = v
            for k in ("gross_rate", "miss_rate", "confidence"):
                a = arrays[k][np.isfinite(arrays[k])]
                if ((a < 0) | (a > 1)).any():
                    raise ValueError(f"{k}: expected shares in [0, 1]")
            return cls(str(data.get("name", "detector")), source=dict(data.get("source", {})),
                       **arrays)
        except (KeyError, TypeError, ValueError) as e:
            raise ValueError(f"{where}: {e}") from None


def load_fit(path=None) -> DetectorFit:
    """A fitted detector from its JSON file (default: the shipped BlazePose fit)."""
    path = Path(path) if path is not None else SHIPPED
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no detector model here (expected the JSON file "
                                f"scripts/fit_detector.py writes, or 'blazepose')")
    return DetectorFit.from_dict(read_json(path, "detector model"), str(path))


def _views(cameras: list[Camera], scene: Scene, keypoints: Keypoints, occluded: np.ndarray):
    """Per joint view of a scene: camera index, frame, joint, detected pixel, confidence,
    hidden, in view."""
    C, T, J = keypoints.confidence.shape
    c, t, j = np.meshgrid(np.arange(C), np.arange(T), np.arange(J), indexing="ij")
    seen = np.stack([in_view(cam, scene.joints) for cam in cameras])
    return (c.ravel(), t.ravel(), j.ravel(), keypoints.pixels.reshape(-1, 2),
            keypoints.confidence.ravel(), occluded.ravel(), seen.ravel())


def fit_detector(name: str, cameras: list[Camera], scenes: list[Scene],
                 keypoints: list[Keypoints], source: dict | None = None) -> DetectorFit:
    """Fit the model (module notes) to a detector's ``keypoints`` of each of ``scenes``, all
    seen through the true ``cameras``."""
    if len(scenes) != len(keypoints) or not scenes:
        raise ValueError("fit_detector: expected one set of keypoints per scene")
    rows = {k: [] for k in ("X", "R", "cam", "joint", "px", "conf", "hidden", "seen")}
    for scene, kp in zip(scenes, keypoints):
        c, t, j, px, conf, hidden, seen = _views(cameras, scene, kp,
                                                 scene_occlusion(cameras, scene))
        frames = body_frames(scene.joints)
        rows["X"].append(scene.joints[t, j])
        rows["R"].append(frames[t])
        for k, v in (("cam", c), ("joint", j), ("px", px), ("conf", conf), ("hidden", hidden),
                     ("seen", seen)):
            rows[k].append(v)
    X, R, cam, joint, px, conf, hidden, seen = (np.concatenate(rows[k]) for k in rows)
    hidden = hidden.astype(int)
    arrays = {k: np.full((NUM_JOINTS, 2), np.nan) for k in
              ("sigma_mm", "gross_rate", "gross_mm", "miss_rate", "confidence")}
    offset = np.full((NUM_JOINTS, 3), np.nan)
    detected = seen & (conf > 0) & np.isfinite(px).all(axis=1)
    for jj in range(NUM_JOINTS):
        mine = detected & (joint == jj)
        if np.count_nonzero(mine) < MIN_VIEWS:
            continue
        idx = np.flatnonzero(mine)

        def project(o, idx=idx):
            P = X[idx] + R[idx] @ o
            out = np.empty((len(idx), 2))
            for ci, camera in enumerate(cameras):
                k = cam[idx] == ci
                out[k] = camera.project(P[k])
            return out

        fit = least_squares(lambda o: (project(o) - px[idx]).ravel(), np.zeros(3),
                            loss="soft_l1", f_scale=ROBUST_SCALE_PX, x_scale=10.0)
        offset[jj] = fit.x
        resid = project(fit.x) - px[idx]
        P = X[idx] + R[idx] @ fit.x
        mm = np.empty_like(resid)
        for ci, camera in enumerate(cameras):
            k = cam[idx] == ci
            depth = camera.world_to_cam(P[k])[:, 2]
            mm[k] = resid[k] * (depth / (0.5 * (camera.fx + camera.fy)))[:, None]
        for h in (0, 1):
            in_class = seen & (joint == jj) & (hidden == h)
            k = hidden[idx] == h
            if np.count_nonzero(k) < MIN_VIEWS:
                continue
            r = mm[k]
            sigma = 1.4826 * np.median(np.abs(r - np.median(r, axis=0)))
            norm = np.linalg.norm(r, axis=1)
            gross = norm > GROSS_SIGMAS * sigma
            arrays["sigma_mm"][jj, h] = sigma
            arrays["gross_rate"][jj, h] = gross.mean()
            arrays["gross_mm"][jj, h] = np.median(norm[gross]) if gross.any() else 0.0
            arrays["miss_rate"][jj, h] = 1.0 - np.count_nonzero(k) / np.count_nonzero(in_class)
            arrays["confidence"][jj, h] = conf[idx][k].mean()
        # A class with too few views (a joint never hidden) borrows the other's figures.
        for k in arrays:
            row = arrays[k][jj]
            if np.isnan(row).any() and np.isfinite(row).any():
                arrays[k][jj] = np.where(np.isnan(row), row[np.isfinite(row)][0], row)
        if np.isnan(arrays["sigma_mm"][jj]).any():
            offset[jj] = np.nan
    for k in arrays:
        arrays[k][np.isnan(offset).any(axis=1)] = np.nan
    return DetectorFit(name, offset, source=dict(source or {}), **arrays)


def observe_fitted(cameras: list[Camera], scene: Scene, fit: DetectorFit,
                   rng: np.random.Generator, occluded: np.ndarray | None = None) -> Keypoints:
    """Synthetic detections of the scene's joints drawn from ``fit`` (module notes): each
    reported joint moved by its offset in the body frame, projected through the true cameras,
    scattered in pixels by its sigma in mm at its depth, with its gross errors and misses; only
    where the joint is in the image. ``occluded``: :func:`scene_occlusion`, if computed."""
    if occluded is None:
        occluded = scene_occlusion(cameras, scene)
    frames = body_frames(scene.joints)
    offset = np.nan_to_num(fit.offset_mm)
    target = scene.joints + np.einsum("tab,jb->tja", frames, offset)
    shape = (len(cameras),) + scene.joints.shape[:2]
    gauss = rng.normal(size=shape + (2,))
    u_gross, u_miss = rng.random(shape), rng.random(shape)
    angle = 2 * np.pi * rng.random(shape)
    h = occluded.astype(int)
    j = np.broadcast_to(np.arange(NUM_JOINTS), shape)
    pick = {k: np.nan_to_num(getattr(fit, k)[j, h]) for k in
            ("sigma_mm", "gross_rate", "gross_mm", "miss_rate", "confidence")}
    pixels = np.empty(shape + (2,))
    for c, camera in enumerate(cameras):
        depth = camera.world_to_cam(target)[..., 2]
        px_per_mm = (0.5 * (camera.fx + camera.fy)) / np.maximum(depth, 1e-6)
        gross = u_gross[c] < pick["gross_rate"][c]
        step = np.where(gross[..., None],
                        pick["gross_mm"][c][..., None] * np.stack(
                            [np.cos(angle[c]), np.sin(angle[c])], -1),
                        pick["sigma_mm"][c][..., None] * gauss[c])
        pixels[c] = camera.project(target) + px_per_mm[..., None] * step
        pixels[c] = np.clip(pixels[c], 0, [camera.width - 1, camera.height - 1])
    seen = np.stack([in_view(cam, scene.joints) for cam in cameras])
    detected = seen & fit.reported[None, None, :] & (u_miss >= pick["miss_rate"])
    pixels[~detected] = np.nan
    confidence = np.where(detected, pick["confidence"], 0.0)
    return Keypoints(pixels, confidence, occluded)
