"""`stereo-bench calibrate-images`: calibrate a user's own capture with every method, and report
what can be known without ground truth.

The capture (``image_folders.ImageFolders``) goes through the stages a rendered dataset goes
through (stage.load_or_detect, stage.calibrate_cameras, pipeline.rig_of and rig_summary).
Between detection and calibration, each camera's views are asked whether they can determine the
camera at all (diagnostics.view_geometry: enough views, at orientations that fix the focal
length); a camera whose views cannot is not calibrated by any method, and says why, once. In
place of the scoring against the truth, each estimate gets:

* its fit: RPE per camera and per view, with outlier views and points flagged, and a test that
  the residuals are noise (diagnostics.py);
* held-out error: k-fold cross-validation over views (diagnostics.heldout);
* its uncertainty: the parameters' standard deviations and mrcal's projection uncertainty over
  the image (uncertainty.py), for the methods whose model is OpenCV's;
* where it can be used: the share of the image with a unique ray (an overfitted model folds);
* agreement between methods: the projection difference between each pair of estimates;
* the image's coverage by the detected features;
* for two or more cameras, the rig: RPE per camera, baselines and rotations, the triangulated
  board's shape and scale against its known layout, and beside it OpenCV's multi-camera
  calibration (calibrateMultiview, intrinsics fixed) on the same detections and intrinsics.

Layout of the output folder (``rundir.CapturePaths``): the trial layout of a run (detections/,
calibrations/<method>/<camera>.json | .yaml | _views.npz, rig/<method>.json) plus frames.json
(the pairing of the files), results.json, report.md and plots/.
"""

from __future__ import annotations

import dataclasses
import itertools
import time

import numpy as np

from ..calibrate import get_calibrator, parse_method
from ..calibrate.lens_models import core_lens
from ..config.schema import CalibrationConfig
from ..detect.boards import measure_disc_diameter
from ..calibrate.diagnostics import diagnose, heldout, view_geometry
from ..evaluate.stage import (Estimate, warp_option, calibrate_cameras, clear_calibrations, intrinsics_frames,
                              load_or_detect, observations)
from ..scene.image_folders import ImageFolders
from ..evaluate.metrics import projection_difference
from ..multiview.opencv_ref import opencv_multiview
from ..multiview.orientation import described
from .pipeline import rig_of, rig_summary
from ..calibrate.next_view import REGIONS, empty_ninths, in_words, suggest
from ..report.plots import plot_capture, primary_method
from ..io.rundir import CapturePaths, Notes, with_outputs
from ..core.files import strict, write_json
from ..multiview.bundle import rig_errors
from ..calibrate.uncertainty import parameter_covariance, projection_uncertainty
from ..calibrate.view_selection import chosen_views, selection_warnings

DEFAULT_FOLDS = 5


def _estimate_report(method: str, est: Estimate, folds: int, seed: int,
                     given: str | None = None, options: dict | None = None) -> dict:
    """The truth-free checks of one camera's estimate by one method (module notes). ``given``:
    where the camera's intrinsics came from when they were not estimated here (then only its
    poses were fitted: no intrinsics to hold out, no covariance of them). ``options``: the
    calibrator's, for the held-out folds (e.g. the board's shape fitted)."""
    result, obs = est.result, est.obs
    params = () if given else get_calibrator(method).model_parameters
    report = {"diagnostics": diagnose(result.camera, obs, result.rvecs, result.tvecs, params,
                                      seed=seed)}
    if given:
        why = f"intrinsics given ({given}), not estimated from these images"
        return {**report, "heldout": {"error": why}, "uncertainty": {"error": why}}
    try:
        report["heldout"] = heldout(method, obs, k=folds, seed=seed, **(options or {}))
    except ValueError as e:
        report["heldout"] = {"error": str(e)}
    if params is None:
        report["uncertainty"] = {"error": f"{method}'s model is not OpenCV's: no covariance of "
                                          f"its parameters is propagated"}
        return report
    try:
        report["uncertainty"] = {
            "parameters": parameter_covariance(result.camera, obs, result.rvecs, result.tvecs,
                                               params),
            "projection": projection_uncertainty(result.camera, obs, result.rvecs,
                                                 result.tvecs, params)}
    except (ValueError, np.linalg.LinAlgError) as e:
        report["uncertainty"] = {"error": f"{type(e).__name__}: {e}"}
    return report


