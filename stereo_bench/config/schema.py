"""Rig YAML files: the validated description of cameras, pattern, trajectory and environment.

Every key is checked by pydantic: an unknown key, a missing field or a wrong type becomes a
``ConfigError`` whose message names the file, the field path and what was expected.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Annotated, Literal

import numpy as np
from pydantic import (AfterValidator, BaseModel, ConfigDict, Field, Strict, ValidationError,
                      ValidationInfo, field_validator, model_validator)

from ..core.camera import Camera
from ..core.lens import lens_parameters
from ..core.poses import look_at_rotation, matrix_to_rodrigues
from ..core.files import is_safe_name
from .bounds import (ConfigError, MAX_BLUR_PX, MAX_BOARD_MM, MAX_CAMERAS, MAX_DISTANCE_MM,
                     MAX_DISTORTION, MAX_FOCAL_PX, MAX_FRAMES, MAX_IMAGE_PIXELS, MAX_IMAGE_SIDE,
                     MAX_PATTERN_COUNT, MAX_PIXEL_ASPECT, MAX_SKEW_PX, MAX_TIME_OFFSET_MS)
from .yaml_reader import load_yaml


# Strict scalars: YAML's `true` is not 1, `"9"` is not 9, and NaN or infinity is no length.
Int = Annotated[int, Strict()]
Float = Annotated[float, Strict(), Field(allow_inf_nan=False)]


def _safe_name(name: str) -> str:
    if not is_safe_name(name):
        raise ValueError(f"{name!r} is not a safe name (it becomes a folder name: expected 1-64 "
                         f"letters, digits, '_', '-' or '.', and not '.' or '..')")
    return name


Name = Annotated[str, Strict(), AfterValidator(_safe_name)]
Vec3 = tuple[Float, Float, Float]
PatternKind = Literal["checkerboard", "symmetric_circles", "asymmetric_circles", "charuco"]


def _known_environment(kind: str) -> str:
    from .environments import PRESETS

    if kind not in PRESETS:
        raise ValueError(f"unknown environment {kind!r}; expected one of {', '.join(PRESETS)}")
    return kind


#: An environment preset's name (stereo_bench/environments.py).
EnvironmentKind = Annotated[str, Strict(), AfterValidator(_known_environment)]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class LensConfig(_Strict):
    """A camera's image and lens: intrinsics (px) and the ``lens`` model's parameters ``dist``
    (core/lens.py): OpenCV's [k1, k2, p1, p2, k3, k4, k5, k6] (4 to 8 of them) by default;
    kannala_brandt [k1, k2, k3, k4]; mei [xi, k1, k2, p1, p2]; double_sphere [xi, alpha]."""

    width: Int = Field(ge=2, le=MAX_IMAGE_SIDE)
    height: Int = Field(ge=2, le=MAX_IMAGE_SIDE)
    fx: Float = Field(gt=0, le=MAX_FOCAL_PX)
    fy: Float = Field(gt=0, le=MAX_FOCAL_PX)
    cx: Float
    cy: Float
    skew: Float = Field(0.0, ge=-MAX_SKEW_PX, le=MAX_SKEW_PX)
    lens: Literal["opencv", "kannala_brandt", "mei", "double_sphere"] = "opencv"
    dist: list[Float] = Field(default_factory=lambda: [0.0] * 8,
                              description="the lens model's parameters; for opencv "
                                          "[k1, k2, p1, p2, k3, k4, k5, k6] (OpenCV order)")

    @field_validator("dist")
    @classmethod
    def _dist_len(cls, v, info: ValidationInfo):
        if v and max(abs(x) for x in v) > MAX_DISTORTION:
            raise ValueError(f"expected coefficients of magnitude at most {MAX_DISTORTION:g}")
        lens = info.data.get("lens", "opencv")  # validated before dist (declared before it)
        if lens != "opencv":
            return lens_parameters(lens, v, f"{lens} lens").tolist()
        if not 4 <= len(v) <= 8:
            raise ValueError("expected 4 to 8 coefficients [k1, k2, p1, p2, k3, k4, k5, k6]")
        return list(v) + [0.0] * (8 - len(v))

    @model_validator(mode="after")
    def _image(self):
        if max(self.fx / self.fy, self.fy / self.fx) > MAX_PIXEL_ASPECT:
            raise ValueError(f"fx / fy: {self.fx / self.fy:.4g}; expected pixels at most "
                             f"{MAX_PIXEL_ASPECT:g} times as tall as wide or as wide as tall")
        if self.width * self.height > MAX_IMAGE_PIXELS:
            raise ValueError(f"width x height: {self.width}x{self.height} exceeds "
                             f"{MAX_IMAGE_PIXELS:,} pixels")
        # A principal point outside the image leaves no field of view on one side, and the
        # automatic trajectory would put the board kilometres away to keep it in view.
        for axis, c, size in (("cx", self.cx, self.width), ("cy", self.cy, self.height)):
            if not 0.05 * size <= c <= 0.95 * size - 1:
                raise ValueError(f"{axis}: {c} lies outside the central 90 % of the image "
                                 f"(0..{size - 1} px); expected a principal point near the "
                                 f"image centre ({(size - 1) / 2})")
        return self


def _within_reach(v):
    if max(abs(x) for x in v) > MAX_DISTANCE_MM:
        raise ValueError(f"expected coordinates within 1 km ({MAX_DISTANCE_MM:g} mm) of the "
                         f"origin")
    return v


Position = Annotated[Vec3, AfterValidator(_within_reach)]


class CameraConfig(LensConfig):
    """One camera: its lens and where it sits in the world (mm), looking at ``look_at_mm`` with
    ``up`` pointing up in its image."""

    name: Name
    position_mm: Position = (0.0, 0.0, 0.0)
    look_at_mm: Position = (0.0, 0.0, 1000.0)
    up: Vec3 = (0.0, -1.0, 0.0)
    time_offset_ms: Float = Field(0.0, ge=-MAX_TIME_OFFSET_MS, le=MAX_TIME_OFFSET_MS,
                                  description="how far this camera's clock runs ahead of the "
                                              "rig's: its frame f is exposed at f / fps + offset "
                                              "(unsynchronised cameras; bodies only)")

    @model_validator(mode="after")
    def _geometry(self):
        view = np.subtract(self.look_at_mm, self.position_mm)
        if np.linalg.norm(view) < 1e-6:
            raise ValueError("look_at_mm: expected a point other than position_mm")
        if np.linalg.norm(np.cross(view, self.up)) < 1e-9 * np.linalg.norm(view) * max(
                np.linalg.norm(self.up), 1e-300):
            raise ValueError("up: expected a direction not parallel to the viewing direction")
        return self

    def camera(self) -> Camera:
        R = look_at_rotation(np.array(self.position_mm), np.array(self.look_at_mm),
                             np.array(self.up))
        t = -R @ np.array(self.position_mm, dtype=np.float64)
        return Camera(self.name, self.width, self.height, self.fx, self.fy, self.cx, self.cy,
                      self.skew, np.array(self.dist), matrix_to_rodrigues(R), t, self.lens)


class StudioConfig(_Strict):
    """Cameras placed around a capture volume, in a world with z up and the floor at z = 0.

    ``ring``: ``count`` cameras on a circle of ``radius_mm`` around ``centre_mm``, spread
    evenly over ``arc_deg`` from ``start_deg`` (360: a full ring; less: both ends of the arc get
    a camera, e.g. 180 for a half ring). ``rectangle``: half of the cameras on each long side of
    a ``size_mm`` (x, y) rectangle, evenly from corner to corner (4 cameras: the corners). Every
    camera looks at ``look_at_mm``, upright. Heights and lenses are taken in turn from
    ``height_mm`` and ``lenses`` (one entry: the same for all; a list: mixed)."""

    layout: Literal["ring", "rectangle"]
    count: Int = Field(ge=2, le=MAX_CAMERAS)
    radius_mm: Float | None = Field(None, gt=0, le=1e5)
    arc_deg: Float = Field(360.0, gt=0, le=360)
    start_deg: Float = Field(0.0, ge=-360, le=360)
    size_mm: tuple[Float, Float] | None = None
    centre_mm: Position = (0.0, 0.0, 0.0)
    height_mm: list[Float] = Field([1500.0], min_length=1, max_length=MAX_CAMERAS)
    look_at_mm: Position = (0.0, 0.0, 1000.0)
    lenses: list[LensConfig] = Field(min_length=1, max_length=MAX_CAMERAS)
    names: list[Name] | None = None
    time_offset_ms: list[Float] | None = None

    @model_validator(mode="after")
    def _layout(self):
        if self.layout == "ring" and self.radius_mm is None:
            raise ValueError("radius_mm: required for a ring")
        if self.layout == "rectangle":
            if self.size_mm is None or not 0 < min(self.size_mm) <= max(self.size_mm) <= 1e5:
                raise ValueError("size_mm: a rectangle needs its (x, y) size, 0 < size <= 1e5 mm")
            if self.count % 2:
                raise ValueError(f"count: a rectangle puts half of its cameras on each long "
                                 f"side; expected an even count, got {self.count}")
        if self.names is not None and len(self.names) != self.count:
            raise ValueError(f"names: expected {self.count} names (count), got "
                             f"{len(self.names)}")
        if self.time_offset_ms is not None and len(self.time_offset_ms) != self.count:
            raise ValueError(f"time_offset_ms: expected {self.count} offsets (count), got "
                             f"{len(self.time_offset_ms)}")
        if max(abs(h) for h in self.height_mm) > 1e5:
            raise ValueError("height_mm: expected heights within 100 m")
        return self

    def positions(self) -> np.ndarray:
        """Camera centres (count, 3) mm."""
        n = self.count
        if self.layout == "ring":
            full = self.arc_deg >= 360
            angles = np.radians(self.start_deg + self.arc_deg * np.arange(n) / (n if full else
                                                                             n - 1))
            xy = self.radius_mm * np.column_stack([np.cos(angles), np.sin(angles)])
        else:
            w, d = self.size_mm
            long_x = w >= d  # the long sides run along x when the rectangle is wider than deep
            span, side = (w, d) if long_x else (d, w)
            k = n // 2
            along = span * (np.arange(k) / (k - 1) - 0.5) if k > 1 else np.zeros(1)
            pts = [(a, s * side / 2) for s in (-1, 1) for a in (along if s < 0 else along[::-1])]
            xy = np.array([(a, b) if long_x else (b, a) for a, b in pts])
        z = np.resize(np.asarray(self.height_mm, dtype=np.float64), n)
        return np.column_stack([xy, z]) + np.asarray(self.centre_mm)

    def cameras(self) -> list[dict]:
        """The cameras as rig-file entries (``cameras:``), named ``cam1`` ... unless ``names``."""
        names = self.names or [f"cam{i + 1}" for i in range(self.count)]
        return [{**self.lenses[i % len(self.lenses)].model_dump(), "name": names[i],
                 "position_mm": tuple(float(v) for v in p), "look_at_mm": self.look_at_mm,
                 "up": (0.0, 0.0, 1.0),
                 "time_offset_ms": self.time_offset_ms[i] if self.time_offset_ms else 0.0}
                for i, p in enumerate(self.positions())]


def _check_override(field: dataclasses.Field, value):
    """One pattern override, checked against the pattern class's field type and bounds."""
    if field.type in ("bool", bool):
        if not isinstance(value, bool):
            raise ValueError(f"pattern.{field.name}: expected true or false, got {value!r}")
    elif field.type in ("int", int):
        if not isinstance(value, int) or isinstance(value, bool):
            raise ValueError(f"pattern.{field.name}: expected an integer, got {value!r}")
        # Counts of squares, rows or columns, unless the field gives its own bounds (an id).
        least = field.metadata.get("min", 2)
        most = field.metadata.get("max", MAX_PATTERN_COUNT)
        if not least <= value <= most:
            raise ValueError(f"pattern.{field.name}: expected {least}..{most}, got {value}")
    elif field.type in ("float", float):
        if isinstance(value, bool) or not isinstance(value, (int, float)) \
                or not math.isfinite(value):
            raise ValueError(f"pattern.{field.name}: expected a finite number, got {value!r}")
        if not 0 <= value <= MAX_BOARD_MM:
            raise ValueError(f"pattern.{field.name}: expected 0..{MAX_BOARD_MM} mm, got {value}")
        return float(value)
    elif field.type in ("str", str) and not isinstance(value, str):
        raise ValueError(f"pattern.{field.name}: expected a string, got {value!r}")
    return value


