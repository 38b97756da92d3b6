"""A sweep's grid file: rig files crossed with axes over any rig-file field, validated and
expanded into named configurations before anything runs (``parse_grid``, ``load_grid``).
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
import re
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from ..config.bounds import ConfigError
from ..config.schema import EnvironmentKind, Int, Name, PatternKind, RigConfig, describe, load_rig
from ..config.yaml_reader import load_yaml
from ..core.files import is_safe_name


#: A grid beyond this many configurations is refused (a typo in an axis would start days).
MAX_CONFIGURATIONS = 1000


#: Seeds per configuration when a grid says none and any configuration is noisy.
NOISY_TRIALS = 10


_SEGMENT = re.compile(r"^(\*|-?[0-9]+|[A-Za-z_][A-Za-z0-9_]*)$")


class GridConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    name: Name = "grid"
    rigs: list[str] = Field(min_length=1, max_length=100)
    patterns: list[PatternKind] | None = Field(None, min_length=1)
    environments: list[EnvironmentKind] | None = Field(None, min_length=1)
    axes: dict[str, list[Any]] = Field(default_factory=dict)
    methods: list[str] = Field(["zhang", "tsai", "bouguet", "opencv"], min_length=1)
    trials: Int | None = Field(None, ge=1, le=1000)
    frames: Int | None = Field(None, gt=0, le=10_000)

    @field_validator("methods")
    @classmethod
    def _known(cls, v):
        from ..calibrate import check_methods

        check_methods(v)  # any BASE-MODEL variant too; the error says what is accepted
        _once(v)
        return v

    @field_validator("patterns", "environments")
    @classmethod
    def _distinct(cls, v):
        return v if v is None else _once(v)

    @field_validator("axes")
    @classmethod
    def _axes(cls, v):
        for path, values in v.items():
            parts = path.split(".")
            bad = [p for p in parts if not _SEGMENT.match(p)]
            if bad or not path:
                raise ValueError(f"axes.{path}: expected a dotted field path such as "
                                 f"environment.noise_sigma or cameras.*.dist.0 (segments: "
                                 f"names, list indices or *), got segment(s) {bad}")
            if parts[0] == "name":
                raise ValueError(f"axes.{path}: the sweep names each configuration itself")
            if not values:
                raise ValueError(f"axes.{path}: expected at least one value")
            if len(values) > MAX_CONFIGURATIONS:
                raise ValueError(f"axes.{path}: {len(values)} values; expected at most "
                                 f"{MAX_CONFIGURATIONS}")
            for value in values:
                if not _plain(value):
                    raise ValueError(f"axes.{path}: value {value!r}: expected a number, a string, "
                                     f"true/false, null or a list of them")
            _once(values, f"axes.{path}: ")
        return v


def _once(values: list, prefix: str = "") -> list:
    """``values`` unless one is listed twice (two configurations would share one folder)."""
    keys = [value_key(v) for v in values]
    twice = [v for v, k in zip(values, keys) if keys.count(k) > 1]
    if twice:
        raise ValueError(f"{prefix}listed twice: {sorted({json.dumps(v) for v in twice})}")
    return values


def _plain(value, depth: int = 0) -> bool:
    if value is None or isinstance(value, (bool, int, str)):
        return True
    if isinstance(value, float):
        return math.isfinite(value)
    return isinstance(value, list) and depth < 2 and all(_plain(x, depth + 1) for x in value)


def value_key(value) -> str:
    """A value as a hashable, order-exact key (1 and 1.0 stay apart from "1")."""
    return json.dumps(value, sort_keys=True)


@dataclass(frozen=True)
class Axis:
    """One field the grid varies: its dotted path in the rig file, its values, and the short
    label that names it in folder names (the shortest tail of the path that tells the axes
    apart, e.g. ``noise_sigma``)."""

    path: str
    values: tuple
    label: str

    @property
    def numeric(self) -> bool:
        return all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in self.values)

    def to_dict(self) -> dict:
        return {"path": self.path, "label": self.label, "values": list(self.values),
                "scale": "numeric" if self.numeric else "categorical"}


@dataclass(frozen=True)
class Configuration:
    """One cell of the grid: its folder name, rig file, axis values and validated rig."""

    name: str
    rig: str        # the rig file's stem
    rig_file: str   # as the grid names it
    axes: dict      # path -> value, every axis of the grid
    config: RigConfig

    def to_dict(self) -> dict:
        return {"name": self.name, "rig": self.rig, "rig_file": self.rig_file,
                "pattern": self.config.pattern.kind, "environment": self.config.environment.kind,
                "axes": self.axes, "cameras": [c.name for c in self.config.cameras]}


@dataclass(frozen=True)
class Sweep:
    """A loaded grid: everything ``run_sweep`` needs, all validated."""

    grid: GridConfig
    source: str
    axes: list[Axis]
    configurations: list[Configuration]
    trials: int
    trials_reason: str


def _labels(paths: list[str]) -> dict[str, str]:
    """Per path the shortest tail of its segments that no other path shares, starting at a
    field name (``cameras.*.dist.0`` -> ``dist.0``); ``*`` reads ``all``."""
    def tail(path, n):
        parts = [("all" if p == "*" else p) for p in path.split(".")]
        # Grow past trailing indices, so that a label starts with a field's name.
        while n < len(parts) and not parts[-n][0].isalpha():
            n += 1
        return ".".join(parts[-n:])

    out = {}
    for path in paths:
        n = 1
        while any(tail(path, n) == tail(o, n) for o in paths if o != path) \
                and n < len(path.split(".")):
            n += 1
        out[path] = tail(path, n)
    return out


def value_token(value) -> str:
    """A value as a piece of a folder name: 4, 0.5, true, charuco, 1_1 for [1, 1]."""
    if isinstance(value, bool) or value is None:
        return json.dumps(value)
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        short = format(value, "g")
        return short if float(short) == value else repr(value)
    if isinstance(value, list):
        return "_".join(value_token(v) for v in value) or "empty"
    return re.sub(r"[^A-Za-z0-9_.-]", "_", str(value)) or "empty"


def _name(rig: str, pattern: str, environment: str, named: list[tuple[str, Any]]) -> str:
    name = "_".join([rig, pattern, environment] + [f"{label}-{value_token(v)}" for label, v in named])
    if not is_safe_name(name):
        # Too long (or a rig file name that is no safe name): a readable head and a hash of
        # the whole, so that the folder stays unique.
        name = re.sub(r"[^A-Za-z0-9_.-]", "_", name)
        digest = hashlib.sha256(name.encode()).hexdigest()[:8]
        name = f"{name[:55].rstrip('.')}-{digest}"
    return name


class _PathError(ValueError):
    """A path that is not in the rig: what is wrong, and what is there instead."""

    def __init__(self, what: str, there: str = ""):
        super().__init__(what)
        self.what, self.there = what, there


def _model_at(trail: list[str]):
    """The pydantic model of the rig file's section at ``trail`` (None: not a section)."""
    model = RigConfig
    for seg in trail:
        if seg == "*" or seg.lstrip("-").isdigit():
            continue  # a list's entry: the list's annotation gave its model already
        field = model.model_fields.get(seg) if model else None
        if field is None:
            return None
        model = _model_in(field.annotation)
    return model