#: Images per camera the disc diameter is measured on (a median over all their discs).
DIAMETER_IMAGES = 8
#: A circle grid's provisional disc diameter, as a share of the distance between neighbouring
#: centres, when the user does not know it: measure_disc_diameter needs a guess within -20 % /
#: +60 %, so this covers printed diameters of 0.31 to 0.63 of the pitch; a second measurement
#: from the first one's answer settles it.
DIAMETER_GUESS = 0.5


def nearest_pitch_mm(pattern) -> float:
    """The distance between neighbouring feature points of a board, mm."""
    obj = pattern.object_points()[:, :2]
    d = np.linalg.norm(obj[:, None] - obj[None], axis=-1)
    return float(d[d > 0].min())


def with_measured_diameter(source: ImageFolders) -> tuple[ImageFolders, str]:
    """A circle grid's capture with the disc diameter measured from its images (module notes),
    and a sentence saying so; ValueError when no disc could be measured."""
    pattern = dataclasses.replace(source.pattern,
                                  diameter_mm=DIAMETER_GUESS * nearest_pitch_mm(source.pattern))
    images = []
    for c in range(len(source.cameras)):
        have = [f for f in range(source.frames) if source.files[c][f] is not None]
        for f in have[:: max(1, len(have) // DIAMETER_IMAGES)][:DIAMETER_IMAGES]:
            try:
                images.append(source.image(c, f))
            except (OSError, ValueError):
                continue  # recorded when the detection reads it again
    first = measure_disc_diameter(images, pattern)
    second = measure_disc_diameter(images, dataclasses.replace(pattern, diameter_mm=first))
    pattern = dataclasses.replace(pattern, diameter_mm=second)
    return (dataclasses.replace(source, pattern=pattern),
            f"disc diameter measured from {len(images)} images: {second:.3f} mm (first pass "
            f"from a guess of {DIAMETER_GUESS:.0%} of the pitch: {first:.3f} mm); give "
            f"--diameter-mm if it is known")


#: A held-out error this much above the in-sample one says the model fits the noise.
OVERFIT_RATIO = 1.5
#: A fold is reported when it covers at least this share of the image: what rounds to 0.1 %
#: with one decimal. The validity grid (metrics.validity, 64 x 48) has 0.03 % per point, so a
#: fold in one corner point is below it (the report's table still marks the estimate).
REPORTED_FOLD = 0.0005
#: A detection is warned about when it is off its reprojection by at least this much, as well
#: as beyond the statistical threshold (diagnostics.point_outliers): detection errors are not
#: Gaussian, so clean renders flag a dozen corners at 0.05 px, which changes nothing a user sees.
REPORTED_POINT_PX = 0.5


def _grouped(items: list[tuple[str, str, str]]) -> list[str]:
    """(method, camera, text) -> one line per camera and text, naming every method it holds
    for: the same fact once, not once per method. A camera of "" is a fact of the rig (its text
    names the cameras)."""
    methods: dict[tuple[str, str], list[str]] = {}
    for m, cam, text in items:
        methods.setdefault((cam, text), []).append(m)
    return [f"{', '.join(ms)}{f', camera {cam}' if cam else ''}: {text}"
            for (cam, text), ms in methods.items()]


def _where_no_ray(method: str) -> str:
    """Why a method's estimate can have no ray at a pixel: a pinhole model folds; a wide lens
    model's image circle ends (rightly, outside a circular fisheye's)."""
    if core_lens(parse_method(method)[1]) == "opencv":
        return "it folds there"
    return "beyond the image circle it implies: right for a circular fisheye's surround"


def flags(results: dict) -> list[str]:
    """What looks wrong in a capture's estimates, in words: a model that folds inside the image
    (an overfitted high-order distortion, TRAPS.md), a held-out error far above the fit's, views
    that fit worse than the others, detections far off their reprojection. Each fact once: the
    methods it holds for are named together."""
    out = []
    for m, cams in results["calibration"].items():
        for cam, e in cams.items():
            if "error" in e:
                continue
            folded = 1 - e["validity"]["valid_fraction"]
            if not e["validity"]["usable"] and folded >= REPORTED_FOLD:
                out.append((m, cam, f"the lens model has no unique ray over {100 * folded:.1f} % "
                                    f"of the image ({_where_no_ray(m)}); projections and "
                                    f"triangulations there are meaningless"))
            ratio = e.get("heldout", {}).get("ratio")
            if isinstance(ratio, (int, float)) and ratio > OVERFIT_RATIO:
                out.append((m, cam, f"held-out error {ratio:.2f}x the fit's: the model fits the "
                                    f"noise (fewer coefficients, or more views)"))
            points = [p for p in e["diagnostics"]["points"]["flagged"]
                      if p["residual_px"] >= REPORTED_POINT_PX]
            limit = max(REPORTED_POINT_PX, e["diagnostics"]["points"]["threshold_px"])
            if points:
                worst = points[0]
                out.append((m, cam,
                            f"{len(points)} detection(s) off their reprojection by more than "
                            f"{limit:.2f} px (worst "
                            f"{worst['residual_px']:.2f} px in "
                            f"{results['frame_names'][worst['view_id']]} at "
                            f"({worst['image_point'][0]:.0f}, {worst['image_point'][1]:.0f}))"))
    return _grouped(out)


def failures(results: dict) -> list[str]:
    """The cameras and methods that gave no estimate, in words, each reason once: a camera not
    calibrated at all (no usable view, or views that cannot determine it) in one line, a method
    that failed on a camera with the other methods that failed the same way."""
    out, items = [], []
    for cam in (c["name"] for c in results["cameras"]):
        errors = {m: cams[cam]["error"] for m, cams in results["calibration"].items()
                  if "error" in cams.get(cam, {})}
        if cam in results["refused"]:
            out.append(results["refused"][cam])
            continue
        if isinstance(results["detection"][cam]["views_left_out"], str):  # no usable view
            out.append(next(iter(errors.values())))
            continue
        items += [(m, cam, f"failed: {e}") for m, e in errors.items()]
    return out + _grouped(items)


def agreement(estimates: dict[str, Estimate]) -> list[dict]:
    """One camera's estimates by each pair of methods: the projection difference between them
    (metrics.projection_difference, as is and after the best rotation). The rays come from the
    second of the pair; where its model has no unique ray everywhere the first is tried."""
    rows = []
    for a, b in itertools.combinations(sorted(estimates), 2):
        ca, cb = estimates[a].result.camera, estimates[b].result.camera
        row = {"methods": [a, b]}
        for first, second in ((ca, cb), (cb, ca)):
            try:
                row.update(projection_difference(first, second))
                break
            except ValueError as e:  # the second one folds inside the image
                row["error"] = str(e)
        else:
            rows.append(row)
            continue
        row.pop("error", None)
        rows.append(row)
    return rows


def _opencv_rig(rig, image_points, source) -> dict:
    """OpenCV's calibrateMultiview on the same detections with the same intrinsics fixed: the
    peer of the project's rig adjustment (full views only, multiview_ref's notes)."""
    seen = np.isfinite(image_points).all(-1).any(-1)
    try:
        ref = opencv_multiview(rig.cameras, source.object_points, image_points, seen)
    except (ValueError, np.linalg.LinAlgError, ImportError) as e:
        return {"error": f"not run: {e}"}
    out = {"opencv_version": ref.log.get("opencv_version"), "rms_px": ref.rms_px,
           "frames_used": int(ref.frames_used.sum()), "cameras": {}}
    diff = rig_errors(ref.cameras, rig.cameras)  # OpenCV's rig against the project's
    for i, theirs in enumerate(ref.cameras[1:], 1):
        out["cameras"][theirs.name] = {
            "baseline_mm": float(np.linalg.norm(theirs.center)),
            "rotation_deg": float(np.degrees(np.linalg.norm(theirs.rvec))),
            "difference_rotation_deg": float(diff["rotation_deg"][i]),
            "difference_centre_mm": float(diff["centre_mm"][i])}
    return out


def view_evidence(source: ImageFolders, dets, calibration: CalibrationConfig, given=()
                  ) -> tuple[dict[str, dict], dict[str, str], dict[str, dict]]:
    """Before any method runs: per camera with usable views, what they can determine
    (diagnostics.view_geometry); the cameras they cannot determine (except those whose
    intrinsics are ``given``, which the views need not determine), with the reason in words
    (naming the camera, and the board's description when it was found in few images: a wrong
    --inner-corners matches a sub-grid in a few views only); and each camera's found views left
    out (stage.observations). A camera without any usable view is left to the calibration
    stage, which says so."""
    geometry, refused, dropped = {}, {}, {}
    for c, (cam, det) in enumerate(zip(source.cameras, dets)):
        try:
            obs, dropped[cam.name] = observations(det, source.object_points, cam,
                                                  intrinsics_frames(source, c, calibration))
        except ValueError:
            continue
        try:
            g = geometry[cam.name] = view_geometry(obs)
        except (ValueError, np.linalg.LinAlgError) as e:  # the methods will tell
            geometry[cam.name] = {"error": f"{type(e).__name__}: {e}"}
            continue
        if g["refused"] is None or cam.name in given:
            continue
        images = sum(p is not None for p in source.files[c])
        why = f"camera {cam.name!r} not calibrated: {g['refused']}"
        found = int(det.found.sum())
        if found < images / 2:
            why += (f". The board was found in only {found} of {images} images: "
                    + _board_hint(source.pattern))
        refused[cam.name] = why
    return geometry, refused, dropped


#: A rig is not reported when its own figures contradict it: the triangulated board's size off by
#: more than this (a correct rig keeps it to a few hundredths of a percent on real pairs; a view
#: numbered from the wrong corner doubles it) ...
DOUBT_SCALE_PCT = 2.0
#: ... or OpenCV's calibrateMultiview on the same detections, with the same intrinsics, placing a
#: camera more than this far from it (real pairs: about 0.01 degree and 0.1 % of the baseline).
DOUBT_ROTATION_DEG = 1.0
DOUBT_CENTRE_FRACTION = 0.02


def rig_doubts(entry: dict) -> list[str]:
    """Why a rig's own figures say it is wrong, in words (module constants DOUBT_*)."""
    doubts = []
    scale = entry["board_geometry"].get("scale_error_pct")
    if isinstance(scale, float) and abs(scale) > DOUBT_SCALE_PCT:
        doubts.append(f"the board triangulated through it is {scale:+.1f} % off its known size "
                      f"(more than {DOUBT_SCALE_PCT:g} %)")
    for cam, ref in entry.get("opencv_multiview", {}).get("cameras", {}).items():
        baseline = entry["baseline_mm"].get(cam) or 0.0
        if ref["difference_rotation_deg"] > DOUBT_ROTATION_DEG or \
                ref["difference_centre_mm"] > DOUBT_CENTRE_FRACTION * baseline:
            doubts.append(f"OpenCV's calibrateMultiview on the same detections places camera "
                          f"{cam!r} {ref['difference_rotation_deg']:.2f} degrees and "
                          f"{ref['difference_centre_mm']:.3g} mm from it (more than "
                          f"{DOUBT_ROTATION_DEG:g} degree or {100 * DOUBT_CENTRE_FRACTION:g} % of "
                          f"the baseline)")
    return doubts


def _capture_rig(source: ImageFolders, trial, method: str, calibration: CalibrationConfig,
                 estimates: dict) -> dict:
    """One method's rig of the cameras it calibrated (a camera without an estimate is left out
    and named), checked against its own figures (``rig_doubts``): a rig that fails them is
    reported as an error in words, its figures kept under "doubted"."""
    missing = {cam: e["error"] for cam, e in estimates.items() if "error" in e}
    joined = [c.name for c in source.cameras if c.name not in missing]
    if len(joined) < 2:
        return {"method": method, "left_out": missing,
                "error": f"fewer than two cameras calibrated by {method} "
                         f"({', '.join(map(repr, missing))} not)"}
    try:
        rig, image_points = rig_of(source, trial, method, calibration, joined)
        entry, _ = rig_summary(rig, image_points, source.object_points, method, calibration)
        entry["opencv_multiview"] = _opencv_rig(rig, image_points, source)
    except (ValueError, np.linalg.LinAlgError, RuntimeError) as e:
        return {"method": method, "left_out": missing, "error": str(e)}
    entry["left_out"] = missing
    if doubts := rig_doubts(entry):
        return {"method": method, "left_out": missing, "doubted": entry,
                "error": "its own figures contradict it: " + "; ".join(doubts)}
    return entry


def _rig_warnings(rigs: dict, source: ImageFolders) -> list[str]:
    """The cameras each rig left out, the views it renumbered or dropped, and the rigs not
    reported, each fact once with the methods it holds for."""
    items = []
    for m, entry in rigs.items():
        for cam in entry.get("left_out", {}) if "error" not in entry else ():
            items.append((m, cam, "left out of the rig: it has no estimate (above)"))
        log = (entry.get("doubted") or entry).get("log", {})
        for line in described(log.get("orientation", []), source.frame_name):
            items.append((m, "", line))
        if "error" in entry:
            items.append((m, "", f"no rig: {entry['error']}"))
    return _grouped(items)


#: A method's rig baseline this far (relative) from the median of the others' is named.
BASELINE_DISAGREEMENT = 0.02

def empty_regions(counts) -> list[str]:
    """The ninths of the image where no feature was detected in any view, named."""
    return [REGIONS[i // 3][i % 3] for i in np.flatnonzero(empty_ninths(counts))]


def next_views(source: ImageFolders, estimates: dict, results: dict, given) -> dict:
    """Per camera whose intrinsics were estimated here, the board views that would most reduce
    its projection uncertainty where it is largest (next_view.suggest), for the estimate the
    figures show (plots.primary_method) when its model is OpenCV's."""
    out = {}
    for cam in source.cameras:
        m = primary_method(results, cam.name)
        params = get_calibrator(m).model_parameters if m else None
        if params is None or cam.name in given:
            continue
        est = estimates[m, cam.name]
        counts = results["calibration"][m][cam.name]["diagnostics"]["coverage"]["counts"]
        try:
            out[cam.name] = {"method": m, "views": suggest(
                est.result.camera, est.obs, est.result.rvecs, est.result.tvecs, params,
                source.object_points, counts)}
        except (ValueError, np.linalg.LinAlgError) as e:
            out[cam.name] = {"method": m, "error": f"no view suggested: {e}"}
    return out


def recapture(results: dict) -> list[str]:
    """What to shoot again, per camera whose intrinsics were estimated here, in words: the
    views that would most reduce its projection uncertainty where it is largest
    (``next_views``); for a camera without them, the parts of its image no view of the board
    reached (where every estimate extrapolates its distortion)."""
    out = []
    given = (results.get("intrinsics_given") or {}).get("cameras", [])
    for cam in (c["name"] for c in results["cameras"] if c["name"] not in given):
        views = results.get("next_views", {}).get(cam, {}).get("views")
        if views:
            out += [in_words(cam, v, k) for k, v in enumerate(views, 1)]
            continue
        cov = next((e["diagnostics"]["coverage"] for cams in results["calibration"].values()
                    for name, e in cams.items() if name == cam and "diagnostics" in e), None)
        if cov is None:
            continue
        empty = empty_regions(cov["counts"])
        if empty:
            out.append(f"camera {cam}: no board feature reached the {', '.join(empty)} of the "
                       f"image ({100 * cov['cell_fraction']:.0f} % of it covered): the lens model "
                       f"is extrapolated there. Add views with the board in those parts, close "
                       f"enough to fill about a third of the image, some tilted 30-45 degrees "
                       f"about each axis")
    return out


def baseline_outliers(rigs: dict) -> list[str]:
    """Methods whose rig puts a camera more than BASELINE_DISAGREEMENT from the median of every
    method's baseline (with three or more rigs, so that one method cannot move the median)."""
    ok = {m: e for m, e in rigs.items() if "error" not in e}
    out = []
    if len(ok) < 3:
        return out
    for m, e in ok.items():
        for cam, b in e["baseline_mm"].items():
            median = float(np.median([o["baseline_mm"][cam] for o in ok.values()
                                      if cam in o["baseline_mm"]]))
            if median > 0 and abs(b / median - 1) > BASELINE_DISAGREEMENT:
                out.append(f"{m}'s rig puts camera {cam} {b:.1f} mm from the reference, "
                           f"{100 * (b / median - 1):+.1f} % from the methods' median "
                           f"({median:.1f} mm)")
    return out


def _board_hint(pattern) -> str:
    size = getattr(pattern, "pattern_size", None)
    if pattern.kind == "checkerboard" and size:
        return (f"is the board described right? --inner-corners {size[0]}x{size[1]} counts the "
                f"corners where four squares meet (a board of {size[0] + 1}x{size[1] + 1} "
                f"squares); a smaller count than the board's matches a part of it in a few "
                f"views only")
    return "is the board described right (its kind, size and counts)?"


def given_intrinsics(cameras: list, source: ImageFolders, where: str) -> dict:
    """The cameras of a calibration file (``where``) whose names are the capture's, by name;
    ValueError naming the file when none is, or when one's image size is not its camera's."""
    by_name = {c.name: c for c in source.cameras}
    given = {c.name: c for c in cameras if c.name in by_name}
    if not given:
        raise ValueError(f"--intrinsics {where}: its cameras {[c.name for c in cameras]} are "
                         f"none of the capture's {list(by_name)}; expected the same names")
    for name, cam in given.items():
        if cam.size != by_name[name].size:
            raise ValueError(f"--intrinsics {where}: camera {name!r} is {cam.width}x{cam.height} "
                             f"px there, its images {by_name[name].width}x"
                             f"{by_name[name].height} px")
    return given


def calibrate_capture(source: ImageFolders, methods: list[str], out, calibration:
                      CalibrationConfig = CalibrationConfig(), folds: int = DEFAULT_FOLDS,
                      seed: int = 0, progress=None, notes_in: list[str] = (),
                      given: dict | None = None, given_from: str = "") -> dict:
    """Every stage on a real capture, written under ``out`` (module notes); returns the dict
    written to results.json. A camera or method that fails is recorded with its reason and the
    others go on; the detections are reused only for the same images and board. ``notes_in``:
    what the caller found out about the capture (e.g. a measured disc diameter), kept in the
    results. ``given``: cameras whose intrinsics come from a file (``given_intrinsics``;
    ``given_from`` names it), kept for every method, only their poses fitted."""
    given = given or {}
    for m in methods:
        get_calibrator(m)
    paths = CapturePaths(out)
    trial = paths.trial
    notes = Notes()
    for note in notes_in:
        notes.add(note)
    write_json(paths.frames, source.index())
    dets, detect_s, det_fp = load_or_detect(source, trial, progress, notes)
    clear_calibrations(trial)
    t0 = time.perf_counter()
    # The intrinsics from the sharp views, each board pose once (view_selection's notes).
    chosen, deselected, blur = chosen_views(source, dets)
    geometry, refused, dropped = view_evidence(source, chosen, calibration, given)
    # A refused camera reaches the calibration stage without views (so no method runs on it and
    # no estimate of it is written); its entries then say why, in the refusal's words.
    offered = [dataclasses.replace(d, found=np.zeros_like(d.found)) if c.name in refused else d
               for c, d in zip(source.cameras, chosen)]
    entries, estimates, left_out = calibrate_cameras(source, offered, methods, trial,
                                                     calibration, given)
    for name in refused:
        for m in methods:
            entries[m][name] = {"error": f"camera {name!r} not calibrated: "
                                         f"{geometry[name]['refused_brief']} (notes)"}
        left_out[name] = dropped[name]
    for name, views in deselected.items():
        if isinstance(left_out.get(name), dict):
            left_out[name] = dict(sorted({**left_out[name], **views}.items()))
    calibrate_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    for m in methods:
        for cam in source.cameras:
            if (m, cam.name) in estimates:
                entries[m][cam.name].update(_estimate_report(
                    m, estimates[m, cam.name], folds, seed,
                    given_from if cam.name in given else None, warp_option(m, calibration)))
    results = {
        "kind": "capture",
        "pattern": {"kind": source.pattern.kind, **{
            k: v for k, v in vars(source.pattern).items()
            if k != "margin_mm" and not (k == "inverted" and not v)}},
        "cameras": [{"name": c.name, "width": c.width, "height": c.height}
                    for c in source.cameras],
        "frames": source.frames,
        # Views are numbered by frame index (view_ids); this is each index's name.
        "frame_names": [source.frame_name(f) for f in range(source.frames)],
        "methods": methods,
        "calibration_settings": calibration.model_dump(),
        "detection": {c.name: {"frames": source.frames, "found": int(d.found.sum()),
                               "errors": {source.frame_name(f): e for f, e in d.errors.items()},
                               "views_left_out": left_out[c.name]}
                      for c, d in zip(source.cameras, dets)},
        "calibration": entries,
        # What each camera's views can determine (diagnostics.view_geometry), and the cameras
        # not calibrated because of it, with the reason.
        "view_geometry": geometry,
        # The cameras whose intrinsics came from a file, and the file.
        "intrinsics_given": {"file": given_from, "cameras": sorted(given)} if given else None,
        # Each camera's blur per view (view_selection.edge_spread), the basis of the views left
        # out as blurred.
        "view_blur": blur,
        "refused": refused,
        "agreement": {c.name: agreement({m: estimates[m, c.name] for m in methods
                                          if (m, c.name) in estimates})
                      for c in source.cameras},
        "rig": {},
        "warnings": list(source.warnings),
        "detections_fingerprint": det_fp,
    }
    if given:
        results["warnings"].append(
            f"camera(s) {', '.join(sorted(given))}: intrinsics from {given_from}, not estimated "
            f"from these images; every method keeps them (their rows differ only in the rig)")
    results["warnings"] += selection_warnings(deselected, source.frame_name) + \
        failures(results) + flags(results)
    diagnostics_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    if len(source.cameras) >= 2:
        for m in methods:
            results["rig"][m] = entry = strict(_capture_rig(source, trial, m, calibration,
                                                            entries[m]))
            write_json(trial.rig(m), with_outputs(entry, trial.rig(m)))
        results["warnings"] += _rig_warnings(results["rig"], source) + \
            baseline_outliers(results["rig"])
    rig_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    results["next_views"] = next_views(source, estimates, results, given)
    results["recapture"] = recapture(results)
    results["timing"] = {"detect_s": detect_s, "calibrate_s": calibrate_s,
                         "diagnostics_s": diagnostics_s, "rig_s": rig_s,
                         "next_views_s": time.perf_counter() - t0}
    results["notes"] = notes.items
    write_json(paths.results, results)
    results = strict(results)
    results["plots"] = [str(p.relative_to(paths.root)) for p in plot_capture(
        results, estimates, results["frame_names"], paths.plots)]
    write_json(paths.results, results)
    return results
