"""The run directory: every path under ``RUN/``, strict and atomic JSON, stage fingerprints and
the lock that gives a run directory one writer at a time.

Layout (the one place it is spelled out; docs/run_directory.md describes it for users)::

    RUN/.lock                                  held while a command writes into RUN
    RUN/results.json, RUN/report.md, RUN/report.html, RUN/plots/*.png
    RUN/trials/seed_<s>/dataset/               a rendered dataset (layout: DatasetPaths)
    RUN/trials/seed_<s>/detections/<camera>.npz, detections/done.json
    RUN/trials/seed_<s>/calibrations/<method>/<camera>.json | .yaml | _views.npz
    RUN/trials/seed_<s>/metrics.json
    RUN/trials/seed_<s>/rig/<method>.json

A real capture's folder (``CapturePaths``, written by ``stereo-bench calibrate-images``) is one
trial's layout at its top, beside the run's files::

    OUT/.lock, OUT/results.json, OUT/report.md, OUT/report.html, OUT/plots/*.png
    OUT/frames.json                            the images of each frame, per camera
    OUT/detections/..., OUT/calibrations/..., OUT/rig/<method>.json   (as a trial's)
    OUT/export/<format>/<method>/...           exchange files (stereo-bench export)

Every stage ends by writing one JSON marker (manifest.json, detections/done.json, metrics.json,
rig/<method>.json) that carries the fingerprint of exactly what the stage depends on. A stage is
reused only when its marker is readable, its fingerprint matches and the output files it lists
are the ones it wrote (their digests, :func:`with_outputs`); a missing, torn or stale marker, or
an output changed since, means the stage is redone, and :class:`Notes` tells the user which and
why.

JSON is written strictly: NaN and infinities become ``null``, and in a mapping a sibling key
``<key>_reason`` says what the value was ("not a number" or "infinite"), so every file parses with
a browser's ``JSON.parse``. Files are written to a temporary name and moved into place with
``os.replace``, so a kill or a full disk never leaves a torn file under its real name.
"""

from __future__ import annotations

import errno
import fcntl
import hashlib
import json
import os
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from ..core.files import UnreadableFileError, is_safe_name, read_json, strict

#: Bumped when the meaning of any stage's output changes, so older markers are not reused.
FORMAT_VERSION = 3


# ----------------------------------------------------------------------------------------------
# Strict, atomic files
# ----------------------------------------------------------------------------------------------


# ----------------------------------------------------------------------------------------------
# Fingerprints and markers
# ----------------------------------------------------------------------------------------------

def fingerprint(*parts) -> str:
    """A short hash of JSON-able ``parts`` (with the package's format and version), so that a
    changed input, option or code format gives another fingerprint."""
    from .. import __version__

    text = json.dumps(strict([FORMAT_VERSION, __version__, *parts]), sort_keys=True,
                      separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:20]


class Notes:
    """What a run tells its user besides its results: redone stages and their reason,
    warnings about the data. Kept in results.json and printed by the commands."""

    def __init__(self):
        self.items: list[str] = []
        # Once a stage is redone, every later stage is redone too (its inputs changed): one
        # note for the first is enough.
        self.redone = False

    def add(self, text: str) -> None:
        if text not in self.items:
            self.items.append(text)

    def stage_redone(self, text: str) -> None:
        if not self.redone:
            self.add(text + " (and every later stage)")
        self.redone = True


def reusable(path: Path, expected: str, notes: Notes | None, stage: str):
    """The marker at ``path`` if it is readable and was written for fingerprint ``expected``;
    otherwise None, with a note saying why the stage is redone."""
    if not path.is_file():
        return None
    try:
        marker = read_json(path)
    except UnreadableFileError as e:
        if notes:
            notes.stage_redone(f"{e}; redoing the {stage} stage")
        return None
    found = marker.get("fingerprint") if isinstance(marker, dict) else None
    if found != expected:
        if notes:
            notes.stage_redone(f"{path}: written for other inputs (the configuration, the "
                               f"methods or the code changed); redoing the {stage} stage")
        return None
    if changed := changed_output(path, marker):
        if notes:
            notes.stage_redone(f"{changed}; redoing the {stage} stage")
        return None
    return stripped(marker)


