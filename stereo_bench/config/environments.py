"""Environment presets: the imaging model's settings for situations a user knows.

``environment.kind`` names one; its values fill every field the rig file leaves out (a field
given in the file wins), and the resolved configuration lists the result. Each preset says what
it reproduces and the reprojection error OpenCV's own pipeline (cv2.findChessboardCorners,
cv2.cornerSubPix, cv2.calibrateCamera) was tuned to reach on it: about 0.15 px for a
machine-vision camera, 0.4 px for a consumer camera (OpenCV's sample stereo pair calibrates at
0.41 and 0.46 px), about 1 px for the paper's noisy renders. They were tuned on the paper's
wide-angle camera (640 x 480, the size of OpenCV's sample images) with its 9 x 12 checkerboard of
15 mm squares on the conical spring; the same settings give other figures on other cameras and
boards (a warp's pixels grow with the focal length). ``benchmarks/imaging_presets.py``
measures them; docs/imaging.md lists the figures.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Preset:
    description: str
    target_rpe_px: float | None
    settings: dict


PRESETS: dict[str, Preset] = {
    "clean": Preset("an ideal camera: uniform light, a pinhole, no motion, no noise", None, {}),
    "noisy": Preset(
        "the suite's first noisy environment: a lamp's shading and additive Gaussian noise of "
        "6 grey levels", None,
        {"light": {"ambient": 0.35}, "sensor": {"noise_sigma": 6.0}}),
    "studio": Preset(
        "a machine-vision camera in a lit studio: f/8 focused on the working distance, a 2 ms "
        "shutter on a board carried at 0.2 m/s, a 10,000 e- sensor well exposed, lossless "
        "output, a stiff board bowed by half a millimetre", 0.15,
        {"light": {"ambient": 0.7},
         "optics": {"f_number": 8.0, "focal_length_mm": 8.0, "corner_illumination": 0.85},
         "motion": {"exposure_ms": 2.0, "speed_mm_s": 200.0},
         "sensor": {"full_well_e": 10000.0, "exposure": 0.6, "read_noise_e": 6.0},
         "board": {"warp_mm": [0.5, 0.5]}}),
    "office": Preset(
        "a consumer camera in an office: f/2.8, a 15 ms shutter on a hand-held board, uneven "
        "light with a highlight on the glossy print, JPEG at quality 85, a print on card bowed "
        "by 1.6 mm and stretched 0.2 % along the paper", 0.4,
        {"light": {"ambient": 0.5, "specular": 0.15, "shininess": 30.0},
         "optics": {"f_number": 2.8, "focal_length_mm": 4.5, "blur_px": 0.5,
                    "corner_illumination": 0.6},
         "motion": {"exposure_ms": 15.0, "speed_mm_s": 150.0},
         "sensor": {"full_well_e": 6000.0, "exposure": 0.35, "read_noise_e": 3.0,
                    "jpeg_quality": 85},
         "board": {"warp_mm": [1.6, 1.0], "aspect_error_pct": 0.2}}),
    "handheld_low_light": Preset(
        "a phone in dim light: f/1.8 wide open, a 33 ms shutter on a hand-held board, 5 % of "
        "the well exposed and amplified, JPEG at quality 80, a print bowed by 1.5 mm", 0.4,
        {"light": {"ambient": 0.4},
         "optics": {"f_number": 1.8, "focal_length_mm": 4.0, "blur_px": 0.6,
                    "corner_illumination": 0.5},
         "motion": {"exposure_ms": 33.0, "speed_mm_s": 80.0},
         "sensor": {"full_well_e": 4000.0, "exposure": 0.05, "read_noise_e": 3.0,
                    "jpeg_quality": 80},
         "board": {"warp_mm": [1.5, 0.9]}}),
    "paper_noisy": Preset(
        "the paper's noisy renders: a lamp's shading, a soft lens and strong sensor noise", 1.0,
        {"light": {"ambient": 0.35},
         "optics": {"blur_px": 1.75},
         "sensor": {"noise_sigma": 32.0}}),
}