class PatternConfig(_Strict):
    """The board: a kind plus optional overrides of its geometry (see stereo_bench.core.patterns).

    Overrides are checked per kind: the field must exist on that board, with its type, and the
    board they make must be buildable and of a size one machine can render. Counts of at least
    2 per direction keep every board two-dimensional (one row would be collinear)."""

    model_config = ConfigDict(extra="allow", frozen=True)
    kind: PatternKind

    @model_validator(mode="before")
    @classmethod
    def _inner_corners(cls, data):
        """A checkerboard as users (and OpenCV's patternSize) describe it: ``inner_corners:
        [columns, rows]``, 9 x 6 for a board of 10 x 7 squares."""
        if not isinstance(data, dict) or "inner_corners" not in data:
            return data
        data = dict(data)
        corners = data.pop("inner_corners")
        if data.get("kind") != "checkerboard":
            raise ValueError(f"pattern.inner_corners: only for kind checkerboard (a "
                             f"{data.get('kind')} is described by its own fields)")
        if {"squares_x", "squares_y"} & set(data):
            raise ValueError("pattern.inner_corners: give it or squares_x/squares_y, not both")
        if (not isinstance(corners, (list, tuple)) or len(corners) != 2
                or not all(isinstance(n, int) and not isinstance(n, bool) and n >= 2
                           for n in corners)):
            raise ValueError(f"pattern.inner_corners: expected [columns, rows] of inner corners, "
                             f"each an integer of at least 2, got {corners!r}")
        data["squares_x"], data["squares_y"] = corners[0] + 1, corners[1] + 1
        return data

    @model_validator(mode="after")
    def _overrides(self):
        from ..core.patterns import PATTERNS

        cls = PATTERNS[self.kind]
        fields = {f.name: f for f in dataclasses.fields(cls)}
        for name, value in self.overrides().items():
            if name not in fields:
                raise ValueError(f"pattern.{name}: unknown field for {self.kind} (fields: "
                                 f"{', '.join(sorted(fields))})")
            self.model_extra[name] = _check_override(fields[name], value)
        board = self.build()
        w, h = board.size_mm
        if max(w, h) > MAX_BOARD_MM:
            raise ValueError(f"pattern: the board's outline is {w:.0f} x {h:.0f} mm; expected "
                             f"at most {MAX_BOARD_MM:.0f} mm per side")
        return self

    def overrides(self) -> dict:
        return dict(self.model_extra or {})

    def build(self):
        from ..core.patterns import pattern_from_config

        return pattern_from_config(self.kind, **self.overrides())


