"""Plots of a run a person would rather look at than read (matplotlib, Agg backend).

* ``metrics.png``: per-method bars with their values, on a log scale where methods differ by
  decades, error bars over trials when there are several (RPE_RMS, projection
  difference, RMSE_cal);
* ``residuals.png``: the distribution of reprojection residuals per method, a panel per camera
  (first trial);
* ``trajectory.png``: the board's path and the cameras in 3D;
* ``studio.png`` (session trajectories): the studio from above with the board's path, and
  which camera detected the board in which frame;
* ``projection_difference_<camera>.png``: the map over the image of how far each method's
  estimate projects the true camera's rays;
* ``views_<camera>.png``: what a real capture's figure shows, for one estimate (below).

A real capture (``plot_capture``) has no truth; per camera, ``capture_<camera>.png`` shows one
method's RPE per view (flagged views in red), its residual vectors over the image, the image's
coverage by the features, and its projection uncertainty over the image.
"""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib
import matplotlib.colors
import matplotlib.patches

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from ..core.camera import Camera, project_points  # noqa: E402
from ..scene.dataset import Dataset  # noqa: E402
from ..detect.dataset import CameraDetections  # noqa: E402
from ..evaluate.stage import MIN_POINTS  # noqa: E402
from ..evaluate.metrics import projection_difference_map  # noqa: E402
from ..scene.rig import ground_axes, world_up  # noqa: E402
from ..io.rundir import RunPaths, TrialPaths  # noqa: E402
from ..core.files import read_arrays  # noqa: E402

#: Pixels per inch of every figure, made at the resolution it is saved at: the layout then
#: measures its text at the size it is drawn (made at another resolution, the draw measured it
#: all again: 4-14 % of a wide pair's figure time, depending on how it was measured).
DPI = 110


def _bars(ax, agg_rows: dict, column: str, title: str, trials: int) -> None:
    """One metric per method: bars with their value written on them, on a log scale when the
    methods differ by a decade or more (Bouguet's 0.02 px beside Zhang's 18 px), with the std
    over trials as error bars only when there is more than one trial."""
    names = list(agg_rows)
    mean = [agg_rows[n][column]["mean"] for n in names]
    std = [agg_rows[n][column]["std"] for n in names]
    shown = [np.nan if m is None else m for m in mean]
    bars = ax.bar(range(len(names)), shown, yerr=std if trials > 1 else None, capsize=4,
                  color="tab:blue", alpha=0.8)
    ax.bar_label(bars, labels=["failed" if m is None or not np.isfinite(m) else f"{m:.3g}"
                               for m in mean], fontsize=7, padding=2)
    if _spans_decades(shown):
        ax.set_yscale("log")
    ax.margins(y=0.15)
    ax.set_xticks(range(len(names)), names, rotation=30, ha="right", fontsize=8)
    ax.set_title(title, fontsize=9)


