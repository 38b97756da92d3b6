"""pycolmap's bundle adjuster as a reference for the studio rig calibration (bundle.py).

``bundle.calibrate_rig`` refines one cam_from_cam0 per camera (camera 0's is the identity) and
one cam0_from_board per frame by minimizing the summed squared pixel reprojection errors of the
board points. :func:`colmap_rig_bundle` hands the same observations, from the same start
(``bundle.rig_start``), to COLMAP's own bundle adjuster (Ceres), so that the two can be compared
number for number, as ``calibrate/opencv_ref.py`` is the reference for single cameras. It is a
reference and a baseline, not the project's solver.

The embedding, and why it is exact
----------------------------------
COLMAP's "world" is the BOARD frame:

* the board's N feature points are N COLMAP 3D points at their known metric coordinates
  (``object_points``), shared by every frame and held constant: they fix the scale and the gauge
  and keep the board rigid, so no structure is triangulated or estimated;
* the cameras are the sensors of one COLMAP Rig; camera 0 is its reference sensor (its
  sensor_from_rig is the identity by construction, not a parameter), every other camera's
  sensor_from_rig is its cam_from_cam0 (free);
* each time step f the board is used in is one COLMAP Frame of that rig, with
  rig_from_world = cam0_from_board(f) (free);
* each (camera, frame) where the camera saw the board is one COLMAP Image holding the detected
  points, each linked to the board point it observes.

COLMAP's residual of an observation x of board point X by camera c in frame f is then
``img_from_cam(sensor_from_rig(c) * rig_from_world(f) * X) - x``, unweighted, i.e. the project's
``project(cam_from_cam0(c) * cam0_from_board(f) * X) - x``, and Ceres minimizes half its
squared norm summed over all observations: the cost ``calibrate_rig`` minimizes, over the same
parameters (COLMAP steps rotations on the unit-quaternion manifold, the project on Rodrigues
vectors; the minimum is the same).

Camera model. The project's Camera (OpenCV's model, coefficients [k1, k2, p1, p2, k3, k4, k5, k6])
becomes COLMAP's FULL_OPENCV (params fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6, the same
distortion formula), or OPENCV (fx, fy, cx, cy, k1, k2, p1, p2) when k3..k6 are all zero.
COLMAP has no skew: a camera with skew != 0 is refused.

Pixel convention. COLMAP puts the image origin at the top-left CORNER of the top-left pixel (that
pixel's centre is (0.5, 0.5)); the project follows OpenCV (its centre is (0, 0)). On the way in
both the principal point and every observation are shifted by ``PIXEL_SHIFT`` = +0.5 px in u and
v, and on the way out the principal point by -0.5 px. The residual is unchanged,
``f xd + (c + 0.5) - (x + 0.5) = f xd + c - x``, so the reconstruction is a valid COLMAP model
(it can be written and opened with COLMAP's tools) and the cost is exactly the project's. Shifting
one side and not the other is a 0.5 px error in u and v that the poses largely absorb (tests).

Subset supported
----------------
C >= 2 cameras with zero skew; a rigid target of known geometry. A camera counts in a frame
when ``seen`` and it detected at least MIN_POINTS_PER_VIEW points. With intrinsics fixed (the
default) the frames seen by two or more cameras are used (a frame seen by one camera says nothing
about the rig); with ``refine_intrinsics`` every frame seen by one or more, and fx, fy, cx, cy and
every distortion coefficient of the chosen COLMAP model are refined (k1..k6, p1, p2 for
FULL_OPENCV, which planar views do not identify: compare such cameras in projection space). A
board point observed only once in the whole problem is left out, COLMAP requiring tracks of two
or more observations (and so, in turn, any view or frame that falls below its minimum); the log
counts the observations left out. Every camera must be joined to camera 0 through frames seen
together. Losses: trivial (alias "linear"), soft_l1, huber, cauchy with a scale in px; COLMAP
applies them to the squared norm of each observation's 2-vector residual, where scipy's
least_squares (calibrate_rig) applies its own to each coordinate: only the trivial loss is the
same cost in both.

Solver settings: Ceres' function, gradient and parameter tolerances default to 1e-15 (a
reference should sit at the minimum: on the test studio with 0.3 px noise a Gauss-Newton step
from its solution moves the rig by ~4e-8 mm; at 1e-12 by ~4e-5 mm), and one thread (Ceres'
threaded reductions change the last digits, and so the number of steps, with the thread count).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..calibrate.base import MIN_POINTS_PER_VIEW
from ..core.camera import Camera
from ..core.poses import matrix_to_rodrigues, rodrigues_to_matrix
from ..io.colmap import colmap_model, from_colmap_camera, from_rigid3d, opencv_to_colmap_pixels
from .bundle import RigCalibration, covisibility, reprojection_rms, rig_cameras, unreachable

LOSSES = ("trivial", "soft_l1", "huber", "cauchy")
_LOSS_TYPES = {"trivial": "TRIVIAL", "soft_l1": "SOFT_L1", "huber": "HUBER", "cauchy": "CAUCHY"}


def _pycolmap():
    try:
        import pycolmap
    except ImportError as e:
        raise ImportError(
            f"stereo_bench.multiview.colmap_ref needs pycolmap, which is not importable ({e}); "
            f"pip install pycolmap") from None
    return pycolmap


# ----------------------------------------------------------------------------------------------
# Conversions
# ----------------------------------------------------------------------------------------------

def to_colmap_camera(camera: Camera, camera_id: int):
    """A pycolmap.Camera with the intrinsics of a project Camera (see :func:`colmap_model`)."""
    pycolmap = _pycolmap()
    model, params = colmap_model(camera)
    out = pycolmap.Camera.create_from_model_name(int(camera_id), model, camera.fx, camera.width,
                                                 camera.height)
    out.params = params
    return out


def _rigid3d(R: np.ndarray, t: np.ndarray):
    pycolmap = _pycolmap()
    return pycolmap.Rigid3d(pycolmap.Rotation3d(np.asarray(R, dtype=np.float64)),
                            np.asarray(t, dtype=np.float64))


# ----------------------------------------------------------------------------------------------
# Input checks and the problem's layout
# ----------------------------------------------------------------------------------------------

def _array(value, name: str, shape: tuple, finite: bool = True) -> np.ndarray:
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected numbers of shape {shape}, got {type(value).__name__}"
                         ) from None
    if a.shape != shape:
        raise ValueError(f"{name}: expected shape {shape}, got {a.shape}")
    if finite and not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: expected finite numbers, got NaN or inf")
    return a


def _observed(image_points: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """(C, F, N) bool: the point was detected by a camera that counts in that frame."""
    detected = np.all(np.isfinite(image_points), axis=-1)
    counts = seen & (detected.sum(-1) >= MIN_POINTS_PER_VIEW)
    return detected & counts[..., None]


def _selection(image_points: np.ndarray, seen: np.ndarray, min_views: int):
    """The observations in the problem, (C, F, N) bool, and how many were dropped because their
    board point would have been observed only once (COLMAP wants tracks of two or more)."""
    observed = _observed(image_points, seen)
    observed &= (observed.any(-1).sum(0) >= min_views)[None, :, None]
    n_start = int(observed.sum())
    while True:  # dropping a point can drop a view, a frame, and so another point
        before = int(observed.sum())
        observed &= (observed.sum(axis=(0, 1)) >= 2)[None, None, :]
        observed &= (observed.sum(-1) >= MIN_POINTS_PER_VIEW)[..., None]
        observed &= (observed.any(-1).sum(0) >= min_views)[None, :, None]
        if int(observed.sum()) == before:
            return observed, n_start - before


def _check_connected(views: np.ndarray, names: Sequence[str]) -> None:
    """Every camera must be joined to camera 0 through frames seen together: (C, F) bool."""
    together = covisibility(views) > 0
    np.fill_diagonal(together, False)
    lonely = [names[c] for c in np.flatnonzero(~together.any(1))]
    if lonely:
        raise ValueError(f"seen: cameras {lonely} see no frame together with another camera; "
                         f"expected every camera in at least one frame seen by two or more")
    free = [names[c] for c in unreachable(views)]
    if free:
        raise ValueError(f"seen: cameras {free} share no frame with camera {names[0]!r} or any "
                         f"camera connected to it; the rig would not be determined")


# ----------------------------------------------------------------------------------------------
# The reconstruction
# ----------------------------------------------------------------------------------------------

@dataclass(eq=False)
class ColmapRig:
    """A studio as a pycolmap.Reconstruction (world = board), and where everything went.

    reconstruction: one rig (rig_id 1, camera c is camera_id and sensor c + 1, camera 0 the
    reference), one frame per used frame f (frame_id f + 1), one image per (camera, used frame)
    with observations, 3D points = board points. image_ids (C, F) int: the image of each camera
    in each frame, 0 where none. point_ids (N,) int: the 3D point of each board point, 0 where
    it was dropped (observed fewer than twice). observed (C, F, N) bool: the observations in the
    problem. frames_used (F,) bool. dropped_observations: observations of dropped points.
    """

    reconstruction: object
    image_ids: np.ndarray
    point_ids: np.ndarray
    observed: np.ndarray
    frames_used: np.ndarray
    dropped_observations: int


def rig_reconstruction(cameras: Sequence[Camera], object_points, image_points, cam_from_cam0_R,
                       cam_from_cam0_t, board_rvecs, board_tvecs, seen,
                       min_views: int = 2) -> ColmapRig:
    """Build the COLMAP reconstruction of a studio from arrays already checked by
    :func:`colmap_rig_bundle` (same arguments); a frame is used if ``min_views`` cameras see it."""
    pycolmap = _pycolmap()
    obj, img = object_points, image_points
    C, F, N = img.shape[:3]
    observed, dropped = _selection(img, seen, min_views)
    used = observed.any(-1).sum(0) >= min_views
    views = observed.any(-1)

    rec = pycolmap.Reconstruction()
    rig = pycolmap.Rig(rig_id=1)
    for c, cam in enumerate(cameras):
        rec.add_camera(to_colmap_camera(cam, c + 1))
        sensor = pycolmap.sensor_t(pycolmap.SensorType.CAMERA, c + 1)
        if c == 0:
            rig.add_ref_sensor(sensor)
        else:
            rig.add_sensor(sensor, _rigid3d(cam_from_cam0_R[c], cam_from_cam0_t[c]))
    rec.add_rig(rig)

    image_ids = np.zeros((C, F), dtype=np.int64)
    index = np.full((C, F, N), -1, dtype=np.int64)  # point2D index of each observation
    next_id = 1
    for f in np.flatnonzero(used):
        frame = pycolmap.Frame(frame_id=int(f) + 1, rig_id=1)
        frame.rig_from_world = _rigid3d(rodrigues_to_matrix(board_rvecs[f]), board_tvecs[f])
        images = []
        for c in np.flatnonzero(views[:, f]):
            pts = np.flatnonzero(observed[c, f])
            image = pycolmap.Image(name=f"{c}-{cameras[c].name}/{f:06d}",
                                   keypoints=opencv_to_colmap_pixels(img[c, f, pts]),
                                   camera_id=int(c) + 1, image_id=next_id)
            image.frame_id = int(f) + 1
            frame.add_data_id(image.data_id)
            images.append(image)
            image_ids[c, f] = next_id
            index[c, f, pts] = np.arange(len(pts))
            next_id += 1
        rec.add_frame(frame)
        for image in images:
            rec.add_image(image)

    point_ids = np.zeros(N, dtype=np.int64)
    for n in np.flatnonzero(observed.any(axis=(0, 1))):
        cs, fs = np.nonzero(observed[:, :, n])
        track = pycolmap.Track([pycolmap.TrackElement(int(image_ids[c, f]), int(index[c, f, n]))
                                for c, f in zip(cs, fs)])
        point_ids[n] = rec.add_point3D(obj[n], track)
    return ColmapRig(rec, image_ids, point_ids, observed, used, dropped)


# ----------------------------------------------------------------------------------------------
# Bundle adjustment
# ----------------------------------------------------------------------------------------------

def colmap_rig_bundle(
    cameras: Sequence[Camera],
    object_points,
    image_points,
    cam_from_cam0_R,
    cam_from_cam0_t,
    board_rvecs,
    board_tvecs,
    seen,
    refine_intrinsics: bool = False,
    loss: str = "trivial",
    loss_scale_px: float = 1.0,
    tolerance: float = 1e-15,
    max_iterations: int = 200,
    num_threads: int = 1,
) -> RigCalibration:
    """Refine a studio rig with pycolmap's bundle adjuster; see the module notes.

    cameras: C >= 2 project Cameras (intrinsics; pose ignored; skew 0). object_points (N, 3) mm,
    the board frame (z = 0 for a planar board). image_points (C, F, N, 2) px, OpenCV's
    convention, NaN where not detected. cam_from_cam0_R (C, 3, 3), cam_from_cam0_t (C, 3) mm:
    the initial rig, camera 0's the identity. board_rvecs, board_tvecs (F, 3): the initial
    cam0_from_board of each frame, finite for every frame in the adjustment (NaN allowed
    elsewhere); ``bundle.rig_start`` gives calibrate_rig's start. seen (C, F) bool.
    refine_intrinsics: also refine every camera's COLMAP intrinsics (and use the frames seen by
    one camera). loss: one of LOSSES ("linear" is taken for "trivial"), with scale
    ``loss_scale_px`` in px.
    ``tolerance``: Ceres' function, gradient and parameter tolerances. ``num_threads``: Ceres
    threads (1: the same numbers on every machine).

    Returns a RigCalibration: cameras with cam_from_world = cam_from_cam0 (and refined
    intrinsics if asked), cam0_from_board per frame (NaN for unused frames), rms_px and
    rms_px_per_camera through the project's camera model over the observations in the problem,
    iterations = Ceres' Jacobian evaluations, time_s (the whole call), and a log of COLMAP's
    summary (initial and final cost, steps, termination, message, brief report).
    """
    t0 = time.perf_counter()
    pycolmap = _pycolmap()
    cameras = rig_cameras(cameras)
    C = len(cameras)
    for cam in cameras:
        colmap_model(cam)  # refuses skew
    names = [cam.name for cam in cameras]
    img = np.asarray(image_points, dtype=np.float64)
    if img.ndim != 4 or img.shape[0] != C or img.shape[-1] != 2:
        raise ValueError(f"image_points: expected shape (C={C}, F, N, 2), got {img.shape}")
    F, N = img.shape[1:3]
    obj = _array(object_points, "object_points", (N, 3))
    R = _array(cam_from_cam0_R, "cam_from_cam0_R", (C, 3, 3))
    t = _array(cam_from_cam0_t, "cam_from_cam0_t", (C, 3))
    if not np.allclose(np.swapaxes(R, -1, -2) @ R, np.eye(3), atol=1e-9) or np.any(
            np.linalg.det(R) < 0):
        raise ValueError("cam_from_cam0_R: expected rotation matrices (orthonormal, det +1)")
    if not (np.allclose(R[0], np.eye(3), atol=1e-12) and np.allclose(t[0], 0, atol=1e-9)):
        raise ValueError(f"cam_from_cam0_R, cam_from_cam0_t: expected the identity for camera "
                         f"{names[0]!r} (the reference), got R={R[0].tolist()}, t={t[0].tolist()}")
    rv = _array(board_rvecs, "board_rvecs", (F, 3), finite=False)
    tv = _array(board_tvecs, "board_tvecs", (F, 3), finite=False)
    seen = np.asarray(seen)
    if seen.shape != (C, F) or seen.dtype != bool:
        raise ValueError(f"seen: expected a bool array of shape {(C, F)}, got "
                         f"{seen.dtype} {seen.shape}")
    loss = "trivial" if loss == "linear" else loss  # scipy's name for it
    if loss not in LOSSES:
        raise ValueError(f"loss: expected one of {list(LOSSES)}, got {loss!r}")
    if not (isinstance(loss_scale_px, (int, float)) and np.isfinite(loss_scale_px)
            and loss_scale_px > 0):
        raise ValueError(f"loss_scale_px: expected a positive number, got {loss_scale_px!r}")

    min_views = 1 if refine_intrinsics else 2
    views = _observed(img, seen).any(-1)
    if not (views.sum(0) >= 2).any():
        raise ValueError("seen: no frame is seen by two or more cameras")
    _check_connected(views, names)
    observed, _ = _selection(img, seen, min_views)
    _check_connected(observed.any(-1), names)  # dropped points may have cut a link
    bad = [int(f) for f in np.flatnonzero(observed.any(axis=(0, 2)))
           if not (np.all(np.isfinite(rv[f])) and np.all(np.isfinite(tv[f])))]
    if bad:
        raise ValueError(f"board_rvecs, board_tvecs: expected a finite initial pose for every "
                         f"frame in the adjustment, got NaN or inf at frames {bad[:10]}")
    layout = rig_reconstruction(cameras, obj, img, R, t, rv, tv, seen, min_views)
    rec = layout.reconstruction
    start = [cam.with_params(rvec=matrix_to_rodrigues(R[c]), tvec=t[c])
             for c, cam in enumerate(cameras)]
    rms0, _ = reprojection_rms(start, obj, img, rv, tv, layout.observed)

    options = pycolmap.BundleAdjustmentOptions()
    options.print_summary = False
    options.refine_points3D = False
    options.refine_rig_from_world = True
    options.refine_sensor_from_rig = True
    options.refine_focal_length = refine_intrinsics
    options.refine_principal_point = refine_intrinsics
    options.refine_extra_params = refine_intrinsics
    options.ceres.loss_function_type = getattr(pycolmap.LossFunctionType, _LOSS_TYPES[loss])
    options.ceres.loss_function_scale = float(loss_scale_px)
    solver = options.ceres.solver_options
    solver.function_tolerance = tolerance
    solver.gradient_tolerance = tolerance
    solver.parameter_tolerance = tolerance
    solver.max_num_iterations = int(max_iterations)
    solver.num_threads = int(num_threads)

    config = pycolmap.BundleAdjustmentConfig()
    for image_id in layout.image_ids[layout.image_ids > 0]:
        config.add_image(int(image_id))
    for point_id in layout.point_ids[layout.point_ids > 0]:
        config.add_constant_point(int(point_id))
    if not refine_intrinsics:
        for c in range(C):
            config.set_constant_cam_intrinsics(c + 1)

    t_solve = time.perf_counter()
    summary = pycolmap.create_default_bundle_adjuster(options, config, rec).solve()
    solve_s = time.perf_counter() - t_solve
    ceres = summary.ceres_summary

    rig = rec.rig(1)
    R_out, t_out = np.tile(np.eye(3), (C, 1, 1)), np.zeros((C, 3))
    for c in range(1, C):
        R_out[c], t_out[c] = from_rigid3d(
            rig.sensor_from_rig(pycolmap.sensor_t(pycolmap.SensorType.CAMERA, c + 1)))
    rv_out, tv_out = np.full((F, 3), np.nan), np.full((F, 3), np.nan)
    for f in np.flatnonzero(layout.frames_used):
        Rb, tb = from_rigid3d(rec.frame(int(f) + 1).rig_from_world)
        rv_out[f], tv_out[f] = matrix_to_rodrigues(Rb), tb
    intrinsic = [from_colmap_camera(rec.camera(c + 1), cam) if refine_intrinsics else cam
                 for c, cam in enumerate(cameras)]
    out = [cam.with_params(rvec=matrix_to_rodrigues(R_out[c]), tvec=t_out[c])
           for c, cam in enumerate(intrinsic)]
    rms, rms_per = reprojection_rms(out, obj, img, rv_out, tv_out, layout.observed)
    n_obs = int(layout.observed.sum())
    return RigCalibration(
        cameras=out, board_rvecs=rv_out, board_tvecs=tv_out, frames_used=layout.frames_used,
        rms_px=rms, rms_px_per_camera=rms_per, iterations=int(ceres.num_jacobian_evaluations),
        time_s=time.perf_counter() - t0,
        log={"solver": f"pycolmap {pycolmap.__version__} bundle adjustment (Ceres)",
             "camera_models": [colmap_model(cam)[0] for cam in cameras],
             "initial_rms_px": rms0, "initial_cost": float(ceres.initial_cost),
             "final_cost": float(ceres.final_cost),
             # COLMAP's own RMS from its final cost (a robust loss's cost is not a sum of squares)
             "colmap_rms_px": (float(np.sqrt(2 * ceres.final_cost / n_obs))
                               if loss == "trivial" else None),
             "successful_steps": int(ceres.num_successful_steps),
             "unsuccessful_steps": int(ceres.num_unsuccessful_steps),
             "termination": summary.termination_type.name, "message": str(ceres.message),
             "usable": bool(summary.is_solution_usable()),
             "linear_solver": ceres.linear_solver_type_used.name,
             "brief_report": summary.brief_report(), "solve_time_s": solve_s,
             "n_observations": n_obs, "dropped_observations": layout.dropped_observations,
             "n_images": int(rec.num_images()), "refine_intrinsics": bool(refine_intrinsics),
             "loss": loss, "loss_scale_px": float(loss_scale_px)})