class TrajectoryConfig(_Strict):
    """How the board moves (rig.py builds the poses).

    ``spring``: the paper's conical spring, a helix around the rig's viewing axis whose radius
    grows linearly with depth (``depth_mm``, ``radius_mm``; None: chosen from the board size and
    the narrowest camera's field of view); the board faces the rig, tilted by up to ``tilt_deg``.

    ``dome``: for a wide lens, the board over its whole field (past 90 degrees off axis where
    it sees behind its plane), each frame at a direction up to ``max_angle_deg`` off the rig's
    viewing axis (None: the lens's reach toward its image edges) and a depth in ``depth_mm``,
    facing the rig, tilted by up to ``tilt_deg`` (rig.dome).

    ``poses``: the board exactly where ``poses`` puts it, one world_from_board per frame,
    each ``[rx, ry, rz, tx, ty, tz]`` (Rodrigues vector, rad; translation, mm); ``frames`` is
    their number (a twin of a real capture replays the poses its calibration estimated).

    ``session``: a calibration session in a studio that surrounds the volume: ``frames`` of the
    board carried through the volume (within ``walk_radius_mm`` of its centre, its centre at
    heights ``height_mm``), turned ``turns`` times about the vertical so that it faces every
    camera in turn, tilted by up to ``tilt_deg``; then, when ``closeups`` > 0, that many frames
    per camera of the board waved close in front of it (each camera's own conical spring, with
    ``depth_mm``/``radius_mm`` if given), as studios take them for intrinsics.
    """

    kind: Literal["spring", "dome", "poses", "session"] = "spring"
    frames: Int = Field(127, gt=0, le=MAX_FRAMES)
    depth_mm: tuple[Float, Float] | None = None
    radius_mm: tuple[Float, Float] | None = None
    turns: Float = Field(4.0, gt=0, le=1000)
    tilt_deg: Float = Field(30.0, ge=0, lt=80)
    roll_deg: Float = Field(20.0, ge=0, le=180)
    closeups: Int = Field(0, ge=0, le=MAX_FRAMES)
    walk_radius_mm: Float | None = Field(None, ge=0, le=1e5)
    height_mm: tuple[Float, Float] | None = None
    max_angle_deg: Float | None = Field(None, gt=0, lt=180)
    poses: list[tuple[Float, Float, Float, Float, Float, Float]] | None = Field(
        None, min_length=1, max_length=MAX_FRAMES)

    @model_validator(mode="after")
    def _ranges(self):
        if self.depth_mm is not None and not 0 < self.depth_mm[0] <= self.depth_mm[1] <= 1e6:
            raise ValueError("depth_mm: expected 0 < near <= far <= 1e6 mm")
        if self.radius_mm is not None and not 0 <= min(self.radius_mm) <= max(
                self.radius_mm) <= 1e6:
            raise ValueError("radius_mm: expected radii in 0..1e6 mm")
        if self.kind != "session":
            # Their defaults are allowed: the resolved configuration lists every field.
            for f, default in (("closeups", 0), ("walk_radius_mm", None), ("height_mm", None)):
                if getattr(self, f) != default:
                    raise ValueError(f"{f}: only a session trajectory (kind: session) has it")
        if self.kind != "dome" and self.max_angle_deg is not None:
            raise ValueError("max_angle_deg: only a dome trajectory (kind: dome) has it")
        if (self.kind == "poses") != (self.poses is not None):
            raise ValueError("poses: a poses trajectory (kind: poses) needs them, and only it "
                             "has them")
        if self.poses is not None:
            if "frames" in self.model_fields_set and self.frames != len(self.poses):
                raise ValueError(f"frames: {self.frames}, but poses has {len(self.poses)} "
                                 f"(leave frames out: it is their number)")
            object.__setattr__(self, "frames", len(self.poses))
            if any(abs(math.hypot(*p[3:])) > 1e6 or math.hypot(*p[:3]) > 4 * math.pi
                   for p in self.poses):
                raise ValueError("poses: expected [rx, ry, rz] within 4 pi rad and a "
                                 "translation within 1 km per frame")
        if self.kind == "dome" and self.radius_mm is not None:
            raise ValueError("radius_mm: a dome trajectory spreads the board over the lens's "
                             "field (max_angle_deg); the spring has a radius")
        if self.height_mm is not None and not -1e5 <= self.height_mm[0] <= self.height_mm[1] \
                <= 1e5:
            raise ValueError("height_mm: expected (low, high) with low <= high, within 100 m")
        return self

    def frames_for(self, cameras: int) -> int:
        """Frames of the dataset: the walk, then the close-ups of every camera."""
        return self.frames + (self.closeups * cameras if self.kind == "session" else 0)


