"""OpenCV 5's cv2.calibrateMultiview as a second reference for the studio rig calibration.

``bundle.calibrate_rig`` refines one cam_from_cam0 per camera and one cam0_from_board per frame
by least squares on the pixel reprojection errors; ``colmap_ref`` hands the same problem to
pycolmap's bundle adjuster. :func:`opencv_multiview` hands the same observations to OpenCV's
multi-camera calibration, ``cv2.calibrateMultiviewExtended`` (OpenCV >= 5; the Extended form of
calibrateMultiview, which also returns the board poses, the per-view errors and the pairs its
initialization chained), and returns its answer as a ``stereo.RigCalibration``. It is a reference
and a baseline, not the project's solver; unlike pycolmap it does not start from
``bundle.rig_start`` (see "What OpenCV does").

OpenCV's conventions, and how they are mapped
---------------------------------------------
* Cameras and frames: ``imagePoints`` is a list over cameras of lists over frames of (N, 2)
  float32 arrays, ``objPoints`` one (N, 3) float32 array per frame, ``detectionMask`` (C, F)
  uint8 says which camera saw the board in which frame, ``models`` (C,) uint8 is
  CALIB_MODEL_PINHOLE for a camera of the core's ``opencv`` lens ([k1, k2, p1, p2, k3, k4, k5,
  k6]) and CALIB_MODEL_FISHEYE for a ``kannala_brandt`` one (cv2.fisheye's k1..k4). Neither
  takes a skew: the pinhole's K has none, and a fisheye camera's K[0, 1] (cv2.fisheye's alpha)
  is not honoured throughout (measured: a skew of 0.8 px on noise-free views left an RMS of
  0.03 px and cameras 1.2 mm off). The omnidirectional lenses have no model there.
* Output poses: ``Rs[c], Ts[c]`` map camera 0's frame into camera c's, ``p_c = R p_0 + T``:
  cam_from_cam0, camera 0 the reference (Rs[0] = identity, Ts[0] = 0), in the unit of the
  object points; 5.0.0's Python binding returns Rs as Rodrigues vectors (3, 1) although its
  documentation says 3 x 3 (both are accepted). ``rvecs0[f], tvecs0[f]`` are cam0_from_board of
  every frame in its problem (empty for the others). The returned cameras carry
  cam_from_world = cam_from_cam0 and the board poses are OpenCV's own, so nothing is refitted.
* Units: OpenCV divides the object points by the SQUARED largest distance between two of them
  (though it uses it as a length) and then calls three of them collinear when the squared norm
  of their cross product is below 1e-6: a 9 x 6 board at 60 mm given in millimetres fails with
  "Pattern points are collinear!" (measured). The points go in in "board units" of
  ``board_unit_mm`` (their largest pairwise distance), where that scale is 1 and the
  normalization a no-op; translations come back in board units and are multiplied back to mm.
* Precision: object and image points go in as float32 (OpenCV asserts CV_32F). Rounding a pixel
  coordinate between 256 and 512 to float32 is a uniform error of up to 3e-5 px (RMS ~1.8e-5
  px), a noise 1/15000 of 0.3 px that moves a 3.5 m studio's cameras by ~1e-4 mm (measured:
  noise-free observations give the true rig to 2.3e-4 mm and 2.5e-7 deg, RMS 2e-6 px through
  the project's model, 7e-6 px as OpenCV computes it on its float32 copies).
* Intrinsics. ``fix_intrinsics=True`` (the default) passes the cameras' K and distortion with
  ``flags=CALIB_USE_INTRINSIC_GUESS``; they come back unchanged. CALIB_FIX_INTRINSIC (a
  stereoCalibrate flag) is ignored by calibrateMultiview (measured: with it alone OpenCV
  re-estimates every camera). ``fix_intrinsics=False`` lets OpenCV calibrate each camera on its
  own with cv2.calibrateCamera from its views in the problem, with that camera's
  ``flagsForIntrinsics`` (``intrinsics_flags``; 0: k1, k2, p1, p2, k3 estimated, no skew): the
  given intrinsics are discarded (its Ks are cleared first, so CALIB_USE_INTRINSIC_GUESS in
  flagsForIntrinsics fails and is refused here). Either way the joint adjustment of the rig
  never refines intrinsics (the returned ones equal a standalone calibrateCamera's, tests).

What OpenCV does (5.0.0), as its source reads and as far as measured
--------------------------------------------------------------------
(modules/calib/src/multiview_calibration.cpp; read to understand, the measurements are of 5.0.0)

1. A board pose per view: cv2.solvePnP with the given intrinsics (or calibrateCamera's poses).
2. A maximum spanning tree over the cameras, weighted by the frames they share (plus terms for
   the board's image area and angles), then one cv2.registerCameras per tree edge (pairwise
   extrinsics with intrinsics fixed), chained to camera 0; ``initializationPairs`` lists the
   edges. Each frame's cam0_from_board comes from its best-fitting camera.
   CALIB_STEREO_REGISTRATION (stereoCalibrate for the pairs) did not change the result.
3. A Levenberg-Marquardt adjustment over cam_from_cam0 of cameras 1..C-1 and cam0_from_board of
   every frame in the problem, with a robust weight per board point, exp(-|e|^2 / 30 px^2) on
   its squared pixel error |e|^2, recomputed at every step (the stationary point of a
   Welsch-type cost, scale ~5.5 px). Measured with the project's residuals on the test studio
   at 0.3 px noise: the minimum of that cost is about 1 % of the rig's error against the truth
   away from the least-squares minimum ``calibrate_rig`` and pycolmap find; a corner off by
   tens of pixels is ignored outright (tests).

Limits met: (a) its LM can stop short of its own minimum. On a poorly conditioned studio (5
cameras on a 3.5 m ring, a 70 px board facing directions drawn at random, the rig's errors
against the truth 2-7 mm at 0.3 px noise) one Gauss-Newton step of its own robust cost from its
solution still moved a camera by up to ~0.1 mm (1-4 % of the error against the truth), and
adding frames that only one camera saw (which cannot move the rig at a minimum: with fixed
intrinsics their poses are decoupled) moved it by as much; neither ``criteria`` (even 1000
iterations at epsilon 0) nor a start given with CALIB_USE_EXTRINSIC_GUESS (the identity, or the
minimum of its own cost) changed its result in the last digit, so neither is passed. On the
test studio (a calibration session, errors ~1 mm) it reaches its minimum: that step moves a
camera by ~1e-4 of its error against the truth, the added frames by 2e-5 (tests). (b) Partial
views: its documentation says to mark undetected points (-1, -1); 5.0.0 uses such placeholders
as points (replacing 20 of 54 points by (-1, -1) in half the views of the test studio, the RMS
came back 9e4 px). (c) NaN image points make it fail ("Failed to build tree for stereo
calibration").

Subset supported
----------------
C >= 2 cameras with zero skew, pinhole or Kannala-Brandt fisheye, mixed freely; a rigid target of N
>= 4 known points, not collinear (planar, z = 0, when OpenCV calibrates the intrinsics). FULL VIEWS
ONLY: a camera counts in a frame when ``seen`` and it detected every board point, each inside [0,
width] x [0, height] (OpenCV's documented valid range); other views are left out and counted in the
log. With intrinsics fixed the frames seen by two or more such views are used (the observations
``calibrate_rig`` uses when every view is full), otherwise every frame seen by one or more
(``min_views`` chooses otherwise).
Every camera must be joined to camera 0 through frames seen together (ValueError otherwise);
an error inside OpenCV becomes a RuntimeError carrying its message. One OpenCV thread, as for
the calibrateCamera reference (on the test studio two threads gave the same bits).
"""

