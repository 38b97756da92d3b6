"""A real capture's synthetic twin: the capture rendered again with exact truth.

``stereo-bench twin CAPTURE_DIR`` reads a ``calibrate-images`` output and builds a rig file that
replicates it (:func:`twin_rig`):

* the cameras as the chosen method estimated them (a rig's with their poses; world = the
  reference camera's frame);
* the board as described, at the poses that calibration estimated for each frame (a ``poses``
  trajectory; a frame no camera has a pose for is left out);
* the imaging measured on the user's own images (render/imaging_fit.py): the print's levels and
  the background, the noise against signal, the vignetting, the edge width (a lens blur, plus
  a thin lens's defocus where the width grows with the board's distance from a focus) and the
  JPEG quality.
  A rig file has one environment: the cameras' figures are averaged. The measured figures are
  of the images; the settings that reproduce them are found by rendering the twin once,
  measuring it the same way and correcting (:func:`calibrated_environment`): the edge width by
  the rendered edge's own (added in quadrature), the noise by the ratio of the measured gains
  (JPEG smooths noise).

Then every seed renders the twin, runs it through calibrate-images as a capture (the same
detection, methods, diagnostics and rig as the real one), and scores each method's estimates
against the twin's truth. The report puts the real capture and the twin side by side, says
where they disagree (an RPE outside +-20 %, residuals random on one side only) and, only where
they agree, how far each method's calibration most likely is from the truth (95 % intervals
over seeds).

The board's warp is reproduced when the capture fitted it (``calibrate-images
--fit-board-warp``, the cameras' estimates averaged). Not reproduced: motion blur and the
board's scale; a twin whose RPE is too low for these reasons says so.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

from ..calibrate.base import fitted_shape
from ..config.schema import OpticsConfig
from ..core.camera import Camera
from ..core.files import read_arrays, read_json
from ..core.patterns import Checkerboard, pattern_from_config
from ..core.poses import compose, invert, matrix_to_rodrigues, rodrigues_to_matrix
from .sweep_stats import t_interval
from ..render.imaging_fit import ImagingFit, fit_imaging, jpeg_quality, view_samples

RPE_TOLERANCE = 0.2   # a twin whose RPE is more than 20 % off the real one does not match
RANDOMNESS_GAP = 0.1  # neighbour correlations this far apart: residuals of another nature
MAX_SEEDS = 100


def _load(path: Path, what: str) -> dict:
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no {what}; expected a calibrate-images output "
                                f"folder")
    return read_json(path, what)


def capture_estimate(capture: Path, method: str, results: dict) -> tuple[list[Camera], dict]:
    """(the method's cameras, cam_from_world with world = the reference camera's frame;
    per camera the (rvecs, tvecs, frame ids) of its views) from a calibrate-images output
    whose results.json is ``results`` (read_capture)."""
    rig_file = capture / "rig" / f"{method}.json"
    if rig_file.exists():
        cameras = [Camera.from_dict(c, str(rig_file)) for c in _load(rig_file, "rig")["cameras"]]
    else:
        cameras = []
        for name in [c["name"] for c in results["cameras"]]:
            path = capture / "calibrations" / method / f"{name}.json"
            if path.exists():
                cameras.append(Camera.load_json(path))
        cameras = cameras[:1]  # no rig: one camera, at the world's origin
    if not cameras:
        raise ValueError(f"{capture}: {method} calibrated no camera of this capture")
    views = {}
    for cam in cameras:
        v = read_arrays(capture / "calibrations" / method / f"{cam.name}_views.npz",
                        "a calibration's views")
        views[cam.name] = (v["rvecs"], v["tvecs"], v["view_ids"])
    return cameras, views


def board_poses(cameras: list[Camera], views: dict) -> dict[int, np.ndarray]:
    """Per frame id, world_from_board as [rx, ry, rz, tx, ty, tz], from the first camera (in the
    rig's order) with a pose of it."""
    out = {}
    for cam in cameras:
        world_from_cam = invert(cam.R, cam.tvec)
        for rv, tv, f in zip(*views[cam.name]):
            if int(f) not in out:
                R, t = compose(*world_from_cam, rodrigues_to_matrix(rv), np.asarray(tv))
                out[int(f)] = np.r_[matrix_to_rodrigues(R), t]
    return dict(sorted(out.items()))


def camera_entry(cam: Camera) -> dict:
    """The rig file's camera of ``cam``: its lens, and its pose as position, look-at point and
    up (which fix any rotation: the optical axis and the image's up)."""
    R, centre = cam.R, cam.center
    entry = {"name": cam.name, "width": cam.width, "height": cam.height, "fx": cam.fx,
             "fy": cam.fy, "cx": cam.cx, "cy": cam.cy, "skew": cam.skew,
             "dist": cam.dist.tolist(), "position_mm": centre.tolist(),
             "look_at_mm": (centre + 1000.0 * R[2]).tolist(), "up": (-R[1]).tolist()}
    if cam.model != "opencv":
        entry["lens"] = cam.model
    return entry


def measure_images(capture: Path, cameras: list[Camera], views: dict, pattern
                   ) -> dict[str, ImagingFit]:
    """Each camera's imaging measured on its real images (render/imaging_fit.py)."""
    frames = _load(capture / "frames.json", "frames.json")["frames"]
    return {cam.name: measure_views(cam, views[cam.name], pattern,
                                    lambda f, c=cam.name: frames[f]["files"].get(c))
            for cam in cameras}


def measure_views(cam: Camera, views, pattern, path_of) -> ImagingFit:
    """One camera's ImagingFit from its views (rvecs, tvecs, frame ids) and ``path_of(frame)``,
    the image file of a frame."""
    if not isinstance(pattern, Checkerboard):
        raise ValueError(f"the twin measures the imaging on a checkerboard's squares; this "
                         f"capture's board is a {pattern.kind}")
    samples, path = [], None
    for rv, tv, f in zip(*views):
        path = path_of(int(f))
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) if path else None
        if image is None:
            raise FileNotFoundError(f"camera {cam.name!r}, frame {int(f)}: image {path} "
                                    f"cannot be read (run twin where calibrate-images ran)")
        samples.append(view_samples(image, cam, rv, tv, pattern))
    return fit_imaging(samples, cam, jpeg_quality(path))


