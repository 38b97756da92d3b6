"""mrcal's own calibration tool, as its users run it: ``mrcal-calibrate-cameras`` on a corners
file, with LENSMODEL_OPENCV8 (``mrcal``) or its splined stereographic model (``mrcal-splined``,
LENSMODEL_SPLINED_STEREOGRAPHIC_order=3, 16 knots across and as many down as the image's aspect
keeps square, over 1.6 times the horizontal field OpenCV's focal guess gives).

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
* The answer: ``camera-<i>.cameramodel``, read back with io.mrcal. A splined lens has no form
  in the suite's camera model: its ToolResult has no cameras but a ``proxy`` that scores it
  through mrcal's own projection (``splined_proxy``).
* Its uncertainty: mrcal.projection_uncertainty at the probe pixels (tools.probe_pixels) at the
  median distance of the boards, with the board poses of its solve (mrcal_worker.py); where mrcal
  cannot compute it (a singular solve: a board whose every point its outlier rejection dropped
  leaves that board's pose free), its message.
"""

from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path

import cv2
import numpy as np

from ..core.camera import Camera
from ..core.files import write_text
from ..core.poses import matrix_to_rodrigues, rodrigues_to_matrix
from ..io import common
from ..io.mrcal import read_camera, read_model
from . import Session, ToolError, ToolResult, environment_python, probe_pixels

ABOUT = {"mrcal": "mrcal-calibrate-cameras, LENSMODEL_OPENCV8, mrcal's defaults (mrcal 2.5)",
         "mrcal-splined": "mrcal-calibrate-cameras, LENSMODEL_SPLINED_STEREOGRAPHIC (order 3, "
                          "16 knots across), mrcal's defaults; scored through mrcal's projection"}
LENSMODEL = "LENSMODEL_OPENCV8"
SPLINE_KNOTS_X = 16
#: The spline's horizontal field over the lens's: its knots must reach the image's corners
#: after the camera frame's gauge rotation (the splined core stays at mrcal's seed).
SPLINE_FIELD_MARGIN = 1.6
TIMEOUT_S = 1800


def python() -> Path:
    return environment_python("SYNTHCAL_MRCAL_PYTHON", "mrcal")


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


def lensmodel(name: str, session: Session, focal: float) -> str:
    if name == "mrcal":
        return LENSMODEL
    width, height = session.sizes[0]
    field = SPLINE_FIELD_MARGIN * 2 * np.degrees(np.arctan2(width / 2, focal))
    ny = max(2, round(SPLINE_KNOTS_X * height / width))
    return (f"LENSMODEL_SPLINED_STEREOGRAPHIC_order=3_Nx={SPLINE_KNOTS_X}_Ny={ny}_"
            f"fov_x_deg={int(np.ceil(field))}")