def _model_in(annotation):
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in typing.get_args(annotation):
        found = _model_in(arg)
        if found is not None:
            return found
    return None


def set_path(data: dict, path: str, value) -> list[tuple]:
    """Set ``value`` at the dotted ``path`` of a rig's resolved dict, in place; ``*`` sets every
    entry of a list and an integer indexes one. Returns the concrete paths set (tuples, as
    pydantic names fields). Raises ValueError when the path is not in ``data``: a missing key
    is accepted only in a section whose model takes keys of its own (the pattern's fields,
    which depend on its kind) and a null section only when the rig file's model has one there
    (it is started empty, its other fields at their defaults)."""
    parts = path.split(".")
    done = []

    def walk(node, i, trail):
        seg, last, here = parts[i], i == len(parts) - 1, ".".join(map(str, trail))
        if isinstance(node, list):
            if seg == "*":
                indices = range(len(node))
            elif seg.lstrip("-").isdigit() and -len(node) <= int(seg) < len(node):
                indices = [int(seg) % len(node)]
            else:
                raise _PathError(f"{here} is a list of {len(node)}: expected an index "
                                 f"0..{len(node) - 1} or *, got {seg!r}")
            steps = [(k, k) for k in indices]
        elif isinstance(node, dict):
            if seg not in node or (node[seg] is None and not last):
                model = _model_at([str(t) for t in trail] + ([seg] if seg in node else []))
                if seg in node and model is not None:
                    node[seg] = {}  # a section the rig file leaves out
                elif seg in node:
                    raise _PathError(f"{here + '.' if here else ''}{seg} is null, not a "
                                     f"section with fields")
                elif not (last and model is not None and model.model_config.get("extra")
                          == "allow"):
                    what = f"fields of {here}" if here else "top-level fields"
                    raise _PathError("no such field", f"{what}: {', '.join(node)}")
            steps = [(seg, seg)]
        else:
            raise _PathError(f"{here} is {json.dumps(node)}, not a section with fields")
        for key, shown in steps:
            if last:
                node[key] = copy.deepcopy(value)
                done.append(tuple(trail) + (shown,))
            else:
                walk(node[key], i + 1, trail + [shown])

    walk(data, 0, [])
    return done


