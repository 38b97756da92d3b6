"""2D keypoints of the body: synthetic detections through the true cameras, or a detector's output.

Synthetic detections start from the exact projections of the 24 SMPL joints (``Camera.project``,
full distortion) and degrade them as a detector would:

* a joint is detected only if it is inside the image (and in front of the camera, within the
  distortion's valid radius);
* self-occlusion: a joint hidden behind the body surface of its own frame keeps its detection,
  as detectors guess hidden joints from context, but with confidence 0.3 and 3x the pixel noise;
* Gaussian noise of ``noise_px`` per coordinate;
* outliers (rate ``outlier_rate``): the detection jumps to a uniform random point within 50 px of
  the truth (a left/right swap or a limb of the wrong person is of that size), confidence kept;
* misses (rate ``miss_rate``): no detection (NaN, confidence 0).
Detections are clipped to the image, as a detector's are. Confidence is 1 otherwise.

Occlusion test. Joints lie inside the body, so the segment from a camera centre to a joint
always crosses the joint's own flesh; what hides a joint is another body part in front of it.
The camera's ray enters and leaves that part, so the joint is occluded iff the segment crosses a
surface whose outward normal points away from the camera (a back face, where the ray leaves a
part) farther than ``neighbourhood_mm`` (50 mm) from the joint. The own flesh around the joint
only ever shows the camera front faces, however thick (the torso is 150 mm to the pelvis from the
side), and the neighbourhood skips the inner walls of overlapping parts near a joint (measured up
to 23 mm on the stand-in, whose body is a union of capsules). Segment-triangle intersections are
Moeller-Trumbore ("Fast, minimum storage ray/triangle intersection", 1997) in numpy, on the
triangles whose image-plane bounding box contains the joint: trimesh's ray casting needs rtree
or embree, which the package does not depend on.

OpenPose files (:func:`read_openpose`, :func:`write_openpose`), one per camera and frame::

    FOLDER/<camera name>/<frame:06d>_keypoints.json
    {"people": [{"pose_keypoints_2d": [x0, y0, c0, x1, y1, c1, ...]}]}

with exactly the 24 SMPL joints in SMPL's order (pose_eval.motion.JOINT_NAMES), pixels in
OpenCV's convention, and the first person taken. The frame number (from 0) is the digits before
``_keypoints.json``, so OpenPose's own ``<video>_<frame:012d>_keypoints.json`` names work too. OpenPose's own BODY_25 or COCO layouts have
other joints (no spine, no collars) and must be mapped to SMPL's 24 first; a file with another
count is refused. c = 0 (OpenPose's "not detected") or a missing file means no detection.

Calibration from the body reads the same files as tracks (:func:`read_tracks`): either layout,
SMPL's 24 joints or OpenPose's BODY_25 (its own 25, unmapped: the method needs no joint
definitions but the feet, the head and the height chain), and several people when a tracker
gave each the same ``person_id`` in every camera; without ids, the first person of each file.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from stereo_bench.core.camera import Camera
from stereo_bench.core.files import UnreadableFileError, read_json, write_json

from .body import NUM_JOINTS
from .scene import Scene, in_view

OUTLIER_RADIUS_PX = 50.0
OCCLUDED_CONFIDENCE = 0.3
OCCLUDED_NOISE_FACTOR = 3.0


@dataclass(frozen=True, eq=False)
class Keypoints:
    """pixels (C, T, 24, 2), NaN where not detected; confidence (C, T, 24), 0 where not detected.

    Synthetic detections also say which joints were occluded and which are outliers (C, T, 24);
    a detector's output read from files leaves them None.
    """

    pixels: np.ndarray
    confidence: np.ndarray
    occluded: np.ndarray | None = None
    outlier: np.ndarray | None = None

    def under_two_views(self) -> np.ndarray:
        """(T, 24) bool: the joint is detected by fewer than two cameras, too few to triangulate."""
        return np.count_nonzero(self.confidence > 0, axis=0) < 2

    def counts(self) -> dict:
        """How many joint views there are, were detected, occluded, outliers; and how many joints
        (frame x joint) were detected by fewer than two cameras (``under_two_views``)."""
        n = {"views": int(self.confidence.size), "detected": int(np.count_nonzero(self.confidence))}
        for name in ("occluded", "outlier"):
            flags = getattr(self, name)
            if flags is not None:
                n[name] = int(np.count_nonzero(flags & (self.confidence > 0)))
        n["under_two_views"] = int(np.count_nonzero(self.under_two_views()))
        return n


@dataclass(frozen=True)
class DetectorModel:
    """How synthetic detections deviate from the exact projections (see the module notes)."""

    noise_px: float = 0.0
    outlier_rate: float = 0.0
    miss_rate: float = 0.0
    occlusion: bool = True

    def __post_init__(self):
        if self.noise_px < 0:
            raise ValueError(f"noise_px: expected >= 0, got {self.noise_px}")
        for name in ("outlier_rate", "miss_rate"):
            if not 0 <= getattr(self, name) <= 1:
                raise ValueError(f"{name}: expected a rate in [0, 1], got {getattr(self, name)}")


def occluded_joints(camera: Camera, joints: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                    neighbourhood_mm: float = 50.0) -> np.ndarray:
    """(T, 24) bool: the joint is hidden from ``camera`` by another part of its frame's body.

    joints (T, J, 3), vertices (T, V, 3) world mm, faces (F, 3) with outward normals.
    """
    hidden = np.zeros(joints.shape[:2], dtype=bool)
    for t in range(len(joints)):
        P = camera.world_to_cam(joints[t])  # the camera centre is the origin here
        tri = camera.world_to_cam(vertices[t])[faces]  # (F, 3 corners, 3)
        # Back faces: n . v0 = det[v0; v1; v2] > 0 for the outward normal n = (v1-v0) x (v2-v0);
        # then any ray from the camera that meets the face has n . ray > 0 as well.
        tri = tri[np.linalg.det(tri) > 0]
        # Image-plane bounding boxes; a triangle reaching behind the camera is always a candidate.
        z = tri[..., 2]
        xy = tri[..., :2] / np.where(z > 1e-9, z, 1.0)[..., None]
        front = (z > 1e-9).all(axis=1)[:, None]
        lo = np.where(front, xy.min(axis=1), -np.inf)
        hi = np.where(front, xy.max(axis=1), np.inf)
        px, py = (P[:, :2] / P[:, 2:3]).T[..., None]  # (J, 1) each
        j, f = np.nonzero((lo[:, 0] <= px) & (px <= hi[:, 0]) & (lo[:, 1] <= py) & (py <= hi[:, 1]))
        if len(j) == 0:
            continue
        # Moeller-Trumbore for the segment origin -> P[j] (parameter s in (0, 1)).
        d, a0 = P[j], tri[f, 0]
        E1, E2 = tri[f, 1] - a0, tri[f, 2] - a0
        h = np.cross(d, E2)
        det = np.einsum("ki,ki->k", E1, h)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / det
            u = -inv * np.einsum("ki,ki->k", a0, h)
            q = np.cross(E1, a0)  # (origin - a0) x E1
            v = inv * np.einsum("ki,ki->k", d, q)
            s = inv * np.einsum("ki,ki->k", E2, q)
        hit = (u >= 0) & (v >= 0) & (u + v <= 1) & (s > 0) & (s < 1)
        far = (1 - s) * np.linalg.norm(d, axis=1) > neighbourhood_mm
        hidden[t, np.unique(j[hit & far])] = True
    return hidden


def scene_occlusion(cameras: list[Camera], scene: Scene) -> np.ndarray:
    """(C, T, 24) bool: :func:`occluded_joints` for every camera."""
    return np.stack([occluded_joints(cam, scene.joints, scene.vertices, scene.faces)
                     for cam in cameras])


def observe(cameras: list[Camera], scene: Scene, detector: DetectorModel,
            rng: np.random.Generator, occluded: np.ndarray | None = None) -> Keypoints:
    """Synthetic detections of the scene's joints in every camera (see the module notes).

    occluded: :func:`scene_occlusion` of these cameras and scene, if already computed (it does
    not depend on the noise, so trials share it); ignored when ``detector.occlusion`` is off.
    Random numbers are drawn in a fixed order whatever the rates, so two detector models with the
    same generator seed share their noise (a paired comparison).
    """
    J = scene.joints
    shape = (len(cameras),) + J.shape[:2]
    exact = np.stack([cam.project(J) for cam in cameras])
    seen = np.stack([in_view(cam, J) for cam in cameras])
    if not detector.occlusion:
        occluded = np.zeros(shape, dtype=bool)
    elif occluded is None:
        occluded = scene_occlusion(cameras, scene)
    gauss = rng.normal(size=shape + (2,))
    outlier = rng.random(shape) < detector.outlier_rate
    radius = OUTLIER_RADIUS_PX * np.sqrt(rng.random(shape))  # uniform over the disc
    angle = 2 * np.pi * rng.random(shape)
    missed = rng.random(shape) < detector.miss_rate

    sigma = detector.noise_px * np.where(occluded, OCCLUDED_NOISE_FACTOR, 1.0)
    pixels = exact + sigma[..., None] * gauss
    jump = radius[..., None] * np.stack([np.cos(angle), np.sin(angle)], -1)
    pixels = np.where(outlier[..., None], exact + jump, pixels)
    for c, cam in enumerate(cameras):
        pixels[c] = np.clip(pixels[c], 0, [cam.width - 1, cam.height - 1])
    detected = seen & ~missed
    pixels[~detected] = np.nan
    confidence = np.where(detected, np.where(occluded, OCCLUDED_CONFIDENCE, 1.0), 0.0)
    return Keypoints(pixels, confidence, occluded, outlier)


def stacked(parts: list[Keypoints], axis: int) -> Keypoints:
    """Keypoints joined along ``axis``: 0 for cameras, 2 for tracks side by side (people)."""
    def cat(name):
        values = [getattr(k, name) for k in parts]
        return None if any(v is None for v in values) else np.concatenate(values, axis=axis)

    return Keypoints(cat("pixels"), cat("confidence"), cat("occluded"), cat("outlier"))


def keypoints_at_clocks(cameras: list[Camera], views: list[list[Scene]], draw, seed) -> Keypoints:
    """Keypoints (C, T, people x 24) of ``views`` ([camera][person] scenes, each camera's at its
    own clock: scene.seen_by_clocks), drawn by ``draw(cameras, scene, rng)`` (observe or
    observe_fitted with its model), each camera and person from its own stream of ``seed``."""
    return stacked([stacked([draw([cam], views[c][p], np.random.default_rng([*seed, c, p]))
                             for p in range(len(views[c]))], axis=2)
                    for c, cam in enumerate(cameras)], axis=0)


def _keypoint_path(folder: Path, camera: Camera, frame: int) -> Path:
    return folder / camera.name / f"{frame:06d}_keypoints.json"


def _frame_files(folder: Path, cameras: list[Camera]) -> list[dict[int, Path]]:
    """Per camera, frame number -> keypoint file (the digits before ``_keypoints.json``)."""
    found = []
    for cam in cameras:
        if not (folder / cam.name).is_dir():
            raise FileNotFoundError(f"{folder / cam.name}: no keypoint folder for camera "
                                    f"{cam.name!r}; expected <camera>/<frame:06d>_keypoints.json")
        files = {}
        for path in (folder / cam.name).glob("*_keypoints.json"):
            number = path.name[:-len("_keypoints.json")].rsplit("_", 1)[-1]
            if not number.isdigit():
                raise ValueError(f"{path}: expected a frame number before _keypoints.json")
            files[int(number)] = path
        found.append(files)
    return found


def read_openpose(folder, cameras: list[Camera], frames: int | None = None) -> Keypoints:
    """Detections from OpenPose-style JSON files (layout and joint order in the module notes).

    frames: how many frames (0 .. frames-1) to read; None reads up to the highest frame number
    found. Missing files, an empty ``people`` list and c = 0 mean "not detected".
    """
    files = _frame_files(Path(folder), cameras)
    if frames is None:
        if not any(files):
            raise FileNotFoundError(f"{folder}: no <frame:06d>_keypoints.json files")
        frames = max(max(f) for f in files if f) + 1
    pixels = np.full((len(cameras), frames, NUM_JOINTS, 2), np.nan)
    confidence = np.zeros((len(cameras), frames, NUM_JOINTS))
    for c in range(len(cameras)):
        for t, path in files[c].items():
            if t >= frames:
                continue
            try:
                people = read_json(path, "OpenPose JSON file")["people"]
            except (UnreadableFileError, KeyError, TypeError) as e:
                raise ValueError(f"{path}: expected OpenPose JSON with a 'people' list "
                                 f"({e})") from None
            if not people:
                continue
            values = np.asarray(people[0].get("pose_keypoints_2d", []), dtype=np.float64)
            if values.size != 3 * NUM_JOINTS:
                raise ValueError(
                    f"{path}: people[0].pose_keypoints_2d has {values.size} values; expected "
                    f"{3 * NUM_JOINTS} (x, y, c for SMPL's 24 joints in SMPL's order). Map "
                    f"OpenPose BODY_25/COCO keypoints to SMPL's joints first")
            xyc = values.reshape(NUM_JOINTS, 3)
            ok = xyc[:, 2] > 0
            pixels[c, t, ok] = xyc[ok, :2]
            confidence[c, t, ok] = xyc[ok, 2]
    return Keypoints(pixels, confidence)


#: Joints per person of the layouts :func:`read_tracks` reads, by name.
LAYOUTS = {"smpl24": NUM_JOINTS, "body25": 25}


def _person_id(person: dict) -> int:
    """A person's tracker id (OpenPose writes [-1] when it has none), -1 for none."""
    pid = person.get("person_id", -1)
    pid = pid[0] if isinstance(pid, list) and pid else pid
    return pid if isinstance(pid, int) and not isinstance(pid, bool) else -1


