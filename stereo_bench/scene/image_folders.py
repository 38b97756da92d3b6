"""A real capture: a user's image folders behind the read interface of a rendered dataset.

Detection and calibration (evaluate/stage.py, pipeline.py) read a source's ``cameras`` (each with a
``name`` and an image ``size``), ``frames``, ``image(camera, frame)``, ``pattern``,
``object_points``, ``closeup_of`` and ``fingerprint``; a ``Dataset`` adds the ground truth, an
``ImageFolders`` has none. So a real capture runs every stage but the scoring.

Files. Each camera is a folder (or a glob such as ``data/left*.jpg``) of JPEG, PNG or TIFF images.
Frames are paired across cameras by the number in the file name: the last run of digits of the
stem (``left07.jpg``, ``cam2/0007.png`` and ``right_7.tif`` are all frame 7); a name without a
digit pairs by its whole stem. A frame one camera lacks is a frame that camera did not see.

Videos. A camera may instead be one video file (MP4, AVI, MOV, MKV, WebM), decoded with OpenCV.
Synchronised videos pair by frame index; videos whose frames were not triggered together pair by
a timestamps file (``read_timestamps``): each moment of the camera with the most frames takes
every other camera's frame nearest in time, within half that camera's median frame interval
(``paired_by_time``). Every ``stride``-th moment is taken, the stride raised so that at most
``max_frames`` moments are (a calibration needs tens of distinct views, not every frame of a
minute of video); only the frames taken are decoded. They are held in memory, PNG-compressed,
and named ``VIDEO@INDEX`` in the records, which also hold each moment's time spread.

Image size. A camera's image size is the most common size among its images (on a tie, the size
of its earliest image among the tied), so one odd image, first or not, cannot make the others
look wrong; the images of another size, and the unreadable ones, are named with their sizes in
the capture's warnings and recorded by the detection as frames not found.
"""

from __future__ import annotations

import glob
import hashlib
import re
from collections import Counter
import dataclasses
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from ..core.patterns import Pattern
from ..core.files import encode_png, is_safe_name, read_grey

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp")
VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v")
_LAST_NUMBER = re.compile(r"(\d+)(?!.*\d)")
#: Frames taken from the longest video by default (module notes).
MAX_VIDEO_FRAMES = 100


@dataclass(frozen=True)
class VideoFrame:
    """One frame taken from a video: its file, its index and its grey pixels as PNG bytes."""

    video: Path
    index: int
    png: bytes

    @property
    def name(self) -> str:
        return f"{self.video.name}@{self.index}"

    def __str__(self) -> str:
        return f"{self.video}@{self.index}"


def is_video(where: str) -> bool:
    return Path(where).suffix.lower() in VIDEO_SUFFIXES and Path(where).is_file()


def video_length(name: str, path: Path) -> int:
    """The frame count a video declares; a ValueError naming the camera when OpenCV cannot open
    it."""
    import cv2

    capture = cv2.VideoCapture(str(path))
    try:
        if not capture.isOpened():
            raise ValueError(f"camera {name!r}: {path} is not a video OpenCV can decode")
        return max(int(capture.get(cv2.CAP_PROP_FRAME_COUNT)), 0)
    finally:
        capture.release()


#: Column names a timestamps file may give its camera and its time (first match wins).
_CAMERA_COLUMNS = ("camera", "cam_id", "cam", "port")
_TIME_COLUMNS = ("time", "frame_time", "timestamp")


def _timestamp_camera(value: str, names: list[str]) -> str | None:
    """The camera a timestamps row names: by its name, or by the number its name ends with
    (``0`` is ``cam_0``)."""
    if value in names:
        return value
    numbered = [n for n in names if (m := _LAST_NUMBER.search(n)) and value.isdigit()
                and int(m.group(1)) == int(value)]
    return numbered[0] if len(numbered) == 1 else None


