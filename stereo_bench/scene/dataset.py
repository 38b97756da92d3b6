"""A rendered dataset on disk: images per camera plus exact ground truth as NumPy arrays.

Layout (documented in docs/dataset_format.md; paths built by ``rundir.DatasetPaths``)::

    DIR/manifest.json               schema version, fingerprint, resolved config, seed, camera
                                    and file lists, how each camera sees the board, warnings
    DIR/config.yaml                 the resolved rig configuration (re-render with it)
    DIR/pattern.png                 the board texture
    DIR/timing.json                 how long the render took (the only file that varies)
    DIR/blender/<camera>_texture.png  the print Blender rendered (renderer.kind blender only)
    DIR/ground_truth/*.npy          K (C,3,3), dist (C,8), cam_from_world_{rvec,tvec} (C,3),
                                    world_from_board_{rvec,tvec} (F,3), object_points (N,3)
                                    (the pattern's, given to the calibrations), board_points
                                    (N,3) (the physical board's, in the board frame: what the
                                    truth is made of), ids (N,), image_points (C,F,N,2),
                                    visible (C,F,N)
    DIR/images/<camera>/000000.png  synchronized frames, one folder per camera

The manifest is written last, so a directory with a readable manifest is complete; its
``fingerprint`` (of the resolved configuration and the code's format version) says what it was
rendered from, so a run reuses it only for the same configuration.
"""

from __future__ import annotations

import contextlib
import struct
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml

from ..core.camera import Camera
from ..config.bounds import ConfigError
from ..config.schema import RigConfig, parse_rig
from ..render import AnalyticRenderer, RenderSettings
from ..render.imaging import Light, Motion, Optics, Sensor
from .rig import GroundTruth, Rig, Trajectory, board_as_made, coverage_warnings
from ..io.rundir import DatasetPaths, changed_output, fingerprint, with_outputs
from ..core.files import (UnreadableFileError, read_arrays, read_grey, read_json, write_json,
                          write_npy, write_png, write_text)

SCHEMA_VERSION = 4  # 4: the imaging model (environment sections, board_points)
TEXTURE_PX_PER_MM = 10.0


def frame_rng(seed: int, camera_index: int, frame: int) -> np.random.Generator:
    """The noise generator of one image: independent of rendering order, so any subset of
    frames can be (re)rendered alone and still be byte-identical."""
    return np.random.default_rng([seed, camera_index, frame])


def render_settings(cfg: RigConfig, rig: Rig, cam: Camera) -> RenderSettings:
    """The renderer's settings for one camera of the rig (its focus: ``median_depth`` when the
    rig file leaves it to the camera)."""
    return environment_settings(cfg.environment, rig.median_depth(cam), rig.board)


def environment_settings(env, depth_mm: float, board=None) -> RenderSettings:
    """The imaging model of a rig file's ``environment`` section for a camera whose subject is
    ``depth_mm`` away (its focus when the section leaves the focus to the camera)."""
    o = env.optics
    focus = o.focus_distance_mm if o.focus_distance_mm is not None else max(
        depth_mm, 1.01 * o.focal_length_mm)
    return RenderSettings(
        supersampling=env.supersampling, background=env.background,
        black_level=env.black_level, white_level=env.white_level,
        light=Light(tuple(env.light.direction), env.light.distance_mm, env.light.ambient,
                    env.light.specular, env.light.shininess),
        motion=Motion(env.motion.exposure_ms, env.motion.speed_mm_s),
        optics=Optics(o.f_number, o.focal_length_mm, focus, o.blur_px, o.corner_illumination),
        sensor=Sensor(**env.sensor.model_dump()),
        board=board)


def dataset_fingerprint(cfg: RigConfig) -> str:
    """What a dataset depends on: the resolved configuration (seed included) and the format,
    and for the Blender backend the worker's packages; not the calibration settings, which
    only the later stages read."""
    # Nor the cameras' clock offsets, which a board dataset refuses (write_dataset): datasets
    # keep the fingerprints they had before cameras had clocks.
    config = cfg.model_dump(mode="json", exclude={"calibration": True, "renderer": True,
                                                  "cameras": {"__all__": {"time_offset_ms"}}})
    parts = ["dataset", SCHEMA_VERSION, config]
    if cfg.renderer.kind == "blender":
        # The analytic renderer's datasets keep the fingerprints they had before there was a
        # choice; Cycles' thread count does not change its pixels.
        from ..render.blender.environment import REQUIREMENTS

        parts += [cfg.renderer.model_dump(mode="json", exclude={"threads"}), list(REQUIREMENTS)]
    return fingerprint(*parts)


