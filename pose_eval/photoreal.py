"""A body sequence rendered by Blender from every camera of a rig, and 2D keypoints a real
detector finds in it.

:func:`render_body` renders the posed mesh of a :class:`~pose_eval.scene.Scene` (the same body,
motion and placement as the synthetic keypoints use) with Cycles in the worker environment
(stereo_bench.render.blender): per-vertex colours by body part (skin for the head, neck, forearms
and hands; a shirt, trousers and shoes, from SMPL's skinning weights), a checkered floor under the
feet, a sun from above and ambient light. Each camera renders undistorted and the camera's own
lens is applied by one exact remap, as for the boards, so the images and the projected joints
share one ground truth. Written::

    DIR/images/<camera>/<frame:06d>.png  synchronized frames (8-bit sRGB)
    DIR/joints_mm.npy                    the true joints (T, 24, 3), world mm
    DIR/cameras.json                     the true cameras

:func:`detect_keypoints` runs MediaPipe's BlazePose GHUM "full" model (in the worker environment;
its weights ship in mediapipe's wheel) on every frame and maps its 33 landmarks to the SMPL
joints they stand for (:data:`SMPL_FROM_BLAZEPOSE`); the spine and collar joints have no
landmark and stay undetected. A landmark's visibility is its confidence. BlazePose's hips,
shoulders, ears and toes are not SMPL's joint centres: that definition gap is part of every
row, the true cameras' (``gt``) included, so each calibration's paired cost against gt
isolates the calibration. Its keypoints are also written as OpenPose-style files
(observe.write_openpose) beside the images.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from stereo_bench.core.camera import Camera
from stereo_bench.render import PixelRays
from stereo_bench.render.blender.client import Worker
from stereo_bench.render.blender.lens import PinholeView
from stereo_bench.core.files import write_json, write_npy, write_png

from .body import NUM_JOINTS
from .motion import JOINT
from .observe import Keypoints
from .scene import Scene, rig_axes

# Linear RGB (Cycles' own space) of the parts; each vertex takes its strongest joint's part.
_PART_COLORS = {
    "skin": (0.62, 0.40, 0.29),
    "shirt": (0.10, 0.22, 0.50),
    "trousers": (0.12, 0.12, 0.13),
    "shoes": (0.35, 0.20, 0.10),
}
_PART_OF_JOINT = {
    "skin": ("neck", "head", "left_elbow", "right_elbow", "left_wrist", "right_wrist",
             "left_hand", "right_hand"),
    "shirt": ("spine1", "spine2", "spine3", "left_collar", "right_collar", "left_shoulder",
              "right_shoulder"),
    "trousers": ("pelvis", "left_hip", "right_hip", "left_knee", "right_knee"),
    "shoes": ("left_ankle", "right_ankle", "left_foot", "right_foot"),
}
BACKGROUND = (0.30, 0.32, 0.35)
FLOOR = ((0.45, 0.45, 0.43), (0.25, 0.25, 0.24))  # checker colours
FLOOR_SQUARE_MM = 500.0

# BlazePose landmarks (MediaPipe's order) -> the SMPL joint each mean of landmarks stands for.
SMPL_FROM_BLAZEPOSE = {
    "pelvis": (23, 24), "left_hip": (23,), "right_hip": (24,), "left_knee": (25,),
    "right_knee": (26,), "left_ankle": (27,), "right_ankle": (28,), "left_foot": (31,),
    "right_foot": (32,), "neck": (11, 12), "head": (7, 8), "left_shoulder": (11,),
    "right_shoulder": (12,), "left_elbow": (13,), "right_elbow": (14,), "left_wrist": (15,),
    "right_wrist": (16,), "left_hand": (17, 19), "right_hand": (18, 20),
}


def vertex_colors(lbs_weights: np.ndarray) -> np.ndarray:
    """(V, 3) linear RGB from SMPL's skinning weights (V, 24)."""
    part_of = {JOINT[j]: part for part, joints in _PART_OF_JOINT.items() for j in joints}
    strongest = np.asarray(lbs_weights).argmax(axis=1)
    return np.array([_PART_COLORS[part_of[j]] for j in strongest])