from __future__ import annotations

import time
from typing import Sequence

import numpy as np

from ..calibrate.base import MIN_POINTS_PER_VIEW
from ..core.camera import Camera
from ..core.poses import matrix_to_rodrigues, rodrigues_to_matrix
from .bundle import RigCalibration, covisibility, reprojection_rms, rig_cameras, unreachable

ROBUST_SCALE_PX2 = 30.0  # OpenCV's per-point weight exp(-|e|^2 / ROBUST_SCALE_PX2)
# calibrateCamera flags that would give more than the project's 8 distortion coefficients, or
# that need the intrinsics calibrateMultiview clears before calibrating each camera.
_REFUSED_INTRINSICS_FLAGS = ("CALIB_THIN_PRISM_MODEL", "CALIB_TILTED_MODEL",
                             "CALIB_USE_INTRINSIC_GUESS")
# The core's lens models calibrateMultiview has, by the name of its CALIB_MODEL_ constant.
_MODELS = {"opencv": "CALIB_MODEL_PINHOLE", "kannala_brandt": "CALIB_MODEL_FISHEYE"}


def _cv2():
    import cv2

    if not hasattr(cv2, "calibrateMultiviewExtended"):
        raise ImportError(f"stereo_bench.multiview.opencv_ref needs OpenCV >= 5 "
                          f"(cv2.calibrateMultiviewExtended); OpenCV {cv2.__version__} has none")
    return cv2