def read_timestamps(path, lengths: dict[str, int]) -> dict[str, np.ndarray]:
    """Per camera, the time of each frame of its video, from a CSV file with a header naming a
    camera column (one of ``_CAMERA_COLUMNS``) and a time column (``_TIME_COLUMNS``, seconds);
    a camera's rows, in time order, are its video's frames in order, so their count must be the
    video's frame count (``lengths``). ValueError naming the file and what is wrong."""
    import csv
    import io

    from ..core.files import read_text

    rows = list(csv.DictReader(io.StringIO(read_text(path, "timestamps file"))))
    header = list(rows[0]) if rows else []
    cam_col = next((c for c in _CAMERA_COLUMNS if c in header), None)
    time_col = next((c for c in _TIME_COLUMNS if c in header), None)
    if cam_col is None or time_col is None:
        raise ValueError(f"timestamps file {path}: expected a header with a camera column "
                         f"({', '.join(_CAMERA_COLUMNS)}) and a time column "
                         f"({', '.join(_TIME_COLUMNS)}) and a row per frame; found columns "
                         f"{header or 'none'}")
    times: dict[str, list[float]] = {n: [] for n in lengths}
    for line, row in enumerate(rows, 2):
        cam = _timestamp_camera(str(row[cam_col]).strip(), list(lengths))
        if cam is None:
            continue  # a camera of the session that is not calibrated now
        try:
            t = float(row[time_col])
        except (TypeError, ValueError):
            t = float("nan")
        if not np.isfinite(t):
            raise ValueError(f"timestamps file {path}, line {line}: {time_col} "
                             f"{row[time_col]!r} is not a time in seconds")
        times[cam].append(t)
    for name, n in lengths.items():
        if len(times[name]) != n:
            raise ValueError(f"timestamps file {path}: {len(times[name])} rows for camera "
                             f"{name!r}, whose video has {n} frames; expected one row per frame")
    return {n: np.sort(np.array(t)) for n, t in times.items()}


def paired_by_time(times: dict[str, np.ndarray]) -> tuple[list[dict[str, int]], list[float]]:
    """The moments of a capture whose cameras were not triggered together (module notes): per
    moment, each camera's frame index (a camera whose nearest frame is too far is absent), and
    the moment's spread of times, s."""
    names = list(times)
    ref = max(names, key=lambda n: len(times[n]))  # first of the longest on a tie
    moments = [{ref: i} for i in range(len(times[ref]))]
    for name in names:
        if name == ref or len(times[name]) == 0:
            continue
        t, t_ref = times[name], times[ref]
        tolerance = 0.5 * float(np.median(np.diff(t))) if len(t) > 1 else np.inf
        after = np.searchsorted(t, t_ref)
        lo, hi = np.clip(after - 1, 0, len(t) - 1), np.clip(after, 0, len(t) - 1)
        nearest = np.where(np.abs(t[lo] - t_ref) <= np.abs(t[hi] - t_ref), lo, hi)
        taken: dict[int, int] = {}  # a frame serves the reference moment nearest to it only
        for i, j in enumerate(nearest.tolist()):
            gap = abs(t[j] - t_ref[i])
            if gap <= tolerance and (j not in taken or gap < abs(t[j] - t_ref[taken[j]])):
                taken[j] = i
        for j, i in taken.items():
            moments[i][name] = j
    spread = [float(np.ptp([times[n][j] for n, j in m.items()])) for m in moments]
    return moments, spread


def video_frames(name: str, path: Path, wanted) -> list[VideoFrame]:
    """The frames of a video whose indices are in ``wanted`` (a set, or a range), decoded in
    order (seeking is not exact in every codec), as grey."""
    import cv2

    capture, frames, index = cv2.VideoCapture(str(path)), [], 0
    last = max(wanted, default=-1)
    try:
        while index <= last and capture.grab():
            if index in wanted:
                ok, image = capture.retrieve()
                if ok:
                    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
                    frames.append(VideoFrame(path, index, encode_png(grey)))
            index += 1
    finally:
        capture.release()
    if not frames:
        raise ValueError(f"camera {name!r}: no frame could be decoded from {path}")
    return frames


def read_item(item) -> np.ndarray | None:
    """The grey pixels of an image file or a video frame; None when they cannot be read."""
    if isinstance(item, VideoFrame):
        import cv2

        return cv2.imdecode(np.frombuffer(item.png, np.uint8), cv2.IMREAD_GRAYSCALE)
    return read_grey(item)


@dataclass(frozen=True)
class ImageCamera:
    """A camera of a real capture: its name and image size, nothing else is known."""

    name: str
    width: int
    height: int

    @property
    def size(self) -> tuple[int, int]:
        return (self.width, self.height)


def frame_key(path: Path) -> tuple[int, int | str]:
    """What pairs an image with the other cameras' images of the same moment (module notes);
    numbered frames sort by number, before named ones."""
    m = _LAST_NUMBER.search(path.stem)
    return (0, int(m.group(1))) if m else (1, path.stem)