def read_tracks(folder, cameras: list[Camera]) -> tuple[np.ndarray, np.ndarray, str, list[int]]:
    """(pixels (C, T, N, 2) NaN where undetected, confidence (C, T, N), layout, person ids) of
    the OpenPose-style files under ``folder`` (module notes): N = people x joints, people in
    the order of their ids (one person, id -1, when the files give none)."""
    files = _frame_files(Path(folder), cameras)
    if not any(files):
        raise FileNotFoundError(f"{folder}: no <camera>/<frame>_keypoints.json files")
    T = max(max(f) for f in files if f) + 1
    docs, ids, widths = {}, set(), set()
    for c in range(len(cameras)):
        for t, path in files[c].items():
            try:
                people = read_json(path, "OpenPose JSON file")["people"]
                values = [np.asarray(p["pose_keypoints_2d"], dtype=np.float64) for p in people]
            except (UnreadableFileError, KeyError, TypeError, ValueError) as e:
                raise ValueError(f"{path}: expected OpenPose JSON with a 'people' list, each "
                                 f"with pose_keypoints_2d ({e})") from None
            widths |= {v.size for v in values}
            ids |= {_person_id(p) for p in people}
            docs[c, t] = [(_person_id(p), v) for p, v in zip(people, values)]
    layout = {3 * n: name for name, n in LAYOUTS.items()}
    if not widths or not widths <= set(layout) or len(widths) > 1:
        raise ValueError(f"{folder}: pose_keypoints_2d has {sorted(widths)} values per person; "
                         f"expected one layout: " + ", ".join(
                             f"{3 * n} ({name})" for name, n in LAYOUTS.items()))
    width = widths.pop()
    J = width // 3
    tracked = -1 not in ids
    people = sorted(ids) if tracked else [-1]
    pixels = np.full((len(cameras), T, len(people) * J, 2), np.nan)
    confidence = np.zeros((len(cameras), T, len(people) * J))
    for (c, t), found in docs.items():
        for k, (pid, values) in enumerate(found):
            if not tracked and k > 0:
                break  # without ids, people cannot be matched across cameras: the first only
            slot = people.index(pid) if tracked else 0
            xyc = values.reshape(J, 3)
            ok = (xyc[:, 2] > 0) & np.all(np.isfinite(xyc), axis=1)
            pixels[c, t, slot * J:(slot + 1) * J][ok] = xyc[ok, :2]
            confidence[c, t, slot * J:(slot + 1) * J][ok] = xyc[ok, 2]
    return pixels, confidence, layout[width], people


def write_openpose(folder, cameras: list[Camera], keypoints: Keypoints) -> None:
    """Write detections in the layout :func:`read_openpose` reads (undetected: 0, 0, 0); tracks
    of several people side by side (N = people x 24) as people with ids 0, 1, ..."""
    folder = Path(folder)
    people = keypoints.pixels.shape[2] // NUM_JOINTS
    for c, cam in enumerate(cameras):
        (folder / cam.name).mkdir(parents=True, exist_ok=True)
        for t in range(keypoints.pixels.shape[1]):
            entries = []
            for k in range(people):
                block = slice(k * NUM_JOINTS, (k + 1) * NUM_JOINTS)
                ok = keypoints.confidence[c, t, block] > 0
                xyc = np.zeros((NUM_JOINTS, 3))
                xyc[ok, :2] = keypoints.pixels[c, t, block][ok]
                xyc[ok, 2] = keypoints.confidence[c, t, block][ok]
                entries.append({"person_id": [k if people > 1 else -1],
                                "pose_keypoints_2d": xyc.reshape(-1).tolist()})
            write_json(_keypoint_path(folder, cam, t), {"version": 1.3, "people": entries})
