"""mrcal's own calibration tool, as its users run it: ``mrcal-calibrate-cameras`` on a corners
file, with LENSMODEL_OPENCV8 (mrcal's recommended OpenCV model for a lens that is not wide; its
splined models cannot be read back into the suite's camera model, so they are not scored here).

mrcal has no wheel for Python < 3.12: it runs in its own environment (``make mrcal-env``, with
OpenCV, which its seeding uses), found at SYNTHCAL_MRCAL_PYTHON or .venv/mrcal.

* The corners file (mrcal's vnlog ``# filename x y level``): one row per board point in mrcal's
  order (row-major, x fastest: the order of the board's points here, ``Session.grid``), "- - -"
  for a point not detected; image names ``frame<f>-cam<c>.png`` (never on disk), one glob per
  camera. A view with 2 min(W, H) points or fewer is left out, as mrcal-calibrate-cameras would
  drop it silently; so the frames of its solve are known.
* The options: ``--focal`` from OpenCV's closed-form guess (cv2.initCameraMatrix2D on camera 0's
  views; a user's rough focal, not the truth), ``--object-spacing`` in mm (the extrinsics come
  back in mm), ``--object-width-n``/``--object-height-n``, ``--imagersize`` (or blank images of
  each camera's size when the sizes differ), every other setting mrcal's default (outlier
  rejection, regularization, the board's warp fitted).
* The answer: ``camera-<i>.cameramodel``, read back with io.mrcal.
* Its uncertainty: mrcal.projection_uncertainty at the probe pixels (tools.probe_pixels) at the
  median distance of the boards, with the board poses of its solve (mrcal_worker.py); where mrcal
  cannot compute it (a singular solve: a board whose every point its outlier rejection dropped
  leaves that board's pose free), its message.
"""

from __future__ import annotations

import json
import os
import subprocess
import time
from pathlib import Path

import cv2
import numpy as np

from ..core.files import write_text
from ..io.mrcal import read_camera
from . import Session, ToolError, ToolResult, probe_pixels

NAME = ("mrcal",)
ABOUT = "mrcal-calibrate-cameras, LENSMODEL_OPENCV8, mrcal's defaults (mrcal 2.5)"
LENSMODEL = "LENSMODEL_OPENCV8"
TIMEOUT_S = 1800


def python() -> Path:
    return Path(os.environ.get("SYNTHCAL_MRCAL_PYTHON") or
                Path(__file__).resolve().parents[2] / ".venv" / "mrcal" / "bin" / "python")


def missing() -> str | None:
    exe = python()
    tool = exe.parent / "mrcal-calibrate-cameras"
    if not exe.is_file() or not tool.is_file():
        return (f"no mrcal environment at {exe.parent.parent} (`make mrcal-env`, which needs a "
                f"python3.12 or newer; or set SYNTHCAL_MRCAL_PYTHON)")
    done = subprocess.run([str(exe), "-c", "import mrcal, cv2"], capture_output=True)
    if done.returncode != 0:
        return f"{exe} cannot import mrcal and cv2 (`make mrcal-env` installs both)"
    return None


def _corners(session: Session, width_n: int, height_n: int) -> tuple[str, list[int]]:
    """The corners file's text and the frames it holds (the frames of mrcal's solve, in
    order)."""
    keep = np.isfinite(session.image_points).all(-1) & session.found[..., None]
    enough = keep.sum(-1) > 2 * min(width_n, height_n)  # (C, F)
    frames = np.flatnonzero(enough.any(0)).tolist()
    rows = ["# filename x y level"]
    for f in frames:
        for c in np.flatnonzero(enough[:, f]):
            name = f"frame{f:05d}-cam{c}.png"
            for p, ok in zip(session.image_points[c, f], keep[c, f]):
                rows.append(f"{name} {p[0]:.6f} {p[1]:.6f} 0" if ok else f"{name} - - -")
    return "\n".join(rows) + "\n", frames


def _focal(session: Session) -> float:
    full = np.flatnonzero(session.full_views()[0])
    if not len(full):
        raise ToolError("mrcal: camera 0 has no view of the whole board to guess --focal from")
    obj = [session.object_points.astype(np.float32)] * len(full)
    img = [session.image_points[0, f].astype(np.float32) for f in full]
    K = cv2.initCameraMatrix2D(obj, img, session.sizes[0])
    return float(np.sqrt(K[0, 0] * K[1, 1]))