def _floor(scene: Scene, cameras: list[Camera]) -> dict:
    """A square floor under the body's feet, reaching past every camera (world m)."""
    R, t = scene.world_from_body
    # SMPL's floor is y = 0 in the body frame; the body frame's x and z span the floor.
    centres = np.array([c.center for c in cameras])
    reach = 1.5 * max(np.abs((centres - t) @ R[:, [0, 2]]).max(), 2000.0)
    corners = [R @ np.array([x, 0.0, z]) + t for x, z in
               ((-reach, -reach), (reach, -reach), (reach, reach), (-reach, reach))]
    return {"corners": (np.array(corners) / 1000.0).tolist(), "colors": FLOOR,
            "squares": 2 * reach / FLOOR_SQUARE_MM}


def render_body(cameras: list[Camera], scene: Scene, lbs_weights: np.ndarray, out: Path,
                samples: int = 16, threads: int | None = None, progress=None) -> Path:
    """Render every frame of ``scene`` from every camera into ``out`` (layout in the module
    notes); returns ``out``. ``progress(done, total)`` after each frame of all cameras."""
    out = Path(out)
    views = {c.name: PinholeView.of(c, PixelRays(c)) for c in cameras}
    scratch = out / "scratch"
    scratch.mkdir(parents=True, exist_ok=True)
    write_npy(scratch / "faces.npy", np.asarray(scene.faces, np.int32))
    write_npy(scratch / "colors.npy", vertex_colors(lbs_weights))
    write_npy(scratch / "vertices.npy", (scene.vertices / 1000.0).astype(np.float32))
    up = rig_axes(cameras).up
    sun = -up + 0.4 * np.cross(up, rig_axes(cameras).axis)  # from above, a little aside
    frames = len(scene.joints)
    with Worker("render", threads) as worker:
        worker.request("body", samples=samples, background=BACKGROUND, ambient=0.35,
                       faces=str(scratch / "faces.npy"), colors=str(scratch / "colors.npy"),
                       vertices=str(scratch / "vertices.npy"), floor=_floor(scene, cameras),
                       cameras={c.name: views[c.name].spec() for c in cameras},
                       sun_direction=sun.tolist(), sun_strength=3.0)
        for f in range(frames):
            pinholes = {c.name: str(scratch / f"{c.name}.png") for c in cameras}
            worker.request("body_frame", frame=f, out=pinholes)
            for c in cameras:
                import cv2  # noqa: PLC0415 (kept beside its only use)

                image = cv2.imread(pinholes[c.name], cv2.IMREAD_COLOR)
                if image is None:
                    raise RuntimeError(f"{pinholes[c.name]}: the render worker wrote no image")
                background = [round(255 * v) for v in BACKGROUND[::-1]]
                write_png(out / "images" / c.name / f"{f:06d}.png",
                          views[c.name].distort(image, border=background))
            if progress:
                progress(f + 1, frames)
    for path in scratch.iterdir():
        path.unlink()
    scratch.rmdir()
    write_npy(out / "joints_mm.npy", scene.joints)
    write_json(out / "cameras.json", [c.to_dict() for c in cameras])
    return out


def photograph_body(cameras: list[Camera], scene: Scene, images: Path, out: Path, environment,
                    seed: int) -> Path:
    """The rendered frames ``images/<camera>/<frame:06d>.png`` (:func:`render_body`) as each
    camera of a rig file's ``environment`` section records them, into ``out/<camera>/``: the
    defocus of the body's depth (its median pelvis depth, the focus when the section leaves it
    to the camera, as a camera operator focuses on the subject), the lens blur, vignetting, the
    sensor's noise, ADC and JPEG (``imaging.photograph``); the noise of camera c, frame f is
    drawn from ``frame_rng(seed, c, f)``, as a dataset's. Light and motion blur are the
    render's own (a body frame is rendered at one instant). Returns ``out``."""
    import cv2  # noqa: PLC0415 (kept beside its use, as in render_body)

    from stereo_bench.render.imaging import camera_vignette, photograph
    from stereo_bench.scene.dataset import environment_settings, frame_rng

    images, out = Path(images), Path(out)
    for c, cam in enumerate(cameras):
        depth = float(np.median(cam.world_to_cam(scene.joints[:, JOINT["pelvis"]])[:, 2]))
        st = environment_settings(environment, depth)
        radius = 0.5 * float(st.optics.circle_of_confusion_px(np.array(depth), cam.fx))
        vignette = camera_vignette(PixelRays(cam).xy[1:-1, 1:-1], st.optics)
        for f in range(len(scene.joints)):
            path = images / cam.name / f"{f:06d}.png"
            image = cv2.imread(str(path), cv2.IMREAD_COLOR)
            if image is None:
                raise FileNotFoundError(f"{path}: no rendered frame to photograph")
            write_png(out / cam.name / f"{f:06d}.png",
                      photograph(image, st.optics, st.sensor, st.white_level, vignette,
                                 frame_rng(seed, c, f), radius))
    return out