@contextlib.contextmanager
def _renderers(cfg: RigConfig, paths: DatasetPaths):
    """``make(camera, pattern, settings, R, t)`` -> the rig file's renderer for one camera (R, t:
    its cam_from_board over the frames). The Blender backend shares one render worker between
    the cameras and removes its scratch frames when done."""
    if cfg.renderer.kind == "analytic":
        yield lambda cam, pattern, settings, R, t: AnalyticRenderer(cam, pattern, settings)
        return
    from ..render.blender.board import BlenderRenderer, texture_density
    from ..render.blender.client import Worker

    made = []

    def make(cam, pattern, settings, R, t):
        made.append(BlenderRenderer(cam, pattern, settings, worker, paths.blender,
                                    texture_density(cam, pattern, R, t), cfg.renderer.samples,
                                    noise_threshold=cfg.renderer.noise_threshold))
        return made[-1]

    with Worker("render", cfg.renderer.threads) as worker:
        try:
            yield make
        finally:
            for renderer in made:
                renderer.close()


class UnusableRigError(ConfigError):
    """A valid rig file whose cameras would never see the board well enough to detect it."""


def _render_camera(cfg: RigConfig, rig: Rig, c: int, paths: DatasetPaths, make_renderer,
                   detections, tick) -> float:
    """Render (and write) camera ``c``'s frames, giving each image to ``detections`` if any;
    returns the seconds spent rendering and writing. ``tick()`` after each image."""
    cam = rig.cameras[c]
    settings = render_settings(cfg, rig, cam)
    R, t = rig.cam_from_board(cam)
    start = time.perf_counter()
    renderer = make_renderer(cam, rig.pattern, settings, R, t)
    omega, v = rig.board_velocity(cam, settings.motion.speed_mm_s,
                                  cfg.environment.motion.speed == "trajectory")
    elsewhere = 0.0  # in detections
    for f in range(len(rig.trajectory)):
        image = renderer.render(R[f], t[f], frame_rng(cfg.seed, c, f), (omega[f], v[f]))
        write_png(paths.image(cam.name, f), image)
        if detections is not None:
            before = time.perf_counter()
            detections.add(c, f, image)
            elsewhere += time.perf_counter() - before
        if tick:
            tick()
    return time.perf_counter() - start - elsewhere


def _camera_job(args) -> tuple[float, object]:
    """One camera of ``write_dataset`` in a worker process: (render seconds, the detections
    given, now holding that camera's frames)."""
    cfg_json, out, c, detections = args
    cfg = RigConfig.model_validate(cfg_json)
    cv2.setNumThreads(1)  # the processes share the cores: OpenCV's pool in each would oversubscribe
    paths = DatasetPaths(Path(out))
    with _renderers(cfg, paths) as make_renderer:
        seconds = _render_camera(cfg, Rig.from_config(cfg), c, paths, make_renderer,
                                 detections, None)
    return seconds, detections


def _render_cameras(cfg: RigConfig, rig: Rig, paths: DatasetPaths, detections, workers,
                    progress) -> float:
    """Every camera's frames into ``paths`` (``write_dataset``); the seconds they took."""
    from ..run.workers import in_processes, worker_count  # how this package starts processes

    frames = len(rig.trajectory)
    total = len(rig.cameras) * frames
    if worker_count(workers) > 1 and len(rig.cameras) > 1 and cfg.renderer.kind == "analytic":
        jobs = [(cfg.model_dump(mode="json"), str(paths.root), c, detections)
                for c in range(len(rig.cameras))]
        done = in_processes(_camera_job, jobs, workers,
                            progress and (lambda n, _: progress(n * frames, total)))
        if detections is not None:
            for _, found in done:
                detections.merge(found)
        return sum(seconds for seconds, _ in done)
    ticks = iter(range(1, total + 1))
    with _renderers(cfg, paths) as make_renderer:
        return sum(_render_camera(cfg, rig, c, paths, make_renderer, detections,
                                  progress and (lambda: progress(next(ticks), total)))
                   for c in range(len(rig.cameras)))


