"""Rig YAML files: the validated description of cameras, pattern, trajectory and environment.

Every key is checked by pydantic: an unknown key, a missing field or a wrong type becomes a
``ConfigError`` whose message names the file, the field path and what was expected.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from .camera import Camera, look_at_rotation, matrix_to_rodrigues


class ConfigError(ValueError):
    """A rig file that cannot be used; the message names the file and the field."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class CameraConfig(_Strict):
    """One camera: intrinsics, OpenCV distortion and where it sits in the world (mm)."""

    name: str
    width: int = Field(gt=0)
    height: int = Field(gt=0)
    fx: float = Field(gt=0)
    fy: float = Field(gt=0)
    cx: float
    cy: float
    skew: float = 0.0
    dist: list[float] = Field(default_factory=lambda: [0.0] * 8,
                              description="[k1, k2, p1, p2, k3, k4, k5, k6] (OpenCV order)")
    position_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    look_at_mm: tuple[float, float, float] = (0.0, 0.0, 1000.0)
    up: tuple[float, float, float] = (0.0, -1.0, 0.0)

    @field_validator("dist")
    @classmethod
    def _dist_len(cls, v):
        if not 4 <= len(v) <= 8:
            raise ValueError("expected 4 to 8 coefficients [k1, k2, p1, p2, k3, k4, k5, k6]")
        return list(v) + [0.0] * (8 - len(v))

    def camera(self) -> Camera:
        R = look_at_rotation(np.array(self.position_mm), np.array(self.look_at_mm),
                             np.array(self.up))
        t = -R @ np.array(self.position_mm, dtype=np.float64)
        return Camera(self.name, self.width, self.height, self.fx, self.fy, self.cx, self.cy,
                      self.skew, np.array(self.dist), matrix_to_rodrigues(R), t)


class PatternConfig(_Strict):
    """The board: a kind plus optional overrides of its geometry (see stereo_bench.patterns)."""

    model_config = ConfigDict(extra="allow", frozen=True)
    kind: Literal["checkerboard", "symmetric_circles", "asymmetric_circles", "charuco"]

    def overrides(self) -> dict:
        return dict(self.model_extra or {})


class TrajectoryConfig(_Strict):
    """The paper's conical spring: a helix around the rig's viewing axis whose radius grows
    linearly with depth; the board centre always faces the rig, tilted by up to ``tilt_deg``."""

    frames: int = Field(127, gt=0)
    # None: chosen from the board size and the narrowest camera's field of view (rig.py).
    depth_mm: tuple[float, float] | None = None
    radius_mm: tuple[float, float] | None = None
    turns: float = Field(4.0, gt=0)
    tilt_deg: float = Field(30.0, ge=0, lt=80)
    roll_deg: float = Field(20.0, ge=0, le=180)

    @model_validator(mode="after")
    def _ranges(self):
        if self.depth_mm is not None and not 0 < self.depth_mm[0] <= self.depth_mm[1]:
            raise ValueError("depth_mm: expected 0 < near <= far")
        if self.radius_mm is not None and min(self.radius_mm) < 0:
            raise ValueError("radius_mm: expected non-negative radii")
        return self


class EnvironmentConfig(_Strict):
    """Lighting and sensor: ``clean`` (uniform light, no noise) or ``noisy`` (directional light
    shading plus additive Gaussian noise of ``noise_sigma`` grey levels)."""

    kind: Literal["clean", "noisy"] = "clean"
    noise_sigma: float = Field(6.0, ge=0)
    light_direction: tuple[float, float, float] = (0.6, -0.5, 1.0)
    ambient: float = Field(0.35, ge=0, le=1)
    blur_sigma_px: float = Field(0.0, ge=0)
    background: int = Field(110, ge=0, le=255)
    supersampling: int = Field(2, ge=1, le=16)


class RigConfig(_Strict):
    name: str = "rig"
    seed: int = 0
    cameras: list[CameraConfig] = Field(min_length=1)
    pattern: PatternConfig
    trajectory: TrajectoryConfig = TrajectoryConfig()
    environment: EnvironmentConfig = EnvironmentConfig()

    @model_validator(mode="after")
    def _unique_names(self):
        names = [c.name for c in self.cameras]
        if len(set(names)) != len(names):
            raise ValueError(f"cameras: names must be unique, got {names}")
        return self

    def cameras_true(self) -> list[Camera]:
        return [c.camera() for c in self.cameras]


def _describe(err: ValidationError, source: str) -> str:
    lines = [f"{source}: invalid rig configuration"]
    for e in err.errors():
        path = ".".join(str(p) for p in e["loc"]) or "(top level)"
        msg = e["msg"]
        if e["type"] == "extra_forbidden":
            msg = "unknown key (check its spelling; see docs/rig_format.md)"
        elif e["type"] == "missing":
            msg = "missing required field"
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
        raise ConfigError(_describe(e, source)) from None


def load_rig(path) -> RigConfig:
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except OSError as e:
        raise ConfigError(f"{path}: cannot read rig file ({e.strerror})") from None
    except yaml.YAMLError as e:
        raise ConfigError(f"{path}: not valid YAML ({e})") from None
    return parse_rig(data, str(path))