class CalibrationConfig(_Strict):
    """How the calibrations are computed from the detections (not part of the rendered data:
    editing it reuses the images and the detections).

    ``intrinsics_views``: the views each camera's intrinsics come from: ``all``, only the
    ``closeups`` of a session, or only the ``session`` (walk) frames. The rig stage uses every
    frame two cameras share, and with ``refine_intrinsics`` (the rig's bundle adjustment also
    moves each camera's intrinsics, the parameters its method estimates) every frame any camera
    saw, since each constrains that camera's intrinsics. ``loss``: the robust
    loss of the rig's bundle adjustment (scipy's names; ``linear`` is plain least squares, the
    cost cv2.stereoCalibrate minimizes), with residuals scaled by ``loss_scale_px``."""

    intrinsics_views: Literal["all", "closeups", "session"] = "all"
    refine_intrinsics: Annotated[bool, Strict()] = False
    # Fit the board's warp (mrcal's two-parabola deflection) in each camera's refinement, for
    # the methods that can (zhang and its lens models; calibrate.fits_board_warp).
    fit_board_warp: Annotated[bool, Strict()] = False
    loss: Literal["linear", "soft_l1", "huber", "cauchy"] = "linear"
    loss_scale_px: Float = Field(1.0, gt=0, le=100)


