"""What one request of the web app may cost, counted before any of it is done.

The web app serves whoever can reach it, one job at a time: a valid rig of an 8000x8000 camera
with 16x16 supersampling, or 10,000 frames of two 12 MP cameras, is a fine command-line run and
an afternoon of a shared server. Its cost is counted in rendered samples (pixels x
supersampling^2, per camera and frame), the quantity render time follows; a request over the
budget is refused with its count, the budget and what to change. Motion blur and defocus
multiply the time per sample and are not counted here: the preview's deadline
(preview.PREVIEW_SECONDS) and a job's cancel cover them.
"""

from __future__ import annotations

from ..config.schema import RigConfig

#: One preview frame: the paper's 4096x3072 camera at 2x2 supersampling is 50 M samples.
MAX_PREVIEW_SAMPLES = 64_000_000
#: One job (every frame of every camera, over every configuration and trial of a sweep): the
#: paper's rectilinear pair, 127 frames at 2x2 supersampling, is 1.3e10 samples (minutes here).
MAX_JOB_SAMPLES = 20_000_000_000


def frame_samples(cfg: RigConfig, camera: int) -> int:
    """Samples of one frame of camera ``camera``: its pixels times the supersampling squared."""
    cam = cfg.cameras_true()[camera]
    return cam.width * cam.height * cfg.environment.supersampling ** 2


def rig_samples(cfg: RigConfig) -> int:
    """Samples of every frame of every camera of one trial of the rig."""
    cameras = cfg.cameras_true()
    pixels = sum(c.width * c.height for c in cameras)
    return pixels * cfg.environment.supersampling ** 2 * cfg.trajectory.frames_for(len(cameras))


def refuse_preview(cfg: RigConfig, camera: int) -> None:
    samples = frame_samples(cfg, camera)
    if samples > MAX_PREVIEW_SAMPLES:
        raise ValueError(f"preview: camera {camera} renders {samples:,} samples (pixels x "
                         f"supersampling^2); the web app previews at most "
                         f"{MAX_PREVIEW_SAMPLES:,}: lower environment.supersampling or the "
                         f"image size")


def refuse_job(samples: int, what: str) -> None:
    if samples > MAX_JOB_SAMPLES:
        raise ValueError(f"{what}: {samples:,} samples to render (pixels x supersampling^2 x "
                         f"frames, every camera{', configuration and trial' if 'sweep' in what else ''}); "
                         f"the web app runs at most {MAX_JOB_SAMPLES:,} per job: fewer frames or "
                         f"a lower supersampling, or run it from the command line "
                         f"(stereo-bench RIG.yaml)")