def recorded_keypoints(cameras: list[Camera], scene: Scene, renders: Path, environment,
                       out: Path, seed: int) -> Keypoints:
    """BlazePose's keypoints of the rendered body ``renders/<camera>/<frame:06d>.png`` as the
    cameras of ``environment`` record it (:func:`photograph_body` into ``out/photographed``;
    a clean or absent environment: the renders as they are); its raw landmarks go to ``out``."""
    images = Path(renders)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if environment is not None and environment.kind != "clean":
        images = photograph_body(cameras, scene, images, out / "photographed", environment, seed)
    return detect_keypoints(cameras, images, len(scene.joints), out)


def smpl_keypoints(landmarks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """BlazePose landmarks (..., 33, 4: x, y px from the image's edge, visibility, presence)
    -> SMPL joints (..., 24, 2) px with OpenCV's pixel centres (NaN where none) and their
    confidence (..., 24): the least visibility of the landmarks averaged, 0 where none."""
    landmarks = np.asarray(landmarks, np.float64)
    pixels = np.full(landmarks.shape[:-2] + (NUM_JOINTS, 2), np.nan)
    confidence = np.zeros(landmarks.shape[:-2] + (NUM_JOINTS,))
    for name, marks in SMPL_FROM_BLAZEPOSE.items():
        j = JOINT[name]
        # MediaPipe's x, y are fractions of the width and height from the image's edge; OpenCV's
        # pixel centres are half a pixel in.
        pixels[..., j, :] = landmarks[..., marks, :2].mean(axis=-2) - 0.5
        confidence[..., j] = np.nan_to_num(landmarks[..., marks, 2].min(axis=-1))
    pixels[confidence <= 0] = np.nan
    return pixels, confidence


def detect_keypoints(cameras: list[Camera], images: Path, frames: int,
                     landmarks: Path | None = None) -> Keypoints:
    """BlazePose on ``images/<camera>/<frame:06d>.png`` (as :func:`render_body` writes them),
    mapped to SMPL's joints; the raw landmarks go to ``LANDMARKS/blazepose_<camera>.npy``
    (default: beside ``images``)."""
    images = Path(images)
    landmarks = Path(landmarks) if landmarks is not None else images.parent
    pixels, confidence = [], []
    with Worker("pose2d") as worker:
        for c in cameras:
            paths = [images / c.name / f"{f:06d}.png" for f in range(frames)]
            missing = [p for p in paths if not p.exists()]
            if missing:
                raise FileNotFoundError(f"{missing[0]}: no rendered frame to detect")
            raw = landmarks / f"blazepose_{c.name}.npy"
            worker.request("landmarks", images=[str(p) for p in paths], out=str(raw))
            px, conf = smpl_keypoints(np.load(raw))
            pixels.append(px)
            confidence.append(conf)
    return Keypoints(np.stack(pixels), np.stack(confidence))


def keypoint_errors(cameras: list[Camera], keypoints: Keypoints, joints_mm: np.ndarray) -> dict:
    """The detector's error against the projected true joints, per SMPL joint it reports:
    mean and median px over the joint views it detected, and how many it detected."""
    truth = np.stack([c.project(joints_mm) for c in cameras])  # (C, T, 24, 2)
    err = np.linalg.norm(keypoints.pixels - truth, axis=-1)
    rows = {}
    for name in SMPL_FROM_BLAZEPOSE:
        e = err[:, :, JOINT[name]]
        e = e[np.isfinite(e)]
        rows[name] = {"detected": int(e.size), "views": int(err[:, :, JOINT[name]].size),
                      "mean_px": float(e.mean()) if e.size else None,
                      "median_px": float(np.median(e)) if e.size else None}
    return rows