def calibrate(session: Session, out_dir: Path, name: str = "mrcal") -> ToolResult:
    width_n, height_n, spacing = session.grid()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    text, frames = _corners(session, width_n, height_n)
    corners = write_text(out_dir / "corners.vnl", text)
    cmd = [str(python().parent / "mrcal-calibrate-cameras"), "--corners-cache", str(corners),
           "--lensmodel", LENSMODEL, "--focal", f"{_focal(session):.3f}",
           "--object-spacing", repr(spacing), "--object-width-n", str(width_n),
           "--object-height-n", str(height_n), "--outdir", str(out_dir)]
    if len(set(session.sizes)) == 1:
        cmd += ["--imagersize", *map(str, session.sizes[0])]
    else:  # --imagersize is one size for all: blank images say each camera's
        for c, size in enumerate(session.sizes):
            for f in frames:
                cv2.imwrite(str(out_dir / f"frame{f:05d}-cam{c}.png"),
                            np.zeros(size[::-1], np.uint8))
        cmd += ["--image-directory", str(out_dir)]
    cmd += [f"frame*-cam{c}.png" for c in range(len(session.names))]
    t0 = time.perf_counter()
    try:
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=TIMEOUT_S)
    except subprocess.TimeoutExpired:
        raise ToolError(f"mrcal: mrcal-calibrate-cameras ran past {TIMEOUT_S} s") from None
    elapsed = time.perf_counter() - t0
    write_text(out_dir / "tool.log", done.stdout + done.stderr)  # what its users read
    models = [out_dir / f"camera-{c}.cameramodel" for c in range(len(session.names))]
    if done.returncode != 0 or not all(m.is_file() for m in models):
        last = (done.stderr.strip().splitlines() or ["no message"])[-1]
        raise ToolError(f"mrcal: mrcal-calibrate-cameras failed ({last}; {out_dir}/tool.log)")
    cams = [read_camera(m).with_params(name=n) for m, n in zip(models, session.names)]
    said = done.stdout + done.stderr
    # Boards its outlier rejection emptied (mrcal warns that their poses are then free).
    log = {"command": " ".join(cmd[1:]), "frames": len(frames),
           "boards_thrown_out": said.count("had almost all of its points thrown out")}
    return ToolResult(cams, out_dir, "mrcal", elapsed, log,
                      _uncertainty(session, models, cams, frames, out_dir))


def _uncertainty(session: Session, models, cams, frames: list[int], out_dir: Path) -> dict:
    """mrcal's projection covariance per camera (module notes), or its message saying why it
    could not compute it."""
    pixels = [probe_pixels(*c.size) for c in cams]
    # The median distance of the boards' centres from each camera, through mrcal's own poses.
    request = {"models": [str(m) for m in models], "pixels": [p.tolist() for p in pixels],
               "distance": [1.0] * len(cams)}
    first = _worker(request, out_dir)
    centre = session.object_points.mean(0)
    distance = []
    for entry in first["cameras"]:
        rt = np.array(list(entry["board_poses"].values()), float)
        R = np.array([cv2.Rodrigues(r)[0] for r in rt[:, :3]])
        distance.append(float(np.median(np.linalg.norm(R @ centre + rt[:, 3:], axis=-1))))
    request["distance"] = distance
    reply = _worker(request, out_dir)
    out = {}
    for cam, entry, uv, d in zip(cams, reply["cameras"], pixels, distance):
        if entry.get("covariance") is None:
            out[cam.name] = {"error": f"mrcal: {entry.get('error')}"}
            continue
        poses = {frames[int(i)]: (np.array(rt[:3]), np.array(rt[3:]))
                 for i, rt in entry["board_poses"].items()}
        out[cam.name] = {"projection": {"pixels": uv, "distance_mm": d,
                                        "covariance": np.array(entry["covariance"]),
                                        "board_poses": poses}}
    return out


def _worker(request: dict, out_dir: Path) -> dict:
    path = write_text(out_dir / "uncertainty_request.json", json.dumps(request))
    # -P: not the worker's own folder on sys.path, where this module would shadow mrcal's.
    done = subprocess.run([str(python()), "-P", str(Path(__file__).with_name("mrcal_worker.py")),
                           str(path)], capture_output=True, text=True, timeout=TIMEOUT_S)
    if done.returncode != 0:
        raise ToolError(f"mrcal: its projection uncertainty failed: "
                        f"{(done.stderr.strip().splitlines() or ['no message'])[-1]}")
    return json.loads(done.stdout)