class LightConfig(_Strict):
    """The lamp: ``direction`` it shines in (world frame), its ``distance_mm`` from the world
    origin, the ``ambient`` share (1 = uniform light, no shading), and a glossy print's
    ``specular`` highlight (its peak as a share of the white print) with Blinn-Phong
    ``shininess``."""

    direction: Vec3 = (0.6, -0.5, 1.0)
    distance_mm: Float = Field(1500.0, gt=0, le=1e6)
    ambient: Float = Field(1.0, ge=0, le=1)
    specular: Float = Field(0.0, ge=0, le=2)
    shininess: Float = Field(50.0, ge=1, le=10000)

    @field_validator("direction")
    @classmethod
    def _nonzero(cls, v):
        if not 1e-9 < np.linalg.norm(v) < 1e9:
            raise ValueError("expected a direction of length between 1e-9 and 1e9")
        return v


class OpticsConfig(_Strict):
    """The lens: thin-lens defocus (``f_number``, None = a pinhole with everything in focus;
    the lens's physical ``focal_length_mm``; ``focus_distance_mm``, depth along the optical
    axis; None: each camera focused on the median depth of the board's centre in its views), a
    Gaussian lens blur ``blur_px`` (sigma) and vignetting (``corner_illumination``, the
    relative illumination at the image's farthest corner, 1 = none)."""

    f_number: Float | None = Field(None, ge=0.5, le=128)
    focal_length_mm: Float = Field(8.0, gt=0, le=2000)
    focus_distance_mm: Float | None = Field(None, gt=0, le=1e7)
    blur_px: Float = Field(0.0, ge=0, le=MAX_BLUR_PX)
    corner_illumination: Float = Field(1.0, gt=0, le=1)

    @model_validator(mode="after")
    def _focus(self):
        if self.focus_distance_mm is not None and self.focus_distance_mm <= self.focal_length_mm:
            raise ValueError(f"focus_distance_mm: {self.focus_distance_mm} mm; a lens of "
                             f"{self.focal_length_mm} mm focuses beyond its focal length")
        return self