def plot_metrics(agg: dict, path: Path) -> Path:
    cams = list(agg["detection"])
    panels = [("RPE_RMS px", "RPE_RMS (px)"), ("proj. diff mean px", "projection diff. (px)")]
    n = len(panels) * len(cams) + (1 if "rig" in agg else 0)
    cols = min(n, 6)  # a studio's many cameras wrap onto rows
    lines = -(-n // cols)
    fig, axes = plt.subplots(lines, cols, dpi=DPI, figsize=(3.2 * cols, 3.4 * lines),
                             squeeze=False)
    axes = axes.ravel()
    for ax in axes[n:]:
        ax.set_visible(False)
    i = 0
    for cam in cams:
        rows = {m: agg["calibration"][m][cam] for m in agg["calibration"]}
        for column, title in panels:
            _bars(axes[i], rows, column, f"{cam}: {title}", agg["trials"])
            i += 1
    if "rig" in agg:
        _bars(axes[i], agg["rig"], "RMSE_cal mm", "RMSE_cal (mm)", agg["trials"])
    fig.suptitle(f"mean ± std over {agg['trials']} trials (error bars)" if agg["trials"] > 1
                 else "one trial: no spread to show (run --trials N for error bars)",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=DPI, bbox_inches="tight")
    plt.close(fig)
    return path


def residuals(trial: TrialPaths, ds: Dataset, method: str, camera: Camera) -> np.ndarray:
    """Reprojection residual norms (px) of one method and camera over the views of a trial."""
    if not trial.calibration(method, camera.name).is_file():
        return np.zeros(0)
    est = Camera.load_json(trial.calibration(method, camera.name))
    det = CameraDetections.load(trial.detection(camera.name))
    out = []
    z = read_arrays(trial.views(method, camera.name), "a calibration's views")
    for f, r, t in zip(z["view_ids"], z["rvecs"], z["tvecs"]):
        ok = np.isfinite(det.points[f]).all(1)
        uv = project_points(ds.object_points[ok], est.intrinsics, est.dist, r, t, est.model)
        out.append(np.linalg.norm(uv - det.points[f, ok], axis=1))
    return np.concatenate(out) if out else np.zeros(0)


def plot_residuals(trial: TrialPaths, ds: Dataset, methods: list[str], path: Path) -> Path:
    """The distribution of reprojection residuals per method, one panel per camera."""
    cams = ds.cameras
    cols = min(len(cams), 4)
    lines = -(-len(cams) // cols)
    fig, axes = plt.subplots(lines, cols, dpi=DPI, figsize=(5.2 * cols, 3.4 * lines),
                             squeeze=False)
    for ax in axes.ravel()[len(cams):]:
        ax.set_visible(False)
    for ax, cam in zip(axes.ravel(), cams):
        for m in methods:
            r = residuals(trial, ds, m, cam)
            if len(r):
                ax.hist(r, bins=np.geomspace(max(r.min(), 1e-4), r.max() + 1e-9, 60),
                        histtype="step", label=f"{m} (RMS {np.sqrt(np.mean(r**2)):.3f})")
        ax.set_xscale("log")
        ax.set_xlabel("reprojection residual (px)")
        ax.set_ylabel("points")
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)
            ax.set_title(f"{cam.name}", fontsize=9)
        else:
            ax.set_title(f"{cam.name}: no method calibrated it", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=DPI, bbox_inches="tight")
    plt.close(fig)
    return path


def _world_axes(cameras: list[Camera]) -> tuple[np.ndarray, list[str]]:
    """A plotting basis (3, 3) of rows (horizontal 1, horizontal 2, up) and their labels: up
    is the cameras' (rig.world_up), so a pair (world y down) and a studio (z up) both stand
    upright; a basis vector along a world axis is named after it."""
    try:
        up = world_up(cameras)
    except ValueError:  # cameras rolled against each other: the world's own axes, y down
        return np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]]), ["x (mm)", "z (mm)",
                                                                     "-y (mm)"]
    basis = np.stack([*ground_axes(up), up])
    labels = []
    for v in basis:
        k = int(np.argmax(np.abs(v)))
        labels.append(("-" if v[k] < 0 else "") + "xyz"[k] if abs(v[k]) > 1 - 1e-9 else "")
    return basis, [f"{n} (mm)" if n else "(mm)" for n in labels]


