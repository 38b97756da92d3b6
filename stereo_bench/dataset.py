"""A rendered dataset on disk: images per camera plus exact ground truth as NumPy arrays.

Layout (documented in docs/dataset_format.md)::

    DIR/manifest.json               schema version, resolved config, seed, camera and file lists
    DIR/config.yaml                 the resolved rig configuration (re-render with it)
    DIR/pattern.png                 the board texture
    DIR/timing.json                 how long the render took (the only file that varies)
    DIR/ground_truth/*.npy          K (C,3,3), dist (C,8), cam_from_world_{rvec,tvec} (C,3),
                                    world_from_board_{rvec,tvec} (F,3), object_points (N,3),
                                    ids (N,), image_points (C,F,N,2), visible (C,F,N)
    DIR/images/<camera>/000000.png  synchronized frames, one folder per camera

The manifest is written last, so a directory with a manifest is complete.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml

from .camera import Camera
from .config import RigConfig, parse_rig
from .patterns import pattern_from_config
from .render import AnalyticRenderer, RenderSettings
from .rig import GroundTruth, Rig, Trajectory

SCHEMA_VERSION = 1
TEXTURE_PX_PER_MM = 10.0


def frame_rng(seed: int, camera_index: int, frame: int) -> np.random.Generator:
    """The noise generator of one image: independent of rendering order, so any subset of
    frames can be (re)rendered alone and still be byte-identical."""
    return np.random.default_rng([seed, camera_index, frame])


def image_path(root: Path, camera: str, frame: int) -> Path:
    return Path(root) / "images" / camera / f"{frame:06d}.png"


def render_settings(cfg: RigConfig) -> RenderSettings:
    env = cfg.environment
    return RenderSettings(
        environment=env.kind, noise_sigma=env.noise_sigma,
        light_direction=tuple(env.light_direction), ambient=env.ambient,
        blur_sigma_px=env.blur_sigma_px, background=env.background,
        supersampling=env.supersampling)


def write_dataset(cfg: RigConfig, out: Path, progress=None) -> "Dataset":
    """Render every camera and frame of ``cfg`` into ``out`` and write the ground truth.

    ``progress(done, total)`` is called after each image.
    """
    out = Path(out)
    rig = Rig.from_config(cfg)
    gt = rig.ground_truth()
    settings = render_settings(cfg)
    gt_dir = out / "ground_truth"
    gt_dir.mkdir(parents=True, exist_ok=True)
    manifest = out / "manifest.json"
    manifest.unlink(missing_ok=True)

    total = len(rig.cameras) * len(rig.trajectory)
    done = 0
    t0 = time.perf_counter()
    for c, cam in enumerate(rig.cameras):
        renderer = AnalyticRenderer(cam, rig.pattern, settings)
        R, t = rig.cam_from_board(cam)
        (out / "images" / cam.name).mkdir(parents=True, exist_ok=True)
        for f in range(len(rig.trajectory)):
            img = renderer.render(R[f], t[f], frame_rng(cfg.seed, c, f))
            cv2.imwrite(str(image_path(out, cam.name, f)), img)
            done += 1
            if progress:
                progress(done, total)

    cams = rig.cameras
    arrays = {
        "K": np.stack([c.K for c in cams]),
        "dist": np.stack([c.dist for c in cams]),
        "cam_from_world_rvec": np.stack([c.rvec for c in cams]),
        "cam_from_world_tvec": np.stack([c.tvec for c in cams]),
        "world_from_board_rvec": rig.trajectory.rvecs,
        "world_from_board_tvec": rig.trajectory.tvecs,
        "object_points": rig.pattern.object_points(),
        "ids": rig.pattern.ids(),
        "image_points": gt.points,
        "visible": gt.visible,
    }
    for name, a in arrays.items():
        np.save(gt_dir / f"{name}.npy", a)
    rig.pattern.save_texture(out / "pattern.png", TEXTURE_PX_PER_MM)
    resolved = cfg.model_dump(mode="json")
    (out / "config.yaml").write_text(yaml.safe_dump(resolved, sort_keys=False))
    (gt_dir / "cameras.json").write_text(json.dumps([c.to_dict() for c in cams], indent=2))
    # Timing lives outside the manifest so that the same config and seed give identical files.
    (out / "timing.json").write_text(json.dumps({"render_s": time.perf_counter() - t0}))
    manifest.write_text(json.dumps({
        "schema_version": SCHEMA_VERSION,
        "name": cfg.name,
        "seed": cfg.seed,
        "cameras": [c.name for c in cams],
        "frames": len(rig.trajectory),
        "points_per_frame": int(gt.points.shape[2]),
        "pattern": {"kind": cfg.pattern.kind, "code": rig.pattern.code,
                    "texture_px_per_mm": TEXTURE_PX_PER_MM},
        "frames_out_of_view": rig.frames_out_of_view(gt),
        "config": resolved,
        "opencv_version": cv2.__version__,
        "ground_truth": {k: f"ground_truth/{k}.npy" for k in arrays},
        "images": {c.name: f"images/{c.name}/{{frame:06d}}.png" for c in cams},
    }, indent=2))
    return Dataset.load(out)


@dataclass(frozen=True, eq=False)
class Dataset:
    """A dataset read back from disk (see the module docstring for the layout)."""

    root: Path
    config: RigConfig
    cameras: list[Camera]
    trajectory: Trajectory
    object_points: np.ndarray
    ids: np.ndarray
    ground_truth: GroundTruth
    manifest: dict

    @property
    def pattern(self):
        return pattern_from_config(self.config.pattern.kind, **self.config.pattern.overrides())

    @property
    def render_time_s(self) -> float:
        path = self.root / "timing.json"
        return json.loads(path.read_text())["render_s"] if path.is_file() else float("nan")

    @property
    def frames(self) -> int:
        return len(self.trajectory)

    def image(self, camera: int | str, frame: int) -> np.ndarray:
        name = camera if isinstance(camera, str) else self.cameras[camera].name
        path = image_path(self.root, name, frame)
        img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise FileNotFoundError(f"{path}: missing or unreadable image")
        return img

    def rig(self) -> Rig:
        return Rig(self.config.name, self.config.seed, self.cameras, self.pattern,
                   self.trajectory)

    @classmethod
    def load(cls, root) -> "Dataset":
        root = Path(root)
        mpath = root / "manifest.json"
        if not mpath.is_file():
            raise FileNotFoundError(f"{mpath}: not found; is {root} a complete dataset written "
                                    f"by `stereo-bench render`?")
        manifest = json.loads(mpath.read_text())
        if manifest.get("schema_version") != SCHEMA_VERSION:
            raise ValueError(f"{mpath}: schema_version {manifest.get('schema_version')!r}, "
                             f"expected {SCHEMA_VERSION}")
        cfg = parse_rig(manifest["config"], str(mpath))

        def arr(name):
            p = root / manifest["ground_truth"][name]
            if not p.is_file():
                raise FileNotFoundError(f"{p}: ground-truth array missing")
            return np.load(p)

        cams = [Camera.from_dict(d, f"{root}/ground_truth/cameras.json")
                for d in json.loads((root / "ground_truth" / "cameras.json").read_text())]
        return cls(root, cfg, cams,
                   Trajectory(arr("world_from_board_rvec"), arr("world_from_board_tvec")),
                   arr("object_points"), arr("ids"),
                   GroundTruth(arr("image_points"), arr("visible")), manifest)