def calibrate(session: Session, out_dir: Path, name: str = "mrcal") -> ToolResult:
    width_n, height_n, spacing = session.grid()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    text, frames = _corners(session, width_n, height_n)
    corners = write_text(out_dir / "corners.vnl", text)
    focal = _focal(session)
    lens = lensmodel(name, session, focal)
    cmd = [str(python().parent / "mrcal-calibrate-cameras"), "--corners-cache", str(corners),
           "--lensmodel", lens, "--focal", f"{focal:.3f}",
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
        lines = done.stderr.strip().splitlines() or ["no message"]
        # Its own error line, not the matrix it prints after it.
        last = next((ln.strip() for ln in lines if ln.startswith("Exception")), lines[-1])
        raise ToolError(f"mrcal: mrcal-calibrate-cameras failed ({last}; {out_dir}/tool.log)")
    said = done.stdout + done.stderr
    # Boards its outlier rejection emptied (mrcal warns that their poses are then free).
    log = {"command": " ".join(cmd[1:]), "frames": len(frames),
           "boards_thrown_out": said.count("had almost all of its points thrown out")}
    if name == "mrcal-splined":
        return ToolResult([], out_dir, "mrcal", elapsed, log,
                          proxy=splined_proxy(models, session, out_dir))
    cams = [read_camera(m).with_params(name=n) for m, n in zip(models, session.names)]
    return ToolResult(cams, out_dir, "mrcal", elapsed, log,
                      _uncertainty(session, models, cams, frames, out_dir))


def _uncertainty(session: Session, models, cams, frames: list[int], out_dir: Path) -> dict:
    """mrcal's projection covariance per camera (module notes), or its message saying why it
    could not compute it."""
    pixels = [probe_pixels(*c.size) for c in cams]
    # The median distance of the boards' centres from each camera, through mrcal's own poses.
    request = {"mode": "uncertainty", "models": [str(m) for m in models],
               "pixels": [p.tolist() for p in pixels],
               "distance": [1.0] * len(cams)}
    first = _worker(request, out_dir)
    centre = session.object_points.mean(0)
    distance = []
    for entry in first["cameras"]:
        poses = _board_frame(entry["board_poses"], session.object_points[0]).values()
        distance.append(float(np.median([np.linalg.norm(rodrigues_to_matrix(r) @ centre + t)
                                         for r, t in poses])))
    request["distance"] = distance
    reply = _worker(request, out_dir)
    out = {}
    for cam, entry, uv, d in zip(cams, reply["cameras"], pixels, distance):
        if entry.get("covariance") is None:
            out[cam.name] = {"error": f"mrcal: {entry.get('error')}"}
            continue
        poses = {frames[int(i)]: pose for i, pose in
                 _board_frame(entry["board_poses"], session.object_points[0]).items()}
        out[cam.name] = {"projection": {"pixels": uv, "distance_mm": d,
                                        "covariance": np.array(entry["covariance"]),
                                        "board_poses": poses}}
    return out


def _board_frame(board_poses: dict, origin: np.ndarray) -> dict:
    """mrcal's cam_from_board poses {index: rt} in the session's board frame: mrcal's board has
    its first point at its origin, the session's at ``origin`` (a ChArUco board's first corner
    is one square in), so p_mrcal = p_session - origin and t_session = t - R origin."""
    out = {}
    for i, rt in board_poses.items():
        r, t = np.asarray(rt[:3], float), np.asarray(rt[3:], float)
        out[i] = (r, t - rodrigues_to_matrix(r) @ origin)
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


def _rt_cam_ref(path: Path) -> np.ndarray:
    """rt_cam_ref of a .cameramodel, whatever its lens (io.mrcal reads only the OpenCV ones)."""
    model = read_model(path)
    return common.numbers(model.get("rt_cam_ref", model.get("extrinsics")), (6,),
                          f"{path}: rt_cam_ref")


def splined_proxy(models, session: Session, out_dir: Path):
    """Scoring of a lens the suite's camera model cannot hold (a splined one), through mrcal's
    own projection: ``proxy(truth, image_points) -> (cameras, points, projection)``.

    Its camera frames are a gauge (the spline absorbs any rotation of them, and mrcal keeps the
    core at its seed): each is first turned by the rotation R_c that best maps its rays of the
    detected pixels onto the true camera's rays of the same pixels (mrcal's Procrustes fit;
    where no board was seen the spline extrapolates, and is not trusted for the fit).
    ``cameras`` are then ideal pinholes (the true camera's focal length, no distortion,
    centred) with the rig's poses turned likewise, and ``points`` the detections' rays through
    the spline seen through them: triangulating those is triangulating the spline's rays, with
    residuals weighed as the camera's pixels. ``projection``, per camera: how far the spline
    projects each true ray of a grid of pixels (64 x 48, as evaluate.metrics) from its pixel,
    after R_c (``mean_px``, ``max_px``) and as written (``direct_mean_px``,
    ``direct_max_px``), and R_c's angle."""
    from ..evaluate.metrics import grid_pixels

    def unit_rays(camera, uv):
        rays = np.column_stack([camera.unproject(uv), np.ones(len(uv))])
        return rays / np.linalg.norm(rays, axis=1, keepdims=True)

    def proxy(truth, image_points):
        grids = [grid_pixels(t, (64, 48)) for t in truth]
        seen = np.isfinite(image_points).all(-1)
        pixels = [image_points[c][seen[c]] for c in range(len(truth))]
        request = {"mode": "lens", "models": [str(m) for m in models],
                   "true_rays": [unit_rays(t, g).tolist() for t, g in zip(truth, grids)],
                   "grid": [g.tolist() for g in grids],
                   "pixels": [p.tolist() for p in pixels],
                   "pixel_rays": [unit_rays(t, p).tolist() for t, p in zip(truth, pixels)]}
        reply = _worker(request, out_dir)["cameras"]
        turns = [np.asarray(e["R"], dtype=float) for e in reply]
        rt = [_rt_cam_ref(m) for m in models]
        R0 = turns[0] @ rodrigues_to_matrix(rt[0][:3])  # the true camera 0's from mrcal's ref
        cams, points, projection = [], np.full(image_points.shape, np.nan), []
        for c, (t, e, Rc) in enumerate(zip(truth, reply, turns)):
            Re = rodrigues_to_matrix(rt[c][:3])
            R = Rc @ Re @ R0.T  # true-gauge cam_c from true-gauge cam_0
            tvec = Rc @ rt[c][3:] - R @ (turns[0] @ rt[0][3:])
            cams.append(Camera(session.names[c], *session.sizes[c], t.fx, t.fx, 0.0, 0.0, 0.0,
                               np.zeros(8), matrix_to_rodrigues(R), tvec))
            rays = np.asarray(e["rays"], dtype=float).reshape(-1, 3) @ Rc.T
            ahead = rays[:, 2] > 0
            uv = np.full((len(rays), 2), np.nan)
            uv[ahead] = t.fx * rays[ahead, :2] / rays[ahead, 2:]
            points[c][seen[c]] = uv
            direct, turned = np.asarray(e["direct"]), np.asarray(e["compensated"])
            projection.append({"mean_px": float(turned.mean()), "max_px": float(turned.max()),
                               "direct_mean_px": float(direct.mean()),
                               "direct_max_px": float(direct.max()),
                               "rotation_deg": float(np.degrees(np.linalg.norm(
                                   matrix_to_rodrigues(Rc))))})
        return cams, points, projection

    return proxy