class MotionConfig(_Strict):
    """Motion blur: the shutter is open ``exposure_ms`` while the board moves along its
    trajectory, its fastest outline corner at ``speed_mm_s`` (its rotation follows the
    trajectory's). ``speed``: ``constant``, every frame at ``speed_mm_s``; ``trajectory``,
    the frames are evenly spaced in time (frames of a video, as a studio's session is shot),
    so each moves at ``speed_mm_s`` (the mean of its sequence) scaled by its own step: the
    blur follows the hand, fastest where the trajectory moves most between frames."""

    exposure_ms: Float = Field(0.0, ge=0, le=1000)
    speed_mm_s: Float = Field(0.0, ge=0, le=1e5)
    speed: Literal["constant", "trajectory"] = "constant"


class SensorConfig(_Strict):
    """The photon transfer model: ``full_well_e`` (None: no photon noise), the white print's
    ``exposure`` as a share of the full well (the gain maps it back to its grey level, so low
    light means more noise), extra ``gain`` (> 1 clips highlights), ``read_noise_e``; additive
    Gaussian ``noise_sigma`` in grey levels; an ADC of ``adc_bits``; ``jpeg_quality`` (None:
    lossless)."""

    full_well_e: Float | None = Field(None, ge=10, le=1e7)
    exposure: Float = Field(0.6, gt=0, le=1)
    gain: Float = Field(1.0, gt=0, le=100)
    read_noise_e: Float = Field(0.0, ge=0, le=1e4)
    noise_sigma: Float = Field(0.0, ge=0, le=255)
    adc_bits: Int = Field(8, ge=2, le=8)
    jpeg_quality: Int | None = Field(None, ge=1, le=100)


class BoardConfig(_Strict):
    """The board as made (board_shape.py): printed ``scale_error_pct`` % too large, a further
    ``aspect_error_pct`` % in y, and bowed by ``warp_mm`` (x, y) at its centre (mrcal's
    two-parabola warp; positive towards the camera facing the print). Calibrations are given
    the nominal pattern; the ground truth is the physical board."""

    scale_error_pct: Float = Field(0.0, ge=-10, le=10)
    aspect_error_pct: Float = Field(0.0, ge=-10, le=10)
    warp_mm: tuple[Float, Float] = Field((0.0, 0.0))

    @field_validator("warp_mm")
    @classmethod
    def _warp(cls, v):
        if max(abs(x) for x in v) > 100:
            raise ValueError("expected deflections within 100 mm")
        return v