def _noisy(configs: list[Configuration]) -> str | None:
    """Why trials differ in this grid (so several are needed), or None: the seed draws the
    sensor's noise (and a session's walk), so a configuration with a noisy sensor needs seeds."""
    noisy = [c.name for c in configs
             if c.config.environment.sensor.noise_sigma > 0
             or c.config.environment.sensor.full_well_e is not None]
    if noisy:
        return f"{len(noisy)} configuration(s) render with sensor noise (e.g. {noisy[0]})"
    sessions = [c.name for c in configs if c.config.trajectory.kind == "session"]
    if sessions:
        return f"{len(sessions)} configuration(s) walk a session drawn from the seed"
    return None


def load_grid(path) -> Sweep:
    """The grid and its configurations (rig files crossed with every axis), all validated
    before anything runs; configuration names must be unique."""
    path = Path(path)
    return parse_grid(load_yaml(path, "grid file"), path, rig_reader(path))


def rig_reader(path: Path):
    """:func:`parse_grid`'s reader of the rig files a grid file at ``path`` lists (relative
    to it)."""
    def rig(rig_file: str) -> tuple[dict, dict]:
        base = load_rig(path.parent / rig_file).model_dump(mode="json")
        return base, load_yaml(path.parent / rig_file)  # read again: what the file itself writes
    return rig


def parse_grid(data, path: Path, rig) -> Sweep:
    """:func:`load_grid` of a grid file's ``data``, messages naming ``path``; ``rig(rig_file)``
    gives a listed rig file's resolved data and the data the file itself writes (so that a
    grid whose rig is not on disk yet, the web app's, is validated before anything runs)."""
    try:
        grid = GridConfig.model_validate(data if isinstance(data, dict) else {"": data})
    except ValidationError as e:
        raise ConfigError(describe(e, str(path), "grid file")) from None
    axes_given = dict(grid.axes)
    for key, field in (("patterns", "pattern.kind"), ("environments", "environment.kind"),
                       ("frames", "trajectory.frames")):
        value = getattr(grid, key)
        if value is None:
            continue
        if field in axes_given:
            raise ConfigError(f"{path}: {key} and axes.{field} say the same; give one")
        axes_given[field] = value if isinstance(value, list) else [value]
    # pattern.kind first: setting it drops the base rig's other pattern fields, which must not
    # take a pattern.* axis with them.
    order = sorted(axes_given, key=lambda p: p != "pattern.kind")
    labels = _labels([p for p in order if p not in ("pattern.kind", "environment.kind")])
    axes = [Axis(p, tuple(axes_given[p]), labels.get(p, p.split(".")[0])) for p in order]
    count = len(grid.rigs) * math.prod(len(a.values) for a in axes)
    if count > MAX_CONFIGURATIONS:
        raise ConfigError(f"{path}: {count} configurations (rigs x every axis's values); "
                          f"expected at most {MAX_CONFIGURATIONS}")
    configs = []
    for i, rig_file in enumerate(grid.rigs):
        try:
            base, raw = rig(rig_file)
        except ConfigError as e:
            raise ConfigError(f"{path}: rigs.{i}: {e}") from None
        for combo in _combinations(axes):
            configs.append(_configuration(path, rig_file, base, raw, axes, combo))
    names = [c.name for c in configs]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise ConfigError(f"{path}: configurations {twice} would run twice into one folder (a "
                          f"rig file listed twice, two with the same file name, or axis "
                          f"values that read the same in a folder name)")
    reason = _noisy(configs)
    if grid.trials is not None:
        trials, why = grid.trials, "trials in the grid file"
    elif reason:
        trials, why = NOISY_TRIALS, f"default for a noisy grid: {reason}"
    else:
        trials, why = 1, ("default for a clean grid (a clean spring trajectory renders the "
                          "same images for every seed)")
    return Sweep(grid, str(path), axes, configs, trials, why)


