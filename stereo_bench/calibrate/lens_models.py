"""The lens models a calibration method can be asked to fit: the second axis of a method name.

A method name is ``BASE`` (the algorithm with the model it has always fitted) or ``BASE-MODEL``
(the same initialisation and optimisation with MODEL's distortion coefficients free), so a
comparison can tell what an algorithm costs from what its lens model costs. The family is named
by the coefficients of the camera core's OpenCV model (order k1, k2, p1, p2, k3, k4, k5, k6) that
it frees; every other coefficient stays exactly 0:

    radial2   k1, k2                       Zhang's model
    radial3   k1, k2, k3
    radtan    k1, k2, p1, p2               OpenCV's 4 (Kalibr's pinhole-radtan, COLMAP's OPENCV,
                                           mrcal's LENSMODEL_OPENCV4): exports to every format
    brown     k1, k2, p1, p2, k3           OpenCV's default 5 (Brown-Conrady)
    rational  k1, k2, p1, p2, k3, k4, k5, k6   OpenCV's CALIB_RATIONAL_MODEL 8

and by the wide-angle lenses of the camera core (core/lens.py), each with all its parameters:

    fisheye       Kannala-Brandt k1, k2, k3, k4     cv2.fisheye, Kalibr pinhole-equi, COLMAP
                                                    OPENCV_FISHEYE
    omnidir       Mei xi, k1, k2, p1, p2            cv2.omnidir, Kalibr omni-radtan
    doublesphere  double sphere xi, alpha           Kalibr ds

This module is the one place that knows the family; each calibrator maps the freed names to
its own mechanism (a free mask for refine.py, calibrateCamera flags for OpenCV).
"""

from __future__ import annotations

LENS_MODELS: dict[str, tuple[str, ...]] = {
    "radial2": ("k1", "k2"),
    "radial3": ("k1", "k2", "k3"),
    "radtan": ("k1", "k2", "p1", "p2"),
    "brown": ("k1", "k2", "p1", "p2", "k3"),
    "rational": ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
    "fisheye": ("k1", "k2", "k3", "k4"),
    "omnidir": ("xi", "k1", "k2", "p1", "p2"),
    "doublesphere": ("xi", "alpha"),
}
# The camera core's lens model (core/lens.py) of each: OpenCV's pinhole unless named here.
CORE_LENS = {"fisheye": "kannala_brandt", "omnidir": "mei", "doublesphere": "double_sphere"}
PINHOLE_MODELS = tuple(m for m in LENS_MODELS if m not in CORE_LENS)


def core_lens(lens_model: str | None) -> str:
    """The core lens model (core/lens.py) a method fitting ``lens_model`` estimates."""
    return CORE_LENS.get(lens_model, "opencv")


def describe_lens_models() -> str:
    """``radial2 (k1 k2), radial3 (k1 k2 k3), ...`` for messages and help texts."""
    return ", ".join(f"{m} ({' '.join(c)})" for m, c in LENS_MODELS.items())


def free_coefficients(lens_model: str) -> tuple[str, ...]:
    """The distortion coefficients ``lens_model`` frees, in OpenCV order."""
    if lens_model not in LENS_MODELS:
        raise ValueError(f"unknown lens model {lens_model!r}; lens models: "
                         f"{describe_lens_models()}")
    return LENS_MODELS[lens_model]


def method_name(base: str, lens_model: str | None) -> str:
    """The registry name of ``base`` fitting ``lens_model`` (None: the base's own model)."""
    return base if lens_model is None else f"{base}-{lens_model}"