def _images_of(name: str, where: str) -> list[Path]:
    path = Path(where)
    if path.is_dir():
        files = [p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES]
        what = f"folder {where}"
    else:
        files = [Path(p) for p in glob.glob(where) if Path(p).suffix.lower() in IMAGE_SUFFIXES]
        what = f"pattern {where!r}" if glob.has_magic(where) else f"{where}"
    if not files:
        raise FileNotFoundError(f"camera {name!r}: no JPEG, PNG or TIFF image in {what}")
    keys: dict = {}
    for p in sorted(files):
        k = frame_key(p)
        if k in keys:
            raise ValueError(f"camera {name!r}: {keys[k].name} and {p.name} are both frame "
                             f"{k[1]}; expected one image per frame (frames pair by the last "
                             f"number in the file name)")
        keys[k] = p
    return [keys[k] for k in sorted(keys)]


def _image_size(path) -> tuple[int, int] | None:
    """(width, height) of an image as ``ImageFolders.image`` reads it (grey, so EXIF orientation
    is applied alike), or None when OpenCV cannot read it."""
    img = read_item(path)
    return None if img is None else (img.shape[1], img.shape[0])


#: Odd or unreadable images named in a camera's warning before "and N more".
_NAMED = 5


def _named(paths: list[str]) -> str:
    more = f" and {len(paths) - _NAMED} more" if len(paths) > _NAMED else ""
    return ", ".join(paths[:_NAMED]) + more


def camera_size(name: str, paths: list[Path]) -> tuple[tuple[int, int], str | None]:
    """A camera's image size, the most common among its images (module notes), and a warning
    naming the images of another size (with theirs) and the unreadable ones, or None.
    ValueError naming the camera when none of its images can be read."""
    sizes = {p: _image_size(p) for p in paths}
    votes = Counter(s for s in sizes.values() if s is not None)
    if not votes:
        raise ValueError(f"camera {name!r}: none of its {len(paths)} images is one OpenCV can "
                         f"read (e.g. {paths[0]})")
    size = votes.most_common(1)[0][0]  # ties: the earliest image's, as Counter keeps order
    odd = [f"{p.name} ({s[0]}x{s[1]} px)" for p, s in sizes.items()
           if s is not None and s != size]
    unreadable = [p.name for p, s in sizes.items() if s is None]
    if not odd and not unreadable:
        return size, None
    parts = [f"{len(odd)} of another size: {_named(odd)}"] if odd else []
    if unreadable:
        parts.append(f"{len(unreadable)} OpenCV cannot read (or over 64 M pixels): "
                     f"{_named(unreadable)}")
    return size, (f"camera {name!r}: its images are {size[0]}x{size[1]} px ({votes[size]} of "
                  f"{len(paths)}); left out, " + "; ".join(parts))