def environment(fits: dict[str, ImagingFit], cameras: list[Camera], blur_px: float,
                gain: float | None, read_dn: float) -> dict:
    """The rig file's environment of the measured imaging (averaged over cameras), with the
    lens blur and the sensor's gain and read noise as given (the calibrated settings). Where
    the edge width grows with defocus (ImagingFit.defocus), the thin lens that gives it: at the
    optics' nominal focal length f, the f-number N = fx f / K, focused at the fitted distance."""
    f = list(fits.values())
    optics = {"blur_px": round(float(blur_px), 4),
              "corner_illumination": round(float(np.mean([x.corner_illumination for x in f])),
                                           4)}
    fx = {c.name: c.fx for c in cameras}
    lenses = [(fx[name], x.defocus) for name, x in fits.items() if x.defocus]
    if lenses:
        focal = OpticsConfig().focal_length_mm
        optics.update(focal_length_mm=focal,
                      f_number=round(float(np.mean([f_x * focal / d["k_px_mm"]
                                                    for f_x, d in lenses])), 4),
                      focus_distance_mm=round(float(np.mean([d["focus_mm"]
                                                             for _, d in lenses])), 2))
    white = float(np.mean([x.white_level for x in f]))
    black = float(np.mean([x.black_level for x in f]))
    quality = [x.jpeg_quality for x in f if x.jpeg_quality is not None]
    sensor = {"jpeg_quality": int(round(np.mean(quality))) if quality else None}
    if gain is not None:
        # Grey levels per electron: the white print collects white / gain electrons, so
        # exposure x full well = white / gain; the full well saturates at 255 grey levels.
        sensor.update(full_well_e=255.0 / gain, exposure=min(white / 255.0, 1.0),
                      read_noise_e=read_dn / gain)
    else:
        sensor.update(noise_sigma=read_dn)
    return {"kind": "clean", "background": int(round(np.mean([x.background for x in f]))),
            "black_level": int(round(black)), "white_level": int(round(white)),
            "optics": optics, "sensor": sensor}


def _mean_fit(fits: dict[str, ImagingFit]) -> tuple[float, float | None, float]:
    """(the edge width a lens blur must give: the depth-independent part where defocus was
    fitted, else the median width; the gain; the read noise), averaged over cameras."""
    f = list(fits.values())
    gains = [x.gain_dn_per_e for x in f if x.gain_dn_per_e is not None]
    return (float(np.nanmean([x.defocus["sigma0_px"] if x.defocus else x.edge_sigma_px
                              for x in f])),
            float(np.mean(gains)) if gains else None,
            float(np.mean([x.read_noise_dn for x in f])))