def plot_trajectory(rig, path: Path, session: bool = False) -> Path:
    """The board's path and the cameras (``rig``: a rig.Rig, of a dataset or a rig file)."""
    basis, labels = _world_axes(rig.cameras)
    pts = rig.board_points_world() @ basis.T
    fig = plt.figure(dpi=DPI, figsize=(6, 5))
    ax = fig.add_subplot(projection="3d")
    centre = pts.mean(1)
    ax.plot(*centre.T, "-", color="tab:blue", lw=1, label="board centre")
    corners = [0, -1]
    for i, f in enumerate(range(0, len(pts), max(1, len(pts) // 12))):
        ax.plot(*pts[f][corners].T, color="gray", lw=0.6,
                label="board diagonal (every few frames)" if i == 0 else None)
    scale = 0.15 * np.ptp(np.linalg.norm(centre - centre.mean(0), axis=1)) + 30
    for i, cam in enumerate(rig.cameras):
        c = cam.center
        w, h = cam.width - 1, cam.height - 1
        rays = cam.unproject_rays(cam.within_image_circle(
            np.array([[0, 0], [w, 0], [w, h], [0, h]], float)))
        # A pinhole's frustum at depth `scale`; a wide lens's corner rays (maybe past 90
        # degrees) at distance `scale`.
        ends = rays / rays[:, 2:] if cam.model == "opencv" else rays
        corners_w = (c + scale * ends @ cam.R) @ basis.T
        cb = c @ basis.T
        for q in corners_w:
            ax.plot(*np.stack([cb, q]).T, color="tab:red", lw=0.8)
        loop = np.vstack([corners_w, corners_w[:1]])
        ax.plot(*loop.T, color="tab:red", lw=0.8, label="camera (field of view)" if i == 0
                else None)
        ax.text(*cb, cam.name, fontsize=7)
    ax.set_xlabel(labels[0])
    ax.set_ylabel(labels[1])
    ax.set_zlabel(f"up: {labels[2]}")
    kind = "calibration session" if session else "conical spring"
    ax.set_title(f"board trajectory ({kind}) and cameras", fontsize=9)
    ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=DPI, bbox_inches="tight")
    plt.close(fig)
    return path


def plot_studio(trial: TrialPaths, ds: Dataset, path: Path) -> Path:
    """A studio from above, the board's path through it, and which camera saw the board when.

    Left: the cameras (with their viewing direction) and the board centre's path seen from
    above, the walk coloured by frame and each camera's close-ups in grey. Right: per camera and
    frame, whether the board was detected (dark), in view but not detected (light: e.g. seen
    too obliquely or only partly) or not in view (white), with the close-ups of each camera
    after the walk."""
    rig = ds.rig()
    basis, labels = _world_axes(ds.cameras)
    centre = rig.board_points_world().mean(1) @ basis.T
    walk = rig.closeup_of < 0
    dets = [CameraDetections.load(trial.detection(c.name)) for c in ds.cameras]
    in_view = ds.ground_truth.visible.sum(axis=2) >= MIN_POINTS
    detected = np.stack([d.found for d in dets])
    fig, (top, raster) = plt.subplots(1, 2, dpi=DPI, figsize=(12, 4.8),
                                      gridspec_kw={"width_ratios": [1, 1.6]})
    sc = top.scatter(centre[walk, 0], centre[walk, 1], c=np.flatnonzero(walk), s=8,
                     cmap="viridis", label="board centre, walk")
    top.plot(centre[walk, 0], centre[walk, 1], "-", color="tab:blue", lw=0.4, alpha=0.5)
    if (~walk).any():
        top.scatter(centre[~walk, 0], centre[~walk, 1], s=6, color="0.6",
                    label="board centre, close-ups")
    span = np.ptp(np.stack([c.center for c in ds.cameras]) @ basis[:2].T, axis=0).max()
    for cam in ds.cameras:
        c = cam.center @ basis.T
        d = cam.R[2] @ basis.T
        top.annotate("", xy=c[:2] + 0.12 * span * d[:2] / max(np.linalg.norm(d[:2]), 1e-9),
                     xytext=c[:2], arrowprops={"arrowstyle": "->", "color": "tab:red"})
        top.plot(*c[:2], "s", color="tab:red", ms=5)
        top.text(c[0], c[1], f" {cam.name}", fontsize=8)
    top.set_aspect("equal", adjustable="datalim")
    top.set_xlabel(labels[0])
    top.set_ylabel(labels[1])
    top.set_title("seen from above (red: cameras and their optical axes)", fontsize=9)
    top.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=2)
    fig.colorbar(sc, ax=top, shrink=0.7, label="frame").ax.tick_params(labelsize=7)
    state = np.where(detected, 2, np.where(in_view, 1, 0))
    cmap = matplotlib.colors.ListedColormap(["white", "#9ecae1", "#08519c"])
    raster.imshow(state, aspect="auto", cmap=cmap, vmin=0, vmax=2, interpolation="nearest")
    raster.set_yticks(range(len(ds.cameras)), [c.name for c in ds.cameras], fontsize=8)
    raster.set_xlabel("frame")
    for start in np.flatnonzero(np.diff(rig.closeup_of)) + 1:
        raster.axvline(start - 0.5, color="0.3", lw=0.6)
    handles = [matplotlib.patches.Patch(color=cmap(i), label=t) for i, t in
               ((2, "board detected"), (1, "in view, not detected"))]
    raster.legend(handles=handles, fontsize=7, loc="upper right", framealpha=0.9)
    raster.set_title("which camera saw the board when (lines: walk | close-ups of each "
                     "camera)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=DPI, bbox_inches="tight")
    plt.close(fig)
    return path


def plot_projection_maps(trial: TrialPaths, ds: Dataset, methods: list[str],
                         folder: Path, cameras: list[Camera]) -> list[Path]:
    """``projection_difference_<camera>.png`` for each of ``cameras`` (the dataset's)."""
    paths = []
    for cam in cameras:
        truth = cam.with_params(rvec=np.zeros(3), tvec=np.zeros(3))
        ests = {m: trial.calibration(m, cam.name) for m in methods}
        ests = {m: Camera.load_json(p) for m, p in ests.items() if p.is_file()}
        if not ests:
            continue
        maps = {m: projection_difference_map(est, truth) for m, est in ests.items()}
        # One colour scale for the figure, logarithmic from the smallest 1st to the largest 99th
        # percentile: the same colour is the same error in every panel, and 0.05 px beside
        # 18 px both stay readable (the 99th percentile keeps a few corner pixels where a model
        # breaks down from setting the scale). Grey: where the estimate is not valid (it folds
        # or has a pole; left out of the statistics).
        finite = [d[np.isfinite(d) & (d > 0)] for d in maps.values()]
        finite = [f for f in finite if f.size]
        lo = max(min(np.percentile(f, 1) for f in finite), 1e-4) if finite else 1e-3
        hi = max(max(np.percentile(f, 99) for f in finite), 1.01 * lo) if finite else 1.0
        norm = matplotlib.colors.LogNorm(lo, hi, clip=True)
        cmap = plt.get_cmap("magma").with_extremes(bad="0.6")
        fig, axes = plt.subplots(1, len(ests), dpi=DPI, figsize=(3.6 * len(ests), 3.3),
                                 squeeze=False, layout="constrained")
        for ax, (m, diff) in zip(axes[0], maps.items()):
            valid = np.isfinite(diff)
            im = ax.imshow(diff, extent=(0, cam.width - 1, cam.height - 1, 0), cmap=cmap,
                           norm=norm)
            note = "" if valid.all() else f", {1 - valid.mean():.1%} invalid (grey)"
            title = (f"{m}: mean {np.nanmean(diff):.3g}, max {np.nanmax(diff):.3g} px{note}"
                     if valid.any() else f"{m}: invalid over the whole image")
            ax.set_title(title, fontsize=8)
            ax.set_xlabel("u (px)", fontsize=7)
            ax.set_ylabel("v (px)", fontsize=7)
            ax.tick_params(labelsize=6)
        bar = fig.colorbar(im, ax=axes[0].tolist(), shrink=0.8)
        bar.set_label("projection difference (px, log scale)", fontsize=7)
        bar.ax.tick_params(labelsize=6)
        fig.suptitle(f"{cam.name}: |estimate - truth| projection difference over the image",
                     fontsize=9)
        path = folder / f"projection_difference_{cam.name}.png"
        fig.savefig(path, dpi=DPI)
        plt.close(fig)
        paths.append(path)
    return paths


def plot_views(trial: TrialPaths, ds: Dataset, methods: list[str], folder: Path,
               cameras: list[Camera]) -> list[Path]:
    """``views_<camera>.png``: the capture figure (``plot_capture_camera``: RPE per view with
    the outlier views in red, residual vectors over the image, coverage, projection
    uncertainty) for each camera's estimate by ``opencv`` (else the first method that
    calibrated it), from the trial's saved detections and views; for each of ``cameras`` (the
    dataset's)."""
    from ..calibrate import get_calibrator
    from ..calibrate.base import CalibrationResult
    from ..calibrate.diagnostics import coverage, view_outliers
    from ..evaluate.stage import Estimate, observations
    from ..calibrate.uncertainty import projection_uncertainty

    paths = []
    for cam in cameras:
        done = [m for m in methods if trial.calibration(m, cam.name).is_file()]
        if not done:
            continue
        method = "opencv" if "opencv" in done else done[0]
        est = Camera.load_json(trial.calibration(method, cam.name))
        det = CameraDetections.load(trial.detection(cam.name))
        z = read_arrays(trial.views(method, cam.name), "a calibration's views")
        view_ids, rvecs, tvecs = z["view_ids"], z["rvecs"], z["tvecs"]
        frames = np.isin(np.arange(ds.frames), view_ids)
        obs, _ = observations(det, ds.object_points, cam, frames)
        if list(obs.view_ids) != [int(v) for v in view_ids]:
            continue  # the views saved are not the detections' (a stale pair): no figure
        entry = {"diagnostics": {"views": view_outliers(est, obs, rvecs, tvecs),
                                 "coverage": coverage(obs)}}
        params = get_calibrator(method).model_parameters
        if params is not None:
            try:
                entry["uncertainty"] = {"projection": projection_uncertainty(
                    est, obs, rvecs, tvecs, params)}
            except (ValueError, np.linalg.LinAlgError):
                pass  # the panel says there is none
        results = {"methods": [method], "calibration": {method: {cam.name: entry}}}
        path = folder / f"views_{cam.name}.png"
        plot_capture_camera(results, Estimate(CalibrationResult(est, rvecs, tvecs), obs),
                            [f"frame {f}" for f in range(ds.frames)], path)
        paths.append(path)
    return paths


def plot_run(out: Path, trials: list[dict], agg: dict, workers=1) -> list[Path]:
    """Every plot of a run; the per-trial ones use the first trial. The figures are independent:
    with ``workers`` (a count, or the command's ``run.workers.Workers``) they are drawn that
    many at a time (matplotlib draws one figure at a time in a process)."""
    from ..run.workers import in_processes

    first = trials[0]
    jobs = [(str(out), first, agg, figure, camera)
            for figure, camera in run_figures(_first_dataset(Path(out), first))]
    return [path for paths in in_processes(_plot_job, jobs, workers) for path in paths]


def run_figures(ds: Dataset) -> list[tuple[str, str | None]]:
    """The figures ``plot_run`` draws for a run of ``ds``: (kind, camera name or None)."""
    return [("metrics", None), ("residuals", None), ("trajectory", None),
            *([("studio", None)] if ds.config.trajectory.kind == "session" else []),
            *[("projection", c.name) for c in ds.cameras],
            *[("views", c.name) for c in ds.cameras]]


def _first_dataset(out: Path, first: dict) -> Dataset:
    # The run's own copy, so that a run directory moved elsewhere still plots.
    own = RunPaths(out).trial(first["seed"]).dataset
    return Dataset.load(own.root if own.manifest.is_file() else first["dataset"])


def _plot_job(args) -> list[Path]:
    """One figure of ``plot_run`` (for ``camera``, the per-camera ones)."""
    out, first, agg, figure, camera = args
    folder = Path(out) / "plots"
    folder.mkdir(parents=True, exist_ok=True)
    trial = RunPaths(Path(out)).trial(first["seed"])
    ds = _first_dataset(Path(out), first)
    methods = first["methods"]
    if figure == "metrics":
        return [plot_metrics(agg, folder / "metrics.png")]
    if figure == "residuals":
        return [plot_residuals(trial, ds, methods, folder / "residuals.png")]
    if figure == "trajectory":
        return [plot_trajectory(ds.rig(), folder / "trajectory.png",
                                ds.config.trajectory.kind == "session")]
    if figure == "studio":
        return [plot_studio(trial, ds, folder / "studio.png")]
    cameras = [c for c in ds.cameras if c.name == camera]
    if figure == "projection":
        return plot_projection_maps(trial, ds, methods, folder, cameras)
    return plot_views(trial, ds, methods, folder, cameras)


def primary_method(results: dict, camera: str) -> str | None:
    """The estimate a capture's figures show: ``opencv`` when it calibrated the camera (the
    reference users know), else the first method that did."""
    ok = [m for m in results["methods"] if "error" not in results["calibration"][m].get(camera,
                                                                                       {"error"})]
    return "opencv" if "opencv" in ok else (ok[0] if ok else None)


def plot_capture_camera(results: dict, est, frame_names: list[str], path: Path) -> Path:
    """The four panels of ``capture_<camera>.png`` (module notes) for one Estimate."""
    cam, obs = est.result.camera, est.obs
    entry = results["calibration"][primary_method(results, cam.name)][cam.name]
    diag = entry["diagnostics"]
    fig, axes = plt.subplots(2, 2, dpi=DPI, figsize=(10, 7.2))
    ax = axes[0, 0]
    views = diag["views"]
    flagged = set(views["flagged"])
    colours = ["tab:red" if v in flagged else "tab:blue" for v in views["view_ids"]]
    ax.bar(range(len(views["rms_px"])), views["rms_px"], color=colours)
    # At most about 40 labelled ticks: a label per bar of a long capture is unreadable, and
    # laying out 127 of them took most of the figure's time (seconds per camera in a sweep).
    every = max(1, math.ceil(len(views["view_ids"]) / 40))
    ax.set_xticks(range(0, len(views["view_ids"]), every),
                  [frame_names[v].replace("frame ", "") for v in views["view_ids"][::every]],
                  fontsize=6, rotation=90)
    # Each view's own threshold (a view of few points is noisier, so it may fit worse).
    limit = np.array([np.nan if x is None else x for x in views["threshold_px"]], dtype=float)
    if np.isfinite(limit).any():
        ax.scatter(range(len(limit)), limit, marker="_", s=120, color="tab:red",
                   label="flagged above")
        ax.legend(fontsize=7)
    ax.set_xlabel("frame")
    ax.set_ylabel("RPE of the view (px)")
    ax.set_title(f"RPE per view (red: outliers); all views {views['rms_px_all']:.3f} px",
                 fontsize=8)

    ax = axes[0, 1]
    uv = np.concatenate(obs.image_points)
    proj = np.concatenate([project_points(o, cam.intrinsics, cam.dist, r, t, cam.model)
                           for o, r, t in zip(obs.object_points, est.result.rvecs,
                                              est.result.tvecs)])
    res = uv - proj
    norm = np.linalg.norm(res, axis=1)
    scale = 0.05 * max(cam.width, cam.height) / max(np.percentile(norm, 99), 1e-9)
    q = ax.quiver(uv[:, 0], uv[:, 1], res[:, 0] * scale, res[:, 1] * scale, norm,
                  angles="xy", scale_units="xy", scale=1, cmap="viridis", width=0.003)
    fig.colorbar(q, ax=ax, shrink=0.8, label="residual (px)")
    ax.set_xlim(0, cam.width - 1)
    ax.set_ylim(cam.height - 1, 0)
    ax.set_aspect("equal")
    ax.set_xlabel("u (px)")
    ax.set_ylabel("v (px)")
    ax.set_title(f"residuals x {scale:.0f}: detected - reprojected", fontsize=8)

    ax = axes[1, 0]
    cov = diag["coverage"]
    counts = np.array(cov["counts"], dtype=float)
    im = ax.imshow(np.where(counts > 0, counts, np.nan), extent=(0, cam.width, cam.height, 0),
                   cmap=plt.get_cmap("Blues").with_extremes(bad="0.85"))
    fig.colorbar(im, ax=ax, shrink=0.8, label="features per cell")
    ax.set_xlabel("u (px)")
    ax.set_ylabel("v (px)")
    ax.set_title(f"coverage: {cov['cell_fraction']:.0%} of cells (grey: none), hull "
                 f"{cov['hull_fraction']:.0%} of the image", fontsize=8)

    ax = axes[1, 1]
    proj_unc = entry.get("uncertainty", {}).get("projection")
    if proj_unc:
        m = np.array([[np.nan if x is None else x for x in row] for row in proj_unc["map_px"]])
        u, v = proj_unc["u"], proj_unc["v"]
        im = ax.imshow(m, extent=(u[0], u[-1], v[-1], v[0]),
                       norm=matplotlib.colors.LogNorm(vmin=np.nanmin(m), vmax=np.nanmax(m)),
                       cmap=plt.get_cmap("magma").with_extremes(bad="0.6"))
        fig.colorbar(im, ax=ax, shrink=0.8, label="1σ (px), log scale")
        ax.plot(uv[:, 0], uv[:, 1], ",", color="w", alpha=0.3)
        # The views capture.next_views suggests, numbered as the recapture lines list them.
        suggested = results.get("next_views", {}).get(cam.name, {}).get("views", [])
        for k, view in enumerate(suggested, 1):
            outline = np.array(view["outline_px"] + view["outline_px"][:1])
            ax.plot(outline[:, 0], outline[:, 1], "--", color="tab:cyan", lw=1.2)
            ax.text(*outline[:-1].mean(axis=0), str(k), color="tab:cyan", fontsize=9,
                    ha="center", va="center", fontweight="bold")
        ax.set_xlim(u[0], u[-1])
        ax.set_ylim(v[-1], v[0])
        ax.set_title(f"projection uncertainty at {proj_unc['distance_mm']:.0f} mm (dots: "
                     f"features{'; dashed: views to add' if suggested else ''})", fontsize=8)
    else:
        ax.set_title("no projection uncertainty for this method's model", fontsize=8)
    ax.set_xlabel("u (px)")
    ax.set_ylabel("v (px)")
    fig.suptitle(f"{cam.name}: {primary_method(results, cam.name)}", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return path


def plot_capture(results: dict, estimates: dict, frame_names: list[str], folder: Path
                 ) -> list[Path]:
    """``capture_<camera>.png`` for every camera some method calibrated."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for c in results["cameras"]:
        m = primary_method(results, c["name"])
        if m is not None:
            paths.append(plot_capture_camera(results, estimates[m, c["name"]], frame_names,
                                             folder / f"capture_{c['name']}.png"))
    return paths


def _spans_decades(values) -> bool:
    """Positive values whose largest is at least ten times their smallest: a log scale."""
    v = np.array([x for x in values if x is not None and np.isfinite(x)], float)
    return len(v) > 1 and (v > 0).all() and v.max() >= 10 * v.min()


def plot_sweep_curve(curve: dict, path: Path) -> Path:
    """One figure of a sweep's curve (``sweep_stats.curves``): a panel per metric, the mean over
    trials against the axis value with its 95 % Student-t interval as error bars, a line per
    method (or pattern). A numeric axis is drawn to scale; a categorical or list-valued one as
    evenly spaced categories (labelled by the value's text), the lines nudged apart so that
    their intervals do not hide each other."""
    import json

    metrics = list(curve["metrics"].values())
    cols = min(len(metrics), 2)
    rows = -(-len(metrics) // cols)
    many = max(len(m["lines"]) for m in metrics) > 6  # room for legends beside the panels
    fig, axes = plt.subplots(rows, cols, dpi=DPI, figsize=((5.2 + 2.6 * many) * cols, 3.8 * rows),
                             squeeze=False)
    for ax in axes.ravel()[len(metrics):]:
        ax.set_visible(False)
    values = curve["values"]
    numeric = curve["scale"] == "numeric"
    xs = np.array(values, float) if numeric else np.arange(len(values), dtype=float)
    log_x = numeric and _spans_decades(xs)
    for ax, metric in zip(axes.ravel(), metrics):
        lines = metric["lines"]
        means = [p.get("mean") for ln in lines for p in ln["points"]]
        log_y = metric["unit"] != "share of frames" and _spans_decades(means)
        # An interval reaching below zero cannot be drawn on a log axis: it is cut at a fifth
        # of the panel's smallest mean, and the panel says so.
        floor = 0.2 * min(m for m in means if m is not None and m > 0) if log_y else None
        cut = False
        for k, ln in enumerate(lines):
            pts = ln["points"]
            keep = [i for i, p in enumerate(pts) if p["n"] > 0 and p["mean"] is not None
                    and np.isfinite(p["mean"])]
            if not keep:
                continue
            mean = np.array([pts[i]["mean"] for i in keep], float)
            low = np.array([pts[i]["ci_low"] if pts[i]["n"] > 1 and pts[i]["ci_low"] is not None
                            else pts[i]["mean"] for i in keep], float)
            high = np.array([pts[i]["ci_high"] if pts[i]["n"] > 1 and pts[i]["ci_high"]
                             is not None else pts[i]["mean"] for i in keep], float)
            if log_y and (low < floor).any():
                low, cut = np.maximum(low, floor), True
            x = xs[keep]
            if not numeric:
                x = x + (k - (len(lines) - 1) / 2) * min(0.3 / max(len(lines), 1), 0.08)
            ax.errorbar(x, mean, yerr=[mean - low, high - mean], marker="o", ms=4, capsize=3,
                        lw=1.2, label=ln["label"])
        if log_y:
            ax.set_yscale("log")
        if log_x:
            ax.set_xscale("log")
        if metric["unit"] == "share of frames":
            ax.set_ylim(-0.03, 1.03)
        if not numeric:
            ax.set_xticks(xs, [v if isinstance(v, str) else json.dumps(v) for v in values],
                          rotation=20 if len(values) > 4 else 0, fontsize=8)
        ax.set_xlabel(curve["axis"])
        ax.set_ylabel(f"{metric['title']} ({metric['unit']})")
        ax.set_title(f"{metric['title']} ({metric['better']} is better)"
                     + (";\nintervals below the axis cut" if cut else ""), fontsize=9)
        ax.grid(True, alpha=0.3)
        if len(lines) > 6:  # many lines: the legend beside the panel, not over its data
            ax.legend(fontsize=6, loc="upper left", bbox_to_anchor=(1.01, 1.0),
                      ncol=1 + len(lines) // 13)
        elif ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)
        else:
            ax.text(0.5, 0.5, "no value (failed or not run)", ha="center", va="center",
                    transform=ax.transAxes, fontsize=8)
    held = ", ".join(f"{k} = {v}" for k, v in curve["held"].items())
    fig.suptitle(f"{held}: mean over trials, 95 % Student-t interval", fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=DPI, bbox_inches="tight")
    plt.close(fig)
    return path


def plot_compare(report: dict, path: Path) -> Path:
    """compare-tools.png: per figure, each tool's mean with its 95 % interval over the seeds
    (horizontal bars; log scale where the tools differ by decades)."""
    from .markdown import COMPARE_FIGURES

    table = {n: r for n, r in report["table"].items() if not r["skipped"] and r["seeds"]}
    shown = ("projection_difference_mean_px", "projection_difference_max_px", "rmse_cal_mm",
             "centre_error_mm")
    panels = [(k, f"{t} ({u})") for k, t, u in COMPARE_FIGURES
              if k in shown and (report["cameras"] > 1 or k.startswith("proj"))]
    costs = (report.get("pose") or {}).get("costs")
    rows = {k: {n: r["figures"][k] for n, r in table.items()} for k, _ in panels}
    if costs:
        panels.append(("pose", "pose cost (mm MPJPE)"))
        rows["pose"] = {n: costs.get(n, {}) for n in table}
    fig, axes = plt.subplots(1, len(panels), dpi=DPI,
                             figsize=(3.3 * len(panels), 0.45 * len(table) + 1.6), squeeze=False)
    names = list(table)
    seeds = len(report["seeds"])
    labels = [f"{n} ({table[n]['seeds']}/{seeds})" for n in names]
    for ax, (key, title) in zip(axes[0], panels):
        mean = np.array([np.nan if rows[key][n].get("mean") is None else rows[key][n]["mean"]
                         for n in names], float)
        lo = np.array([rows[key][n].get("ci_low") for n in names], dtype=float)
        hi = np.array([rows[key][n].get("ci_high") for n in names], dtype=float)
        positive = mean[np.isfinite(mean) & (mean > 0)]
        log = len(positive) > 1 and positive.max() / positive.min() >= 10
        if log:  # an interval reaching below zero is drawn down to a tenth of its mean
            lo = np.maximum(lo, 0.1 * mean)
        err = np.where(np.isfinite(lo), [mean - lo, hi - mean], 0.0)
        ax.barh(range(len(names)), mean, xerr=err, capsize=3, color="tab:blue", alpha=0.8)
        ax.set_yticks(range(len(names)), labels if ax is axes[0][0] else [""] * len(names),
                      fontsize=8)
        ax.invert_yaxis()
        if log:
            ax.set_xscale("log")
        ax.set_title(title, fontsize=9)
        ax.tick_params(axis="x", labelsize=7)
    fig.suptitle(f"{report['rig']}, {report['pattern']} board, {report['environment']} imaging: "
                 f"mean and 95 % interval over the seeds each tool calibrated (of {seeds})",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=DPI, bbox_inches="tight")
    plt.close(fig)
    return path


def plot_study(curves: list[dict], share: float, path: Path) -> Path:
    """A study's answer for one studio (``run.study.cost_curve`` per detector): each
    calibration's pose cost against its RMSE_cal (left) and its rig's reprojection error
    (right), one colour per detector, one marker per method; a calibration (configuration and
    method) is its mean over seeds with the 95 % Student-t interval of the cost; on the left the
    fitted model and, dotted, the RMSE_cal where the cost reaches ``share`` of the floor."""
    from scipy import stats

    markers = "osD^v<>pX*h"
    fig, axes = plt.subplots(1, 2, dpi=DPI, figsize=(12, 4.6))
    methods = list(dict.fromkeys(p["method"] for c in curves for p in c["points"]))
    for ci, curve in enumerate(curves):
        colour = f"C{ci}"
        groups: dict = {}
        for p in curve["points"]:
            groups.setdefault((p["configuration"], p["method"]), []).append(p)
        for (_, method), pts in groups.items():
            cost = np.array([p["cost_mm"] for p in pts], float)
            half = (stats.t.ppf(0.975, len(cost) - 1) * cost.std(ddof=1) / np.sqrt(len(cost))
                    if len(cost) > 1 else 0.0)
            for ax, key in zip(axes, ("rmse_cal_mm", "rig_rpe_px")):
                x = np.array([p[key] if p[key] is not None else np.nan for p in pts], float)
                if np.isfinite(x).any():
                    ax.errorbar(np.nanmean(x), cost.mean(), yerr=half, color=colour, capsize=2,
                                marker=markers[methods.index(method) % len(markers)], ms=5,
                                lw=1, alpha=0.85)
        if "k" in curve:
            lo, hi = curve["rmse_cal_range_mm"]
            reach = curve.get("threshold_rmse_cal_mm", lo)
            r = np.geomspace(max(min(lo, reach) / 2, 1e-3), max(hi, reach) * 1.2, 200)
            F = curve["floor_mm"]
            axes[0].plot(r, np.sqrt(F ** 2 + (curve["k"] * r) ** 2) - F, color=colour, lw=1.2,
                         label=f"{curve['detector']}: floor {F:.1f} mm")
            if "threshold_rmse_cal_mm" in curve:
                axes[0].axvline(curve["threshold_rmse_cal_mm"], color=colour, ls=":", lw=1.2)
    for m in methods:
        axes[1].plot([], [], ls="", color="0.3", marker=markers[methods.index(m) % len(markers)],
                     label=m)
    axes[0].set_xlabel("RMSE_cal (mm)")
    axes[1].set_xlabel("rig reprojection error (px)")
    for ax in axes:
        xs = [x for line in ax.lines for x in np.atleast_1d(line.get_xdata()) if x > 0]
        if _spans_decades(xs):
            ax.set_xscale("log")
        # Costs span decades and a near-perfect calibration's paired cost can dip below zero.
        ax.set_yscale("symlog", linthresh=0.1)
        ys = [y for line in ax.lines for y in np.atleast_1d(line.get_ydata())
              if np.isfinite(y)]
        ax.set_ylim(bottom=min(min(ys, default=0.0), 0.0))
        ax.set_ylabel("pose cost: MPJPE minus the true cameras' (mm)")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
    studio = curves[0]["studio"] if curves else ""
    axes[0].set_title(f"{studio}: pose cost against calibration error; dotted: where it "
                      f"reaches {share:.0%} of the floor", fontsize=9)
    axes[1].set_title("the same against what the calibration reports", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return path