def write_dataset(cfg: RigConfig, out: Path, progress=None, detections=None,
                  workers=1) -> "Dataset":
    """Render every camera and frame of ``cfg`` into ``out`` and write the ground truth.

    ``detections``: a ``detect.dataset.DatasetDetections`` given each image as it is made (a
    stage that needs the pixels takes them here rather than reading the files back); its time
    is its own, not the dataset's render time. ``workers`` (a count, or the command's
    ``run.workers.Workers``) > 1: the cameras are rendered (and detected) that many at a time in
    spawned processes; the Blender backend renders in its one
    worker, camera after camera. The images are the same either way (each frame's noise has
    its own generator, ``frame_rng``).

    The ground truth is computed first: a rig in which no camera would see the board larger
    than ``MIN_BOARD_SPAN_PX`` is refused (UnusableRigError) before anything is rendered; a camera
    that alone cannot see it is kept and named in the manifest's warnings.
    ``progress(done, total)`` is called after each image (after each camera with ``workers``).
    """
    paths = DatasetPaths(Path(out))
    shifted = [c.name for c in cfg.cameras if c.time_offset_ms != 0]
    if shifted:
        # A board session's truth is one board pose per frame, shared by every camera (the
        # rig stage pairs views by frame); cameras at other instants would need one per camera.
        raise UnusableRigError(f"rig {cfg.name!r}: cameras {shifted} have a time_offset_ms; the "
                               f"board renderers expose every camera at the same instant (the "
                               f"offsets apply to bodies: pose-eval, calibration from the body)")
    try:
        rig = Rig.from_config(cfg)
    except ValueError as e:  # a camera model or rig geometry the renderer cannot use
        raise UnusableRigError(f"rig {cfg.name!r}: {e}") from None
    gt = rig.ground_truth()
    coverage = rig.coverage(gt)
    warnings, unusable = coverage_warnings(coverage, len(rig.trajectory),
                                           cfg.trajectory.kind == "session")
    if len(unusable) == len(rig.cameras):
        raise UnusableRigError(
            f"rig {cfg.name!r}: no camera would see the board: " + "; ".join(warnings)
            + " (fields: cameras.*.fx/fy/position_mm/look_at_mm, trajectory.depth_mm)")
    paths.manifest.unlink(missing_ok=True)
    with ThreadPoolExecutor(1) as side:
        # The board's picture is made while the cameras render (a studio's board is 45 MP,
        # 1.3 s, which would otherwise follow the cameras' processes).
        texture = side.submit(lambda: write_png(paths.texture,
                                                rig.pattern.texture(TEXTURE_PX_PER_MM)))
        render_s = _render_cameras(cfg, rig, paths, detections, workers, progress)
        texture.result()

    cams = rig.cameras
    arrays = {
        "K": np.stack([c.K for c in cams]),
        "dist": np.stack([c.dist for c in cams]),
        "cam_from_world_rvec": np.stack([c.rvec for c in cams]),
        "cam_from_world_tvec": np.stack([c.tvec for c in cams]),
        "world_from_board_rvec": rig.trajectory.rvecs,
        "world_from_board_tvec": rig.trajectory.tvecs,
        "closeup_of": rig.closeup_of,
        "object_points": rig.pattern.object_points(),
        "board_points": rig.board.points(rig.pattern.object_points()),
        "ids": rig.pattern.ids(),
        "image_points": gt.points,
        "visible": gt.visible,
    }
    for name, a in arrays.items():
        write_npy(paths.array(name), a)
    # The calibration settings are not part of the rendered data (a run may change them and
    # reuse the images): the dataset leaves them out, and the stages that use them record them.
    resolved = cfg.model_dump(mode="json", exclude={"calibration"})
    write_text(paths.config, yaml.safe_dump(resolved, sort_keys=False))
    write_json(paths.cameras, [c.to_dict() for c in cams])
    # Timing lives outside the manifest so that the same config and seed give identical files.
    write_json(paths.timing, {"render_s": render_s})
    write_json(paths.manifest, with_outputs({
        "schema_version": SCHEMA_VERSION,
        "fingerprint": dataset_fingerprint(cfg),
        "name": cfg.name,
        "seed": cfg.seed,
        "cameras": [c.name for c in cams],
        "frames": len(rig.trajectory),
        "points_per_frame": int(gt.points.shape[2]),
        "pattern": {"kind": cfg.pattern.kind, "code": rig.pattern.code,
                    "texture_px_per_mm": TEXTURE_PX_PER_MM},
        "coverage": coverage,
        "warnings": warnings,
        "config": resolved,
        "opencv_version": cv2.__version__,
        "ground_truth": {k: paths.array(k).relative_to(paths.root).as_posix() for k in arrays},
        "images": {c.name: f"images/{c.name}/{{frame:06d}}.png" for c in cams},
    }, paths.manifest, [paths.cameras] + [paths.array(k) for k in arrays]))
    return Dataset.load(out)


def png_size(path: Path) -> tuple[int, int] | None:
    """(width, height) from a PNG's header, or None if the file is not a PNG."""
    with open(path, "rb") as f:
        head = f.read(24)
    if len(head) < 24 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        return None
    return struct.unpack(">II", head[16:24])