def board_unit_mm(object_points) -> float:
    """The largest distance (mm) between two points of the board: the unit the points are given
    to OpenCV in, where its normalization by the squared largest distance is a no-op."""
    obj = np.asarray(object_points, dtype=np.float64)
    d = np.linalg.norm(obj[:, None, :] - obj[None, :, :], axis=-1)
    return float(d.max())


def full_views(cameras: Sequence[Camera], image_points: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """(C, F) bool: ``seen`` and every board point detected inside [0, w] x [0, h]."""
    img = np.asarray(image_points, dtype=np.float64)
    size = np.array([[cam.width, cam.height] for cam in cameras], dtype=np.float64)
    with np.errstate(invalid="ignore"):
        inside = np.all((img >= 0) & (img <= size[:, None, None, :]), axis=-1)  # NaN -> False
    return seen & inside.all(axis=-1)


def _check_inputs(cameras, object_points, image_points, seen, fix_intrinsics, intrinsics_flags):
    cameras = rig_cameras(cameras)
    C = len(cameras)
    for c, cam in enumerate(cameras):
        if cam.model not in _MODELS:
            raise ValueError(f"cameras[{c}] ({cam.name!r}): a {cam.model} lens; "
                             f"calibrateMultiview has {' and '.join(_MODELS)} lenses only")
        if cam.skew != 0:
            raise ValueError(f"cameras[{c}] ({cam.name!r}): skew {cam.skew!r} is not 0; "
                             f"calibrateMultiview takes none")
    if not isinstance(fix_intrinsics, (bool, np.bool_)):
        raise ValueError(f"fix_intrinsics: expected True or False, got {fix_intrinsics!r}")
    try:
        img = np.asarray(image_points, dtype=np.float64)
        obj = np.asarray(object_points, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError("image_points, object_points: expected arrays of numbers") from None
    if img.ndim != 4 or img.shape[0] != C or img.shape[-1] != 2:
        raise ValueError(f"image_points: expected shape (C={C}, F, N, 2), got {img.shape}")
    F, N = img.shape[1:3]
    if obj.shape != (N, 3):
        raise ValueError(f"object_points: expected shape ({N}, 3) (N of image_points), got "
                         f"{obj.shape}")
    if N < MIN_POINTS_PER_VIEW or not np.all(np.isfinite(obj)):
        raise ValueError(f"object_points: expected at least {MIN_POINTS_PER_VIEW} finite points, "
                         f"got {N}")
    centred = obj - obj.mean(0)
    s = np.linalg.svd(centred, compute_uv=False)
    if s[1] <= 1e-9 * s[0]:
        raise ValueError("object_points: the points are collinear; expected a board")
    if not fix_intrinsics and np.abs(obj[:, 2]).max() > 0:
        raise ValueError("object_points: expected a planar board with z = 0 when OpenCV "
                         "calibrates the intrinsics (fix_intrinsics=False)")
    seen = np.asarray(seen)
    if seen.shape != (C, F) or seen.dtype != bool:
        raise ValueError(f"seen: expected a bool array of shape {(C, F)}, got "
                         f"{seen.dtype} {seen.shape}")
    cv2 = _cv2()
    if np.ndim(intrinsics_flags) == 0:
        intrinsics_flags = [intrinsics_flags] * C
    flags = list(intrinsics_flags)
    if len(flags) != C or not all(isinstance(f, (int, np.integer)) and f >= 0 for f in flags):
        raise ValueError(f"intrinsics_flags: expected one non-negative int or one per camera "
                         f"({C}), got {intrinsics_flags!r}")
    if fix_intrinsics and any(flags):
        raise ValueError("intrinsics_flags: only used when OpenCV calibrates the intrinsics "
                         "(fix_intrinsics=False)")
    for name in _REFUSED_INTRINSICS_FLAGS:
        if any(int(f) & getattr(cv2, name) for f in flags):
            raise ValueError(f"intrinsics_flags: {name} is not supported (calibrateMultiview "
                             f"clears the intrinsics before calibrating each camera, and the "
                             f"project's model has 8 distortion coefficients)")
    return cameras, obj, img, seen, np.array(flags, dtype=np.int32)


def _check_connected(views: np.ndarray, names: Sequence[str]) -> None:
    """Every camera joined to camera 0 through frames seen together (views (C, F) bool)."""
    empty = [names[c] for c in np.flatnonzero(~views.any(axis=1))]
    if empty:
        raise ValueError(f"seen: cameras {empty} have no full view of the board in a frame in "
                         f"the problem; calibrateMultiview takes full views only")
    apart = [names[c] for c in unreachable(views)]
    if apart:
        raise ValueError(f"seen: cameras {apart} share no full view of a frame with camera "
                         f"{names[0]!r} or any camera connected to it; the rig would not be "
                         f"determined")


def _rotation(r) -> np.ndarray:
    r = np.asarray(r, dtype=np.float64)
    return r.reshape(3, 3) if r.size == 9 else rodrigues_to_matrix(r.reshape(3))


def opencv_multiview(
    cameras: Sequence[Camera],
    object_points,
    image_points,
    seen,
    fix_intrinsics: bool = True,
    intrinsics_flags: int | Sequence[int] = 0,
    min_views: int | None = None,
) -> RigCalibration:
    """Calibrate a studio rig with cv2.calibrateMultiviewExtended; see the module notes.

    cameras: C >= 2 project Cameras (intrinsics; pose ignored; pinhole or Kannala-Brandt, skew 0).
    object_points (N, 3) mm, the board frame. image_points (C, F, N, 2) px, OpenCV's pixel
    convention, NaN where not detected. seen (C, F) bool: the camera found the board in that frame.
    Only full views are used (module notes). fix_intrinsics: keep the cameras' intrinsics (True) or
    let OpenCV calibrate each camera with cv2.calibrateCamera and ``intrinsics_flags`` (one int, or
    one per camera; OpenCV's flagsForIntrinsics). min_views: a frame is used when that many cameras
    see it in full (default 2 with intrinsics fixed, as calibrate_rig; 1 otherwise).

    Returns a RigCalibration: cameras with cam_from_world = cam_from_cam0 (OpenCV's Rs, Ts) and
    the intrinsics used, board_rvecs/board_tvecs (F, 3) = OpenCV's cam0_from_board (NaN for
    frames not in the problem), frames_used (F,), rms_px and rms_px_per_camera through the
    project's camera model over the views in the problem, iterations = -1 (OpenCV does not report
    them), time_s (the whole call), and a log: OpenCV's version and its own RMS (the root of the
    mean over views of each view's mean squared error), per_view_rms_px (C, F; NaN where not
    used), initialization_pairs (camera names), the flags, board_unit_mm, the views left out by
    reason (partial_views; views_in_frames_seen_by_fewer than min_views; views_dropped_by_opencv,
    -1 in its per-view errors), n_views, n_observations, covisibility (C x C: the frames each
    pair saw in the problem) and opencv_time_s (the call alone).
    """
    t0 = time.perf_counter()
    cv2 = _cv2()
    cameras, obj, img, seen, flags_intr = _check_inputs(cameras, object_points, image_points,
                                                        seen, fix_intrinsics, intrinsics_flags)
    C, F, N = img.shape[:3]
    if min_views is None:
        min_views = 2 if fix_intrinsics else 1
    if not (isinstance(min_views, (int, np.integer)) and 1 <= min_views <= C):
        raise ValueError(f"min_views: expected an int from 1 to {C} (cameras), got {min_views!r}")
    names = [cam.name for cam in cameras]
    full = full_views(cameras, img, seen)
    used = full.sum(axis=0) >= min_views
    views = full & used[None, :]
    if not used.any():
        raise ValueError(f"seen: no frame is seen in full by {min_views} or more cameras")
    _check_connected(views, names)

    unit = board_unit_mm(obj)
    obj32 = np.ascontiguousarray(obj / unit, dtype=np.float32)
    # Views outside the mask are never read; they still need N points of the right type.
    image32 = [[np.ascontiguousarray(img[c, f] if views[c, f] else np.full((N, 2), -1.0),
                                     dtype=np.float32) for f in range(F)] for c in range(C)]
    if fix_intrinsics:
        Ks = [cam.K for cam in cameras]
        dists = [cam.dist.reshape(1, -1).copy() for cam in cameras]
        flags = cv2.CALIB_USE_INTRINSIC_GUESS
    else:
        Ks, dists, flags = None, None, 0
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    t_call = time.perf_counter()
    try:
        (rms_cv, Ks_out, dists_out, Rs, Ts, pairs, rvecs0, tvecs0,
         per_view) = cv2.calibrateMultiviewExtended(
            [obj32] * F, image32, [cam.size for cam in cameras], views.astype(np.uint8),
            np.array([getattr(cv2, _MODELS[cam.model]) for cam in cameras], np.uint8), Ks,
            dists, None, None,
            flagsForIntrinsics=flags_intr, flags=flags)
    except cv2.error as e:
        raise RuntimeError(f"cv2.calibrateMultiview failed: {str(e).strip()}") from None
    finally:
        cv2.setNumThreads(threads)
    call_s = time.perf_counter() - t_call

    R = np.stack([_rotation(r) for r in Rs])
    t = np.stack([np.asarray(v, dtype=np.float64).reshape(3) * unit for v in Ts])
    rv_out, tv_out = np.full((F, 3), np.nan), np.full((F, 3), np.nan)
    for f in range(F):
        if rvecs0[f] is not None and np.size(rvecs0[f]) == 3:
            rv_out[f] = np.asarray(rvecs0[f], dtype=np.float64).reshape(3)
            tv_out[f] = np.asarray(tvecs0[f], dtype=np.float64).reshape(3) * unit
    per_view = np.asarray(per_view, dtype=np.float64).reshape(C, F)
    in_problem = (per_view >= 0) & views  # OpenCV marks the views it did not use with -1
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))
            and np.all(np.isfinite(rv_out[in_problem.any(0)]))):
        raise RuntimeError(f"cv2.calibrateMultiview returned non-finite poses (its RMS "
                           f"{rms_cv!r} px)")

    if fix_intrinsics:
        intrinsic = cameras
    else:
        intrinsic = []
        for cam, K, d in zip(cameras, Ks_out, dists_out):
            K, d = np.asarray(K, dtype=np.float64), np.ravel(np.asarray(d, dtype=np.float64))
            n = cam.dist.size  # OpenCV returns 4 fisheye coefficients, 5 to 14 pinhole ones
            intrinsic.append(cam.with_params(fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2],
                                             skew=K[0, 1], dist=np.pad(d[:n], (0, n - d[:n].size))))
    out = [cam.with_params(rvec=matrix_to_rodrigues(R[c]), tvec=t[c])
           for c, cam in enumerate(intrinsic)]
    rms, rms_per = reprojection_rms(out, obj, img, rv_out, tv_out,
                                    np.broadcast_to(in_problem[..., None], (C, F, N)))
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2) if pairs is not None else []
    partial = seen & ~full
    return RigCalibration(
        cameras=out, board_rvecs=rv_out, board_tvecs=tv_out, frames_used=in_problem.any(0),
        rms_px=rms, rms_px_per_camera=rms_per, iterations=-1, time_s=time.perf_counter() - t0,
        log={"solver": f"OpenCV {cv2.__version__} calibrateMultiview (Extended)",
             "opencv_version": cv2.__version__, "opencv_rms_px": float(rms_cv),
             "per_view_rms_px": np.where(in_problem, per_view, np.nan),
             "initialization_pairs": [(names[a], names[b]) for a, b in pairs],
             "flags": int(flags), "flags_for_intrinsics": flags_intr.tolist(),
             "fix_intrinsics": bool(fix_intrinsics), "board_unit_mm": unit,
             "robust_weight": f"exp(-|e|^2 / {ROBUST_SCALE_PX2:g} px^2) per point (OpenCV's)",
             "left_out": {"partial_views": int(partial.sum()),
                          "views_in_frames_seen_by_fewer": int((full & ~used[None, :]).sum()),
                          "views_dropped_by_opencv": int((views & ~in_problem).sum())},
             "n_views": int(in_problem.sum()), "n_observations": int(in_problem.sum()) * N,
             "covisibility": covisibility(in_problem),
             "opencv_time_s": call_s})