def _digest(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _content_digest(marker: dict) -> str:
    """The digest of a marker's own content (without it), as written: strict JSON, sorted."""
    body = {k: v for k, v in strict(marker).items() if k != "content"}
    return hashlib.sha256(json.dumps(body, sort_keys=True).encode()).hexdigest()


def with_outputs(marker: dict, path: Path, outputs=()) -> dict:
    """The marker to be written at ``path`` with the digest of each of its stage's output files
    (named relative to the marker's folder) and of its own content, so that an output or the
    marker's figures edited, torn or replaced after the stage are not reused as if the stage
    had made them (:func:`changed_output`)."""
    folder = Path(path).parent
    marker = {**marker, "outputs": {Path(p).relative_to(folder).as_posix(): _digest(Path(p))
                                    for p in sorted(outputs)}}
    return {**marker, "content": _content_digest(marker)}


def stripped(marker: dict) -> dict:
    """A marker without the digests :func:`with_outputs` added."""
    return {k: v for k, v in marker.items() if k not in ("outputs", "content")}


def changed_output(path: Path, marker: dict) -> str | None:
    """Why the outputs a marker lists are not the ones its stage wrote (a file missing, or of
    other content), or None. A marker written before outputs were listed lists none."""
    if "content" in marker and marker["content"] != _content_digest(marker):
        return f"{path}: changed since its stage wrote it"
    outputs = marker.get("outputs", {})
    if not isinstance(outputs, dict):
        return f"{path}: its 'outputs' are not a mapping of files to digests"
    folder = Path(path).parent
    for name, digest in outputs.items():
        file = folder / str(name)
        inside = all(is_safe_name(part) for part in str(name).split("/"))
        if not inside or not file.is_file():
            return f"{file}: missing since its stage wrote it"
        if _digest(file) != digest:
            return f"{file}: changed since its stage wrote it"
    return None


# ----------------------------------------------------------------------------------------------
# Paths
# ----------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class DatasetPaths:
    """The files of a dataset (docs/dataset_format.md); ``manifest`` is written last."""

    root: Path

    @property
    def manifest(self) -> Path:
        return self.root / "manifest.json"

    @property
    def config(self) -> Path:
        return self.root / "config.yaml"

    @property
    def texture(self) -> Path:
        return self.root / "pattern.png"

    @property
    def timing(self) -> Path:
        return self.root / "timing.json"

    @property
    def ground_truth(self) -> Path:
        return self.root / "ground_truth"

    @property
    def cameras(self) -> Path:
        return self.ground_truth / "cameras.json"

    def array(self, name: str) -> Path:
        return self.ground_truth / f"{name}.npy"

    def images(self, camera: str) -> Path:
        return self.root / "images" / camera

    def image(self, camera: str, frame: int) -> Path:
        return self.images(camera) / f"{frame:06d}.png"

    @property
    def blender(self) -> Path:
        """The Blender backend's inputs and scratch files (its texture, the pinhole frame)."""
        return self.root / "blender"


@dataclass(frozen=True)
class TrialPaths:
    """The files of one trial (one seed) of a run."""

    root: Path

    @property
    def dataset(self) -> DatasetPaths:
        return DatasetPaths(self.root / "dataset")

    @property
    def detections(self) -> Path:
        return self.root / "detections"

    def detection(self, camera: str) -> Path:
        return self.detections / f"{camera}.npz"

    @property
    def detections_done(self) -> Path:
        return self.detections / "done.json"

    @property
    def all_calibrations(self) -> Path:
        return self.root / "calibrations"

    def calibrations(self, method: str) -> Path:
        return self.all_calibrations / method

    def calibration(self, method: str, camera: str) -> Path:
        return self.calibrations(method) / f"{camera}.json"

    def calibration_yaml(self, method: str, camera: str) -> Path:
        return self.calibrations(method) / f"{camera}.yaml"

    def views(self, method: str, camera: str) -> Path:
        return self.calibrations(method) / f"{camera}_views.npz"

    @property
    def metrics(self) -> Path:
        return self.root / "metrics.json"

    @property
    def rigs(self) -> Path:
        return self.root / "rig"

    def rig(self, method: str) -> Path:
        return self.rigs / f"{method}.json"

    def tool(self, name: str) -> Path:
        """The files another calibration tool wrote (``stereo-bench compare-tools``)."""
        return self.root / "tools" / name

    def tool_score(self, name: str) -> Path:
        """That tool's calibration scored against the truth, and its uncertainty's check."""
        return self.root / "tools" / f"{name}.json"


@dataclass(frozen=True)
class RunPaths:
    """The files of a run directory (one configuration, all its trials)."""

    root: Path

    def trial(self, seed: int) -> TrialPaths:
        return TrialPaths(self.root / "trials" / f"seed_{seed}")

    @property
    def trials(self) -> Path:
        return self.root / "trials"

    def trial_seeds(self) -> list[int]:
        seeds = []
        for p in self.trials.glob("seed_*"):
            tail = p.name[len("seed_"):]
            if p.is_dir() and tail.lstrip("-").isdigit():
                seeds.append(int(tail))
        return sorted(seeds)

    @property
    def results(self) -> Path:
        return self.root / "results.json"

    @property
    def report(self) -> Path:
        return self.root / "report.md"

    @property
    def html(self) -> Path:
        """The self-contained page of the report (report/html.py)."""
        return self.root / "report.html"

    @property
    def plots(self) -> Path:
        return self.root / "plots"

    @property
    def lock_file(self) -> Path:
        return self.root / ".lock"


@dataclass(frozen=True)
class CapturePaths:
    """The files of a real capture's calibration (module notes)."""

    root: Path

    def __post_init__(self):
        object.__setattr__(self, "root", Path(self.root))

    @property
    def trial(self) -> TrialPaths:
        return TrialPaths(self.root)

    @property
    def frames(self) -> Path:
        return self.root / "frames.json"

    @property
    def results(self) -> Path:
        return RunPaths(self.root).results

    @property
    def report(self) -> Path:
        return RunPaths(self.root).report

    @property
    def html(self) -> Path:
        return RunPaths(self.root).html

    @property
    def plots(self) -> Path:
        return RunPaths(self.root).plots

    def export(self, fmt: str, method: str) -> Path:
        return self.root / "export" / fmt / method


def prepare_output(out, what: str = "--out") -> Path:
    """Create the output folder ``out`` (refusing a path that is a file)."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"{what}: {out} exists and is not a directory")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ValueError(f"{what}: cannot create {out} ({e.strerror})") from None
    return out


class RunLockedError(ValueError):
    """Another process is writing into the same run directory."""


@contextmanager
def locked(out, what: str = "--out"):
    """Hold RUN/.lock for the duration: a second command writing into the same folder is refused
    at once, naming the folder (it would otherwise mix its results with the first one's)."""
    root = prepare_output(out, what)
    key = root.resolve()
    if key in _HELD:  # this process holds it already (the command around a library call)
        yield root
        return
    path = RunPaths(root).lock_file
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            if e.errno not in (errno.EAGAIN, errno.EACCES):
                raise
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "another process"
            raise RunLockedError(f"{root}: another run is writing into this folder (pid "
                                 f"{holder}); wait for it to finish or choose another {what}"
                                 ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, str(os.getpid()).encode(), 0)
        _HELD.add(key)
        try:
            yield root
        finally:
            _HELD.discard(key)
    finally:
        os.close(fd)  # closing the descriptor releases the lock


_HELD: set[Path] = set()
