"""Calibrations that come from, or go to, another tool.

* ``estimates_of``: the estimates a run directory or a real capture holds, as rigs (``stereo-bench
  export`` writes them in any format of ``stereo_bench.io``).
* ``as_rig_of``: a calibration read from another tool's file (``io.load``), its cameras matched
  to a rig's by name (or, when the names differ, by order) and re-expressed as cam_from_cam0, the
  form the suite's rigs take.
* ``score_calibration``: such a calibration scored against a rendered dataset's truth, exactly
  as the suite scores its own methods (``stereo-bench score``): per camera the projection
  difference, parameter errors and validity; for a rig, RMSE_cal through the suite's own
  detections of the dataset and the rig's errors. ``pose-eval --calibration`` uses
  ``as_rig_of`` to triangulate a body through the same cameras.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .. import io
from ..core.camera import Camera
from ..core.poses import matrix_to_rodrigues
from ..scene.dataset import Dataset
from ..evaluate.stage import load_or_detect
from ..evaluate.metrics import parameter_errors, projection_difference, validity
from .pipeline import board_geometry, score_rig, triangulated_board
from ..io.rundir import CapturePaths, Notes, RunPaths, TrialPaths, changed_output
from ..core.files import read_json
from ..core.poses import cam_from_cam0


def rebased(cameras: list[Camera]) -> list[Camera]:
    """The cameras with cam_from_world = cam_from_cam0: camera 0 at the identity."""
    R, t = cam_from_cam0(cameras)
    return [c.with_params(rvec=matrix_to_rodrigues(R[i]), tvec=t[i])
            for i, c in enumerate(cameras)]


def as_rig_of(estimate: list[Camera], names: list[str], source: str) -> tuple[list[Camera], str]:
    """``estimate`` (from ``source``) in the order of the cameras ``names``, rebased on the first;
    and how they were matched. By name when every name is in the file; by order when the file
    has as many cameras under other names (the note says so); a ValueError naming both lists
    otherwise."""
    by_name = {c.name: c for c in estimate}
    if set(names) <= set(by_name):
        chosen, how = [by_name[n] for n in names], "matched by name"
    elif len(estimate) == len(names):
        chosen = [c.with_params(name=n) for c, n in zip(estimate, names)]
        how = (f"matched by order: {', '.join(f'{c.name} as {n}' for c, n in zip(estimate, names))}")
    else:
        raise ValueError(f"{source}: cameras {[c.name for c in estimate]} cannot be matched to "
                         f"{names} (expected the same names, or as many cameras in the same "
                         f"order)")
    try:
        return (rebased(chosen) if len(chosen) > 1 else chosen), how
    except ValueError as e:  # a pose the file holds but no rotation matrix keeps finite
        raise ValueError(f"{source}: {e}") from None


def _rig_file_cameras(path: Path) -> list[Camera] | str:
    entry = read_json(path)
    if not isinstance(entry, dict) or "method" not in entry:
        raise ValueError(f"{path}: not a rig calibration written by stereo-bench")
    if changed := changed_output(path, entry):
        raise ValueError(f"{changed}; run the command that wrote it again")
    if "error" in entry:
        return str(entry["error"])
    if not isinstance(entry.get("cameras"), list) or not all(
            isinstance(d, dict) for d in entry["cameras"]):
        raise ValueError(f"{path}: expected 'cameras', a list of cameras, in a rig calibration")
    return io.common.rig([Camera.from_dict(d, str(path)) for d in entry["cameras"]], str(path))


def estimates_of(folder, method: str, seed: int | None = None) -> tuple[dict[str, list[Camera]],
                                                                         str]:
    """The estimates of ``method`` in a run directory (trial ``seed``, default its first) or a
    real capture's folder: {label: cameras} with one rig (label "rig") when the rig was
    calibrated, else one camera per label; and where they came from."""
    folder = Path(folder)
    capture = CapturePaths(folder)
    if capture.results.is_file() and read_json(capture.results).get("kind") == "capture":
        trial, where = capture.trial, f"{folder} (a real capture)"
    else:
        run = RunPaths(folder)
        seeds = run.trial_seeds()
        if not seeds:
            raise FileNotFoundError(f"{folder}: neither a run directory (trials/seed_*) nor a "
                                    f"capture written by `stereo-bench calibrate-images`")
        seed = seeds[0] if seed is None else seed
        if seed not in seeds:
            raise ValueError(f"--seed {seed}: {folder} has trials {seeds}")
        trial, where = run.trial(seed), f"{folder}, trial seed {seed}"
    return _trial_estimates(trial, method, where), where


def _trial_estimates(trial: TrialPaths, method: str, where: str) -> dict[str, list[Camera]]:
    rig = trial.rig(method)
    if rig.is_file():
        cams = _rig_file_cameras(rig)
        if isinstance(cams, str):
            raise ValueError(f"{rig}: the rig calibration of {method} failed: {cams}")
        return {"rig": cams}
    folder = trial.calibrations(method)
    # A run's calibrations are listed, with their digests, by its calibration stage's marker.
    if trial.metrics.is_file() and (changed := changed_output(trial.metrics,
                                                              read_json(trial.metrics))):
        raise ValueError(f"{changed}; run the command that wrote it again")
    files = sorted(p for p in folder.glob("*.json")) if folder.is_dir() else []
    if not files:
        found = sorted(p.name for p in trial.all_calibrations.iterdir()) \
            if trial.all_calibrations.is_dir() else []
        raise FileNotFoundError(f"{where}: no estimate of method {method!r} (methods: "
                                f"{', '.join(found) or 'none'})")
    return {p.stem: [Camera.load_json(p)] for p in files}


def write_estimates(estimates: dict[str, list[Camera]], fmt: str, out,
                    **options) -> tuple[list[Path], dict[str, str]]:
    """``estimates_of``'s rigs in format ``fmt`` under ``out`` (a rig directly, single cameras
    in a folder each): the files written, and {label: why} for each estimate the format or the
    checks on a camera refused (the others are still written)."""
    written, refused = [], {}
    for label, cams in estimates.items():
        target = Path(out) if label == "rig" else Path(out) / label
        try:
            written += io.export(cams, target, fmt, **options)
        except ValueError as e:
            refused[label] = str(e)
    return written, refused


def score_calibration(ds: Dataset, path, fmt: str | None, out) -> dict:
    """A calibration from another tool (file or folder ``path``) against the truth of the
    rendered dataset ``ds`` (module notes). The suite's detections of the dataset are written
    under ``out`` (reused by fingerprint)."""
    estimate = io.load(path, fmt)
    names = [c.name for c in ds.cameras]
    cams, how = as_rig_of(estimate, names, str(path))
    report = {"kind": "imported", "calibration": str(path), "format": fmt or io.guess_format(path),
              "dataset": str(ds.root), "matched": how}
    notes = Notes()
    image_points = None
    if len(cams) > 1:
        dets, _, _ = load_or_detect(ds, TrialPaths(Path(out)), notes=notes)
        image_points = np.stack([d.points for d in dets])
    report.update(score_cameras(ds, cams, image_points, str(path)))
    if len(cams) > 1:
        report["notes"] = notes.items
    return report


def score_cameras(ds: Dataset, cams: list[Camera], image_points: np.ndarray | None,
                  where: str) -> dict:
    """A rig's cameras (cam_from_cam0, in the dataset's order) against the dataset's truth:
    per camera the projection difference, parameter errors and validity; for 2+ cameras, RMSE_cal
    through ``image_points`` (C, F, N, 2), the rig's errors and its board geometry. ``where``
    names the calibration in messages."""
    report = {"cameras": {}}
    for est, truth in zip(cams, ds.cameras):
        if est.size != truth.size:
            raise ValueError(f"{where}: camera {truth.name!r} is {est.width}x{est.height} px, "
                             f"the dataset's {truth.width}x{truth.height}")
        truth0 = truth.with_params(rvec=np.zeros(3), tvec=np.zeros(3))
        report["cameras"][truth.name] = {
            "projection_difference": projection_difference(est, truth0),
            "parameter_errors": parameter_errors(est, truth0),
            "validity": validity(est, truth0)}
    if len(cams) > 1:
        points, dropped = triangulated_board(cams, image_points)
        if not np.isfinite(points).all(-1).any():
            # A rig file that reads as cameras but whose rays never meet in front of them.
            report["rig"] = {"error": "no board point of the dataset triangulates through this "
                                      "rig (its cameras' rays do not meet in front of them)",
                             "detections_outside_model": dropped}
            return report
        rig = score_rig(cams, points, ds)
        rig["board_geometry"] = board_geometry(points, ds.object_points)
        rig["detections_outside_model"] = dropped
        report["rig"] = rig
    return report
