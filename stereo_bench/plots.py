"""Plots of a run a person would rather look at than read (matplotlib, Agg backend).

* ``metrics.png``: per-method bars with error bars over trials (RPE_RMS, projection
  difference, RMSE_cal);
* ``residuals.png``: the distribution of reprojection residuals per method (first trial);
* ``trajectory.png``: the board's path and the cameras in 3D;
* ``projection_difference_<camera>.png``: the map over the image of how far each method's
  estimate projects the true camera's rays.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from .camera import Camera, project_points  # noqa: E402
from .dataset import Dataset  # noqa: E402
from .detect import CameraDetections  # noqa: E402
from .metrics import projection_difference_map  # noqa: E402
from .rundir import RunPaths, TrialPaths  # noqa: E402


def _bars(ax, agg_rows: dict, column: str, title: str) -> None:
    names = list(agg_rows)
    mean = [agg_rows[n][column]["mean"] for n in names]
    std = [agg_rows[n][column]["std"] for n in names]
    ax.bar(range(len(names)), mean, yerr=std, capsize=4, color="tab:blue", alpha=0.8)
    ax.set_xticks(range(len(names)), names, rotation=30, ha="right", fontsize=8)
    ax.set_title(title, fontsize=9)


def plot_metrics(agg: dict, path: Path) -> Path:
    cams = list(agg["detection"])
    panels = [("RPE_RMS px", "RPE_RMS (px)"), ("proj. diff mean px", "projection diff. (px)")]
    n = len(panels) * len(cams) + (1 if "rig" in agg else 0)
    fig, axes = plt.subplots(1, n, figsize=(3.2 * n, 3.4), squeeze=False)
    axes = axes[0]
    i = 0
    for cam in cams:
        rows = {m: agg["calibration"][m][cam] for m in agg["calibration"]}
        for column, title in panels:
            _bars(axes[i], rows, column, f"{cam}: {title}")
            i += 1
    if "rig" in agg:
        _bars(axes[i], agg["rig"], "RMSE_cal mm", "RMSE_cal (mm)")
    fig.suptitle(f"mean ± std over {agg['trials']} trial(s)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def residuals(trial: TrialPaths, ds: Dataset, method: str) -> np.ndarray:
    """Reprojection residual norms (px) of one method over all cameras and views of a trial."""
    out = []
    for cam in ds.cameras:
        if not trial.calibration(method, cam.name).is_file():
            continue
        est = Camera.load_json(trial.calibration(method, cam.name))
        det = CameraDetections.load(trial.detection(cam.name))
        with np.load(trial.views(method, cam.name)) as z:
            for f, r, t in zip(z["view_ids"], z["rvecs"], z["tvecs"]):
                ok = np.isfinite(det.points[f]).all(1)
                uv = project_points(ds.object_points[ok], est.intrinsics, est.dist, r, t)
                out.append(np.linalg.norm(uv - det.points[f, ok], axis=1))
    return np.concatenate(out) if out else np.zeros(0)


def plot_residuals(trial: TrialPaths, ds: Dataset, methods: list[str], path: Path) -> Path:
    fig, ax = plt.subplots(figsize=(6, 3.6))
    for m in methods:
        r = residuals(trial, ds, m)
        if len(r):
            ax.hist(r, bins=np.geomspace(max(r.min(), 1e-4), r.max() + 1e-9, 60),
                    histtype="step", label=f"{m} (RMS {np.sqrt(np.mean(r**2)):.3f})")
    ax.set_xscale("log")
    ax.set_xlabel("reprojection residual (px)")
    ax.set_ylabel("points")
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=8)
    else:
        ax.set_title("no method calibrated a camera", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_trajectory(ds: Dataset, path: Path) -> Path:
    rig = ds.rig()
    pts = rig.board_points_world()
    fig = plt.figure(figsize=(6, 5))
    ax = fig.add_subplot(projection="3d")
    centre = pts.mean(1)
    ax.plot(centre[:, 0], centre[:, 2], -centre[:, 1], "-", color="tab:blue", lw=1,
            label="board centre")
    corners = [0, -1]
    for f in range(0, len(pts), max(1, len(pts) // 12)):
        p = pts[f]
        ax.plot(p[corners, 0], p[corners, 2], -p[corners, 1], color="gray", lw=0.6)
    scale = 0.15 * np.ptp(centre[:, 2]) + 30
    for cam in ds.cameras:
        c = cam.center
        w, h = cam.width - 1, cam.height - 1
        rays = cam.unproject_rays(np.array([[0, 0], [w, 0], [w, h], [0, h]], float))
        corners_w = c + scale * (rays / rays[:, 2:]) @ cam.R
        for q in corners_w:
            ax.plot([c[0], q[0]], [c[2], q[2]], [-c[1], -q[1]], color="tab:red", lw=0.8)
        loop = np.vstack([corners_w, corners_w[:1]])
        ax.plot(loop[:, 0], loop[:, 2], -loop[:, 1], color="tab:red", lw=0.8)
        ax.text(c[0], c[2], -c[1], cam.name, fontsize=7)
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("z (mm)")
    ax.set_zlabel("-y (mm)")
    ax.set_title("board trajectory (conical spring) and cameras", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_projection_maps(trial: TrialPaths, ds: Dataset, methods: list[str],
                         folder: Path) -> list[Path]:
    paths = []
    for cam in ds.cameras:
        truth = cam.with_params(rvec=np.zeros(3), tvec=np.zeros(3))
        ests = {m: trial.calibration(m, cam.name) for m in methods}
        ests = {m: Camera.load_json(p) for m, p in ests.items() if p.is_file()}
        if not ests:
            continue
        fig, axes = plt.subplots(1, len(ests), figsize=(3.6 * len(ests), 3.0), squeeze=False)
        for ax, (m, est) in zip(axes[0], ests.items()):
            diff = projection_difference_map(est, truth)
            # Colour scale to the 99th percentile: a few corner pixels where an estimate's model
            # breaks down would otherwise leave the rest of the map black. Grey: where the
            # estimate is not valid (it folds or has a pole; left out of the statistics).
            cmap = plt.get_cmap("magma").with_extremes(bad="0.6")
            valid = np.isfinite(diff)
            vmax = np.percentile(diff[valid], 99) if valid.any() else 1.0
            im = ax.imshow(diff, extent=(0, cam.width - 1, cam.height - 1, 0), cmap=cmap,
                           vmax=vmax)
            note = "" if valid.all() else f", {1 - valid.mean():.1%} invalid (grey)"
            title = (f"{m}: mean {np.nanmean(diff):.3g}, max {np.nanmax(diff):.3g} px{note}"
                     if valid.any() else f"{m}: invalid over the whole image")
            ax.set_title(title, fontsize=8)
            ax.tick_params(labelsize=6)
            fig.colorbar(im, ax=ax, shrink=0.8).ax.tick_params(labelsize=6)
        fig.suptitle(f"{cam.name}: |estimate - truth| projection difference (px)", fontsize=9)
        fig.tight_layout()
        path = folder / f"projection_difference_{cam.name}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        paths.append(path)
    return paths


def plot_run(out: Path, trials: list[dict], agg: dict) -> list[Path]:
    """Every plot of a run; the per-trial ones use the first trial."""
    folder = Path(out) / "plots"
    folder.mkdir(parents=True, exist_ok=True)
    first = trials[0]
    trial = RunPaths(Path(out)).trial(first["seed"])
    # The run's own copy, so that a run directory moved elsewhere still plots.
    own = trial.dataset
    ds = Dataset.load(own.root if own.manifest.is_file() else first["dataset"])
    methods = first["methods"]
    return [plot_metrics(agg, folder / "metrics.png"),
            plot_residuals(trial, ds, methods, folder / "residuals.png"),
            plot_trajectory(ds, folder / "trajectory.png"),
            *plot_projection_maps(trial, ds, methods, folder)]