def twin_rig(name: str, cameras: list[Camera], poses: dict, pattern: dict, env: dict,
             seed: int) -> dict:
    return {"name": name, "seed": seed, "cameras": [camera_entry(c) for c in cameras],
            "pattern": pattern, "environment": env,
            "trajectory": {"kind": "poses", "poses": [p.tolist() for p in poses.values()]}}


def interval(values) -> dict:
    """mean, the 95 % Student-t interval's half width (sweep_stats.t_interval) and n over the
    finite values."""
    t = t_interval([np.nan if v is None else v for v in values])
    return {"mean": t["mean"], "ci95": float(t["ci_high"] - t["ci_low"]) / 2, "n": t["n"]}


def pattern_of(results: dict):
    """(the rig file's pattern section, the board) of a capture's results."""
    spec = dict(results["pattern"])
    options = {k: v for k, v in spec.items() if k != "kind"}
    return spec, pattern_from_config(spec["kind"], **options)


def _render(rig: dict, out: Path):
    from ..config.schema import parse_rig
    from ..scene.dataset import write_dataset

    return write_dataset(parse_rig(rig, f"the twin's rig file ({out})"), out)


def _true_views(ds, poses: dict) -> dict:
    """Per camera of a rendered twin, (rvecs, tvecs, frame indices) of its true cam_from_board
    in the frames where it sees the whole board: its imaging is measured where the real one's
    was."""
    world = np.array(list(poses.values()))
    views = {}
    for c, cam in enumerate(ds.cameras):
        seen = np.flatnonzero(ds.ground_truth.visible[c].all(axis=1))
        rv, tv = [], []
        for f in seen:
            R, t = compose(cam.R, cam.tvec, rodrigues_to_matrix(world[f, :3]), world[f, 3:])
            rv.append(matrix_to_rodrigues(R))
            tv.append(t)
        views[cam.name] = (np.array(rv).reshape(-1, 3), np.array(tv).reshape(-1, 3), seen)
    return views


def calibrated_environment(name, cameras, poses, pattern_spec, pattern, fits, out: Path
                           ) -> tuple[dict, dict]:
    """(the environment that reproduces the measured imaging, the figures of that step): the
    twin rendered once with no lens blur and the measured noise, measured the same way, and
    corrected (module notes)."""
    sigma, gain, read = _mean_fit(fits)
    first = _render(twin_rig(name, cameras, poses, pattern_spec,
                             environment(fits, cameras, 0.0, gain, read), 0), out)
    views = _true_views(first, poses)
    measured = {cam.name: measure_views(cam.with_params(rvec=np.zeros(3), tvec=np.zeros(3)),
                                        views[cam.name], pattern,
                                        lambda f, c=cam.name: first.paths.image(c, f))
                for cam in first.cameras}
    sigma0, gain0, read0 = _mean_fit(measured)
    blur = math.sqrt(max(sigma ** 2 - sigma0 ** 2, 0.0))
    if gain is not None and gain0 is not None:
        gain = gain * gain / gain0
    read = read * read / read0 if read0 > 0 else read
    return environment(fits, cameras, blur, gain, read), {
        "measured_on_real": {c: f.as_dict() for c, f in fits.items()},
        "measured_on_uncorrected_twin": {c: f.as_dict() for c, f in measured.items()},
        "edge_sigma_px": {"real": sigma, "rendered_without_blur": sigma0, "blur_px": blur}}


def _capture_of(ds, methods, out: Path, pattern, settings: dict) -> dict:
    """The twin's images through calibrate-images, as the real ones went (the same methods and
    calibration settings, e.g. --fit-board-warp)."""
    from ..config.schema import CalibrationConfig
    from ..scene.image_folders import ImageFolders
    from .capture import calibrate_capture

    source = ImageFolders.open({c.name: str(ds.paths.images(c.name)) for c in ds.cameras},
                               pattern)
    return calibrate_capture(source, methods, out, CalibrationConfig(**settings))