@dataclass(frozen=True, eq=False)
class Dataset:
    """A dataset read back from disk (see the module docstring for the layout)."""

    root: Path
    config: RigConfig
    cameras: list[Camera]
    trajectory: Trajectory
    closeup_of: np.ndarray
    object_points: np.ndarray
    ids: np.ndarray
    ground_truth: GroundTruth
    manifest: dict

    @property
    def paths(self) -> DatasetPaths:
        return DatasetPaths(self.root)

    @property
    def pattern(self):
        return self.config.pattern.build()

    @property
    def fingerprint(self) -> str:
        return self.manifest["fingerprint"]

    @property
    def warnings(self) -> list[str]:
        return list(self.manifest.get("warnings", []))

    @property
    def render_time_s(self) -> float:
        try:
            return float(read_json(self.paths.timing)["render_s"])
        except (FileNotFoundError, UnreadableFileError, KeyError, TypeError, ValueError,
                OverflowError):  # a wall time only: an unreadable one is unknown, not fatal
            return float("nan")

    @property
    def frames(self) -> int:
        return len(self.trajectory)

    def image(self, camera: int | str, frame: int) -> np.ndarray:
        if isinstance(camera, str):
            by_name = {c.name: c for c in self.cameras}
            if camera not in by_name:
                raise ValueError(f"{self.root}: no camera {camera!r} (cameras: {list(by_name)})")
            cam = by_name[camera]
        else:
            cam = self.cameras[camera]
        path = self.paths.image(cam.name, frame)
        img = read_grey(path)
        if img is None:
            raise FileNotFoundError(f"{path}: missing or unreadable image")
        if img.shape != (cam.height, cam.width):
            raise ValueError(f"{path}: {img.shape[1]}x{img.shape[0]} px, expected "
                             f"{cam.width}x{cam.height} (camera {cam.name!r})")
        return img

    def rig(self) -> Rig:
        """The rig the dataset was rendered from, its board as made (so that what is scored
        against the truth, e.g. RMSE_cal, meets the physical board, not its pattern file)."""
        return Rig(self.config.name, self.config.seed, self.cameras, self.pattern,
                   self.trajectory, self.closeup_of, board_as_made(self.config, self.pattern))

    def check_images(self) -> None:
        """Refuse a dataset whose images are not the size of their camera (an image replaced
        after rendering would otherwise be detected and scored against the wrong truth)."""
        for cam in self.cameras:
            for f in range(self.frames):
                path = self.paths.image(cam.name, f)
                if not path.is_file():
                    continue  # a missing image is one failed frame, recorded by detection
                size = png_size(path)
                if size is None:
                    raise ValueError(f"{path}: not a PNG image")
                if size != (cam.width, cam.height):
                    raise ValueError(f"{path}: {size[0]}x{size[1]} px, expected "
                                     f"{cam.width}x{cam.height} (camera {cam.name!r}); the "
                                     f"dataset was changed after it was rendered")

    @classmethod
    def load(cls, root) -> "Dataset":
        """Read a dataset; FileNotFoundError when it has no manifest, UnreadableFileError or
        ValueError (naming the file) when its files are torn, inconsistent or of another
        version."""
        root = Path(root)
        paths = DatasetPaths(root)
        mpath = paths.manifest
        if not mpath.is_file():
            raise FileNotFoundError(f"{mpath}: not found; is {root} a complete dataset written "
                                    f"by `stereo-bench render`?")
        manifest = read_json(mpath)
        if not isinstance(manifest, dict) or manifest.get("schema_version") != SCHEMA_VERSION:
            found = manifest.get("schema_version") if isinstance(manifest, dict) else None
            raise UnreadableFileError(f"{mpath}: schema_version {found!r}, expected "
                                      f"{SCHEMA_VERSION} (render it again)")
        try:
            # Calibration settings are not rendered data (an older dataset may still hold them).
            cfg = parse_rig({k: v for k, v in manifest["config"].items() if k != "calibration"},
                            str(mpath))
            if manifest["fingerprint"] != dataset_fingerprint(cfg):
                raise UnreadableFileError(f"{mpath}: its fingerprint does not match its config "
                                          f"(edited by hand?); render it again")
            if changed := changed_output(mpath, manifest):
                raise UnreadableFileError(f"{changed}; render it again")

            def arr(name):
                p = root / manifest["ground_truth"][name]
                if not p.is_file():
                    raise FileNotFoundError(f"{p}: ground-truth array missing")
                return read_arrays(p, "a ground-truth array")

            cams = [Camera.from_dict(d, str(paths.cameras)) for d in read_json(paths.cameras)]
        except (KeyError, TypeError) as e:
            raise UnreadableFileError(f"{mpath}: incomplete ({e!r} missing)") from None
        if [c.name for c in cams] != [c.name for c in cfg.cameras]:
            raise UnreadableFileError(f"{paths.cameras}: cameras do not match {mpath}")
        ds = cls(root, cfg, cams,
                 Trajectory(arr("world_from_board_rvec"), arr("world_from_board_tvec")),
                 arr("closeup_of"), arr("object_points"), arr("ids"),
                 GroundTruth(arr("image_points"), arr("visible")), manifest)
        ds.check_images()
        return ds