def _combinations(axes: list[Axis]) -> list[tuple]:
    combos = [()]
    for axis in axes:
        combos = [c + (v,) for c in combos for v in axis.values]
    return combos


def _configuration(source: Path, rig_file: str, base: dict, raw: dict, axes: list[Axis],
                   combo: tuple) -> Configuration:
    d = copy.deepcopy(base)
    concrete, values = {}, dict(zip((a.path for a in axes), combo))
    stem = Path(rig_file).stem
    # A section's kind selects its fields' meaning and defaults (a board's geometry, an
    # environment's preset): a new kind restarts the section from what the rig file itself
    # wrote there (for the pattern nothing: its fields describe the old board), and the rig is
    # resolved again before the other axes are set into it.
    restarted = False
    for axis, value in zip(axes, combo):
        section = axis.path.split(".")[0]
        if axis.path == f"{section}.kind" and isinstance(d.get(section), dict) \
                and d[section].get("kind") != value:
            own = raw.get(section) if section != "pattern" else None
            d[section] = {**(own if isinstance(own, dict) else {}), "kind": value}
            concrete[axis.path] = [(section, "kind")]
            restarted = True
    if restarted:
        try:
            d = RigConfig.model_validate(d).model_dump(mode="json")
        except ValidationError as e:
            raise ConfigError(_refusal(e, source, rig_file, axes, values, concrete,
                                       stem)) from None
    for axis, value in zip(axes, combo):
        try:
            concrete[axis.path] = set_path(d, axis.path, value)
        except _PathError as e:
            raise ConfigError(f"{source}: axes.{axis.path}: {e.what} in rig file {rig_file}"
                              + (f" ({e.there})" if e.there else "")) from None
    named = [(a.label, v) for a, v in zip(axes, combo)
             if len(a.values) > 1 and a.path not in ("pattern.kind", "environment.kind")]
    d["name"] = _name(stem, str(d["pattern"]["kind"]), str(d["environment"]["kind"]), named)
    try:
        cfg = RigConfig.model_validate(d)
    except ValidationError as e:
        raise ConfigError(_refusal(e, source, rig_file, axes, values, concrete, d["name"])
                          ) from None
    return Configuration(cfg.name, stem, rig_file, values, cfg)


def _refusal(e: ValidationError, source, rig_file, axes, values, concrete, name) -> str:
    """The validation error of one configuration, told against the axis whose value the rig
    refused when one of its fields is named, else against the whole configuration."""
    for err in e.errors():
        loc = tuple(str(p) for p in err["loc"])
        for axis in axes:
            for p in concrete.get(axis.path, []):
                p = tuple(map(str, p))
                if p[:len(loc)] == loc or loc[:len(p)] == p:
                    return describe(e, f"{source}: axes.{axis.path}: value "
                                       f"{json.dumps(values[axis.path])} in rig file {rig_file}")
    said = ", ".join(f"{k} = {json.dumps(v)}" for k, v in values.items())
    return describe(e, f"{source}: configuration {name} (rig file {rig_file}"
                       + (f"; {said})" if said else ")"))