def _scores(capture_results: dict, capture_out: Path, ds) -> dict:
    """Per method: per camera its true projection difference and intrinsics errors; for a rig,
    per camera its rotation and centre errors."""
    from ..detect.dataset import CameraDetections
    from ..evaluate.metrics import parameter_errors, projection_difference
    from .pipeline import score_rig, triangulated_board

    truth = {c.name: c for c in ds.cameras}
    out = {}
    for m in capture_results["methods"]:
        entry = {"cameras": {}}
        for name, cam in truth.items():
            path = capture_out / "calibrations" / m / f"{name}.json"
            if not path.exists():
                continue
            est, true0 = Camera.load_json(path), cam.with_params(rvec=np.zeros(3),
                                                                 tvec=np.zeros(3))
            entry["cameras"][name] = {"projection_difference": projection_difference(est, true0),
                                      "parameter_errors": parameter_errors(est, true0)}
        rig_file = capture_out / "rig" / f"{m}.json"
        if len(truth) > 1 and rig_file.exists():
            est = [Camera.from_dict(c) for c in read_json(rig_file, "rig")["cameras"]]
            if [c.name for c in est] == list(truth):
                # The twin's detections triangulated through the method's rig, scored as a run
                # scores its rigs: RMSE_cal against the physical board, the cameras' errors.
                dets = np.stack([CameraDetections.load(capture_out / "detections"
                                                       / f"{name}.npz").points
                                 for name in truth])
                scored = score_rig(est, triangulated_board(est, dets)[0], ds)
                entry["rig"] = {"rmse_cal_mm": scored["rmse_cal_mm"],
                                **{k: np.asarray(v).tolist()
                                   for k, v in scored["rig_errors"].items()}}
        out[m] = entry
    return out


def _real_figures(results: dict, method: str, camera: str) -> dict:
    """The figures a capture shows of itself, per camera, for one method."""
    det = results["detection"][camera]
    e = results["calibration"].get(method, {}).get(camera, {})
    if "error" in e or not e:
        return {"detected": det["found"], "frames": det["frames"]}
    rand = e["diagnostics"]["randomness"]
    proj = e.get("uncertainty", {}).get("projection", {})
    return {"detected": det["found"], "frames": det["frames"], "rpe_px": e["rpe_rms_px"],
            "heldout_px": e.get("heldout", {}).get("heldout_rms_px"),
            "view_rpe_px": e["diagnostics"]["views"]["rms_px"],
            "neighbour_correlation": rand["statistic"], "correlation_p": rand["p_value"],
            "residuals_random": not rand["flagged"],
            "projection_sigma_px": proj.get("worst_px") if isinstance(proj, dict) else None}


def read_capture(capture: Path, method: str, seeds: int) -> dict:
    """The capture's results.json, checked before anything is written: a ValueError or
    FileNotFoundError naming the file or the option otherwise."""
    if not 1 <= seeds <= MAX_SEEDS:
        raise ValueError(f"--seeds: expected 1..{MAX_SEEDS}, got {seeds}")
    real = _load(Path(capture) / "results.json", "results.json")
    missing = [k for k in ("pattern", "methods", "cameras", "calibration", "detection")
               if not isinstance(real, dict) or k not in real]
    if not isinstance(real, dict) or real.get("kind") != "capture" or missing:
        raise ValueError(f"{capture}/results.json: not a calibrate-images output's (expected "
                         f"kind: capture with {', '.join(missing) or 'its fields'})")
    if method not in real["methods"]:
        raise ValueError(f"--method {method}: not one of the capture's methods "
                         f"({', '.join(real['methods'])})")
    return real


def run_twin(capture: Path, method: str, seeds: int, out: Path, progress=print) -> dict:
    """The twin of ``capture`` (module notes), written under ``out``; returns results.json's
    dict."""
    from ..core.files import strict, write_json

    capture = Path(capture)
    real = read_capture(capture, method, seeds)
    pattern_spec, pattern = pattern_of(real)
    cameras, views = capture_estimate(capture, method, real)
    poses = board_poses(cameras, views)
    if not poses:
        raise ValueError(f"{capture}: {method} has no board pose of any frame")
    name = f"twin_{capture.resolve().name}"
    progress(f"measuring the imaging on {sum(len(v[2]) for v in views.values())} real views")
    fits = measure_images(capture, cameras, views, pattern)
    env, calibration = calibrated_environment(name, cameras, poses, pattern_spec, pattern, fits,
                                              out / "calibration")
    shape = fitted_shape(pattern.object_points(), [e.get("log", {}) for e in
                                                   real["calibration"][method].values()])
    if shape is not None:  # the capture fitted its board (--fit-board-warp): so is the twin's
        w_x, w_y, aspect = shape.fit_params
        env["board"] = {"warp_mm": [round(w_x, 4), round(w_y, 4)],
                        "aspect_error_pct": round(float(aspect), 4)}
    methods = real["methods"]
    trials = []
    for s in range(seeds):
        progress(f"seed {s + 1} of {seeds}: render, calibrate as a capture, score")
        rig = twin_rig(name, cameras, poses, pattern_spec, env, s)
        ds = _render(rig, out / f"seed_{s}" / "dataset")
        results = _capture_of(ds, methods, out / f"seed_{s}" / "capture", pattern,
                              real.get("calibration_settings", {}))
        trials.append({"capture": results,
                       "scores": _scores(results, out / f"seed_{s}" / "capture", ds)})
    summary = summarize(real, trials, [c.name for c in cameras], method, methods)
    doc = {"capture": str(capture), "method": method, "seeds": seeds,
           "frames": {"real": len(real.get("frame_names", [])), "twin": len(poses)},
           "rig": twin_rig(name, cameras, poses, pattern_spec, env, 0),
           "imaging": calibration, **summary}
    write_json(out / "results.json", strict(doc))
    return doc