#: Keys of the environment before the imaging model, and where they live now.
_MOVED = {"noise_sigma": "sensor.noise_sigma", "light_direction": "light.direction",
          "ambient": "light.ambient", "blur_sigma_px": "optics.blur_px"}


class EnvironmentConfig(_Strict):
    """How the images are formed (render/imaging.py) and the board as made (``board``):
    ``kind`` names a preset, a situation
    (stereo_bench/environments.py: clean, noisy, studio, office, handheld_low_light,
    paper_noisy), whose values fill every field the file does not give; the resolved
    configuration lists them all."""

    kind: EnvironmentKind = "clean"
    background: Int = Field(110, ge=0, le=255)
    # The print's grey levels under full light: its black squares and its white paper.
    black_level: Int = Field(20, ge=0, le=254)
    white_level: Int = Field(235, ge=1, le=255)
    supersampling: Int = Field(2, ge=1, le=16)
    light: LightConfig = LightConfig()
    optics: OpticsConfig = OpticsConfig()
    motion: MotionConfig = MotionConfig()
    sensor: SensorConfig = SensorConfig()
    board: BoardConfig = BoardConfig()

    @model_validator(mode="after")
    def _levels(self):
        if self.black_level >= self.white_level:
            raise ValueError(f"black_level: {self.black_level}, expected below white_level "
                             f"({self.white_level})")
        return self

    @model_validator(mode="before")
    @classmethod
    def _preset(cls, data):
        from .environments import PRESETS

        if not isinstance(data, dict):
            return data
        for old, new in _MOVED.items():
            if old in data:
                raise ValueError(f"{old}: now environment.{new} (see docs/imaging.md)")
        kind = data.get("kind", "clean")
        preset = PRESETS.get(kind) if isinstance(kind, str) else None
        if preset is None:
            return data  # the kind's own validator names what is expected
        merged = {**preset.settings}
        for key, value in data.items():
            if isinstance(value, dict) and isinstance(merged.get(key), dict):
                merged[key] = {**merged[key], **value}
            else:
                merged[key] = value
        return merged


class RendererConfig(_Strict):
    """Which backend forms the images: ``analytic`` (the package's exact renderer, every part of
    the imaging model) or ``blender`` (Cycles in the worker environment, render/blender/: a
    matte textured plane lit by the environment's light, the lens applied by one exact remap;
    ``samples`` per pixel at most, ``noise_threshold`` Cycles' adaptive sampling (a pixel stops
    once its estimated noise is below it, relative to its value; 0: every pixel takes every
    sample), ``threads`` for Cycles, None: all cores)."""

    kind: Literal["analytic", "blender"] = "analytic"
    samples: Int = Field(64, ge=1, le=4096)
    noise_threshold: float = Field(0.01, ge=0.0, le=1.0)
    threads: Int | None = Field(None, ge=1, le=256)


#: What the Blender backend does not model, as (field, test on the resolved config, why).
_NOT_IN_BLENDER = (
    ("environment.motion", lambda c: c.environment.motion.exposure_ms > 0
     and c.environment.motion.speed_mm_s > 0, "motion blur"),
    ("environment.light.specular", lambda c: c.environment.light.specular > 0,
     "a glossy print (Blinn-Phong)"),
    ("environment.board", lambda c: c.environment.board != BoardConfig(),
     "a board that is not its pattern"),
    ("pattern.two_sided", lambda c: bool(c.pattern.overrides().get("two_sided")),
     "a two-sided board"),
)