@dataclass(frozen=True, eq=False)
class ImageFolders:
    """The images of every camera of a real capture, paired by frame (module notes).

    files[c][f]: camera c's image of frame f, or None; keys[f]: frame f's pairing key.
    """

    cameras: list[ImageCamera]
    files: list[list[Path | None]]
    keys: list[tuple[int, int | str]]
    pattern: Pattern
    #: Per camera with odd or unreadable images, the warning naming them (camera_size).
    size_warnings: tuple[str, ...] = ()
    #: Videos paired by a timestamps file: per frame key, the spread of its cameras' times, s.
    time_spread: dict = dataclasses.field(default_factory=dict)

    @classmethod
    def open(cls, cameras: dict[str, str], pattern: Pattern, stride: int = 1,
             max_frames: int = MAX_VIDEO_FRAMES, timestamps=None) -> "ImageFolders":
        """``cameras``: name -> folder, glob or video file. Raises ValueError or
        FileNotFoundError naming the camera and the file when a folder is empty, a name is
        unusable, a video cannot be decoded or none of a camera's images can be read; images of
        another size than most of a camera's are named in ``warnings``. ``stride``,
        ``max_frames`` and ``timestamps`` (a file, for videos only): the frames taken from
        videos and their pairing (module notes)."""
        if not cameras:
            raise ValueError("cameras: expected at least one camera folder")
        if stride < 1 or max_frames < 2:
            raise ValueError(f"--frame-stride {stride}, --max-frames {max_frames}: expected a "
                             f"stride of at least 1 and at least 2 frames")
        for name in cameras:
            if not is_safe_name(name):
                raise ValueError(f"camera name {name!r}: expected letters, digits, '_', '-' or "
                                 f"'.' (it names files of the output)")
        videos = {n: Path(w) for n, w in cameras.items() if is_video(w)}
        lengths = {n: video_length(n, p) for n, p in videos.items()}
        if timestamps is not None and len(videos) < len(cameras):
            raise ValueError(f"--timestamps {timestamps}: pairs videos; camera(s) "
                             f"{', '.join(repr(n) for n in cameras if n not in videos)} are "
                             f"images, which pair by the number in their names")
        if timestamps is not None:
            moments, spread = paired_by_time(read_timestamps(timestamps, lengths))
        else:
            moments = [{n: i for n in videos if i < lengths[n]}
                       for i in range(max(lengths.values(), default=0))]
            spread = [0.0] * len(moments)
        taken = range(0, len(moments), max(stride, -(-len(moments) // max_frames)))
        per_camera = {}
        for name, where in cameras.items():
            if name in videos:
                frame_of = {moments[i][name]: (0, i) for i in taken if name in moments[i]}
                per_camera[name] = {frame_of[f.index]: f
                                    for f in video_frames(name, videos[name], frame_of)}
                continue
            per_camera[name] = {frame_key(p): p for p in _images_of(name, where)}
        keys = sorted(set().union(*per_camera.values()))
        files = [[images.get(k) for k in keys] for images in per_camera.values()]
        cams, warnings = [], []
        for name, row in zip(per_camera, files):
            size, warning = camera_size(name, [p for p in row if p is not None])
            cams.append(ImageCamera(name, *size))
            warnings += [warning] if warning else []
        spreads = {(0, i): spread[i] for i in taken} if timestamps is not None else {}
        return cls(cams, files, keys, pattern, tuple(warnings), spreads)

    @property
    def frames(self) -> int:
        return len(self.keys)

    @property
    def object_points(self) -> np.ndarray:
        return self.pattern.object_points()

    @property
    def closeup_of(self) -> np.ndarray:
        """(F,) -1: a real capture has no close-ups marked (``intrinsics_views: all``)."""
        return np.full(self.frames, -1)

    @property
    def warnings(self) -> list[str]:
        alone = [self.frame_name(f) for f in range(self.frames)
                 if sum(row[f] is not None for row in self.files) == 1]
        out = []
        if len(self.cameras) > 1 and alone:
            out.append(f"{len(alone)} frame(s) have an image from one camera only (e.g. "
                       f"{alone[0]}): they serve that camera's intrinsics, not the rig")
        return out + list(self.size_warnings)

    def frame_name(self, frame: int) -> str:
        kind, key = self.keys[frame]
        return f"frame {key}" if kind == 0 else str(key)

    def image(self, camera: int, frame: int) -> np.ndarray:
        """8-bit grey image of ``camera`` at ``frame``; FileNotFoundError when the camera has no
        image of that frame, ValueError when it cannot be read or differs in size (both are
        recorded by the detection as a frame not found)."""
        cam, path = self.cameras[camera], self.files[camera][frame]
        if path is None:
            raise FileNotFoundError(f"camera {cam.name!r} has no image of {self.frame_name(frame)}")
        img = read_item(path)
        if img is None:
            raise ValueError(f"{path}: not an image OpenCV can read (or over 64 M pixels)")
        if (img.shape[1], img.shape[0]) != cam.size:
            raise ValueError(f"{path}: {img.shape[1]}x{img.shape[0]} px, expected {cam.width}x"
                             f"{cam.height} px like most of camera {cam.name!r}'s images")
        return img

    @cached_property
    def fingerprint(self) -> str:
        """Of the images' bytes, their pairing and the board: detections are reused only for
        exactly these images of exactly this board."""
        h = hashlib.sha256(repr(self.pattern).encode())
        for cam, row in zip(self.cameras, self.files):
            h.update(cam.name.encode())
            for path in row:
                data = b"-" if path is None else (
                    path.png if isinstance(path, VideoFrame) else path.read_bytes())
                h.update(hashlib.sha256(data).digest())
        return h.hexdigest()[:16]

    def index(self) -> dict:
        """The pairing, for the run's records: per frame its key and each camera's file."""
        return {"cameras": [c.name for c in self.cameras],
                "frames": [{"frame": self.frame_name(f),
                            "files": {c.name: None if row[f] is None else str(row[f])
                                      for c, row in zip(self.cameras, self.files)},
                            **({"time_spread_s": self.time_spread[self.keys[f]]}
                               if self.keys[f] in self.time_spread else {})}
                           for f in range(self.frames)]}