def summarize(real: dict, trials: list[dict], cameras: list[str], method: str,
              methods: list[str]) -> dict:
    """Side by side (real, twin mean) per camera for ``method``; whether the twin matches; and
    each method's true errors with their 95 % intervals over seeds."""
    side, mismatch = {}, []
    for cam in cameras:
        r = _real_figures(real, method, cam)
        t = [_real_figures(tr["capture"], method, cam) for tr in trials]
        twin = {k: interval([x.get(k) for x in t])
                for k in ("detected", "rpe_px", "heldout_px", "neighbour_correlation",
                          "projection_sigma_px")}
        twin["residuals_random_share"] = float(np.mean([bool(x.get("residuals_random"))
                                                        for x in t]))
        side[cam] = {"real": {k: v for k, v in r.items() if k != "view_rpe_px"},
                     "twin": twin,
                     "view_rpe_px": {"real": r.get("view_rpe_px"),
                                     "twin": [x.get("view_rpe_px") for x in t]}}
        if r.get("rpe_px") and np.isfinite(twin["rpe_px"]["mean"]):
            ratio = twin["rpe_px"]["mean"] / r["rpe_px"]
            if abs(ratio - 1) > RPE_TOLERANCE:
                mismatch.append(f"camera {cam!r}: the twin's RPE is {ratio:.2f}x the real one"
                                + (": the real images have error the twin lacks (a board "
                                   "warp, motion blur, a lens outside the model or a detector "
                                   "bias)" if ratio < 1 else
                                   ": the twin's images are harder than the real ones (noise "
                                   "or blur overestimated)"))
        # Residuals random on one side only, and clearly so: the neighbour correlations differ
        # by more than RANDOMNESS_GAP (one capture's test flags noise at its alpha by chance).
        if "residuals_random" in r and np.isfinite(twin["neighbour_correlation"]["mean"]):
            twin_random = twin["residuals_random_share"] >= 0.5
            gap = r["neighbour_correlation"] - twin["neighbour_correlation"]["mean"]
            if r["residuals_random"] != twin_random and abs(gap) > RANDOMNESS_GAP:
                said = {True: "random", False: "not random"}
                mismatch.append(
                    f"camera {cam!r}: residuals are {said[r['residuals_random']]} in the real "
                    f"capture (neighbour correlation {r['neighbour_correlation']:.2f}) and "
                    f"{said[twin_random]} in the twin "
                    f"({twin['neighbour_correlation']['mean']:.2f})"
                    + (": the real residuals carry a structure (a bent board, a lens outside "
                       "the model or a detector bias) the twin does not reproduce"
                       if twin_random else ""))
    errors = {}
    for m in methods:
        per_cam = {}
        for cam in cameras:
            entries = [tr["scores"].get(m, {}).get("cameras", {}).get(cam) for tr in trials]
            entries = [e for e in entries if e]
            if not entries:
                continue
            per_cam[cam] = {
                "projection_mean_px": interval([e["projection_difference"]["mean_px"]
                                                for e in entries]),
                "projection_max_px": interval([e["projection_difference"]["max_px"]
                                               for e in entries]),
                **{f"{k}_err_px": interval([abs(e["parameter_errors"][k]) for e in entries])
                   for k in ("fx", "fy", "cx", "cy")}}
        rigs = [tr["scores"].get(m, {}).get("rig") for tr in trials]
        rigs = [r for r in rigs if r]
        entry = {"cameras": per_cam}
        if rigs:
            # The worst camera's errors (camera 0, the reference, has none).
            entry["rig"] = {k: interval([max(np.abs(r[k])) for r in rigs])
                            for k in ("rotation_deg", "centre_mm", "baseline_mm")}
            entry["rig"]["rmse_cal_mm"] = interval([r["rmse_cal_mm"] for r in rigs])
        errors[m] = entry
    return {"side_by_side": side, "matches": not mismatch, "mismatch": mismatch,
            "true_errors": errors}