class RigConfig(_Strict):
    """A rig file. The cameras are given as a list (``cameras``) or placed by a ``studio``
    layout; a studio is expanded into the list when the file is read, so the resolved
    configuration (the dataset's config.yaml) always lists every camera."""

    name: Name = "rig"
    seed: Int = Field(0, ge=0, lt=2**63)
    cameras: list[CameraConfig] = Field(default_factory=list, max_length=MAX_CAMERAS)
    studio: StudioConfig | None = None
    pattern: PatternConfig
    trajectory: TrajectoryConfig = TrajectoryConfig()
    environment: EnvironmentConfig = EnvironmentConfig()
    calibration: CalibrationConfig = CalibrationConfig()
    renderer: RendererConfig = RendererConfig()

    @model_validator(mode="after")
    def _blender_can_render(self):
        if self.renderer.kind == "blender":
            for field, used, what in _NOT_IN_BLENDER:
                if used(self):
                    raise ValueError(f"{field}: the blender renderer does not model {what}; "
                                     f"use renderer.kind: analytic")
        return self

    @model_validator(mode="after")
    def _cameras(self):
        if self.studio is not None:
            if self.cameras:
                raise ValueError("cameras: give either a list of cameras or a studio, not both")
            cams = []
            for entry in self.studio.cameras():
                try:
                    cams.append(CameraConfig.model_validate(entry))
                except ValidationError as e:
                    lines = describe(e, "", "camera").split("\n")[1:]
                    raise ValueError(f"studio: camera {entry['name']!r}: " + "; ".join(
                        line.strip().removeprefix("(top level): ") for line in lines))
            # Frozen model: the expansion replaces the studio once, at validation.
            object.__setattr__(self, "cameras", cams)
            object.__setattr__(self, "studio", None)
        if not self.cameras:
            raise ValueError("cameras: expected at least one camera (or a studio)")
        names = [c.name for c in self.cameras]
        if len(set(names)) != len(names):
            raise ValueError(f"cameras: names must be unique, got {names}")
        frames = self.trajectory.frames_for(len(self.cameras))
        total = sum(c.width * c.height for c in self.cameras) * frames
        if total > 4e11:
            raise ValueError(f"trajectory.frames: {frames} frames of these "
                             f"cameras are {total:.2g} pixels; expected at most 4e11")
        if frames > MAX_FRAMES:
            raise ValueError(f"trajectory.closeups: {frames} frames in all; expected at most "
                             f"{MAX_FRAMES}")
        views, tr = self.calibration.intrinsics_views, self.trajectory
        if views != "all" and tr.kind != "session":
            raise ValueError(f"calibration.intrinsics_views: {views!r} names frames of a "
                             f"session; this trajectory is a {tr.kind} (use 'all')")
        if views == "closeups" and tr.closeups == 0:
            raise ValueError("calibration.intrinsics_views: 'closeups' needs close-up frames; "
                             "set trajectory.closeups above 0")
        return self

    def cameras_true(self) -> list[Camera]:
        return [c.camera() for c in self.cameras]

    def time_offsets_ms(self) -> np.ndarray:
        """(C,) each camera's clock offset, ms (cameras[i].time_offset_ms)."""
        return np.array([c.time_offset_ms for c in self.cameras])


def describe(err: ValidationError, source: str, what: str = "rig configuration") -> str:
    """A pydantic error as lines naming ``source`` and each field with what was expected."""
    lines = [f"{source}: invalid {what}"]
    for e in err.errors():
        path = ".".join(str(p) for p in e["loc"]) or "(top level)"
        msg = e["msg"]
        if e["type"] == "extra_forbidden":
            msg = "unknown key (check its spelling; see docs/rig_format.md)"
        elif e["type"] == "missing":
            msg = "missing required field"
        elif e["type"] == "value_error":
            msg = msg.removeprefix("Value error, ")
            if msg.startswith(f"{path}."):  # the message names the field inside this one
                lines.append(f"  {msg}")
                continue
        else:
            shown = repr(e.get("input"))
            msg += f", got {shown if len(shown) <= 60 else shown[:57] + '...'}"
        lines.append(f"  {path}: {msg}")
    return "\n".join(lines)


def parse_rig(data: dict, source: str = "<rig>") -> RigConfig:
    """Validate a rig given as a dict; raises ConfigError naming ``source`` and the fields."""
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a mapping at the top level, got "
                          f"{type(data).__name__}")
    try:
        return RigConfig.model_validate(data)
    except ValidationError as e:
        raise ConfigError(describe(e, source)) from None


def load_rig(path) -> RigConfig:
    return parse_rig(load_yaml(path, "rig file"), str(path))
