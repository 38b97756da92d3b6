"""Calibration methods behind one registry: ``get_calibrator(name, **options)``.

Methods are imported on first use, so one method's module (or its optional dependencies) failing
to import does not take the others down.
"""

from __future__ import annotations

from importlib import import_module

from .base import CalibrationResult, Calibrator, Observations

# name -> (module, class, fixed options)
_METHODS = {
    "zhang": ("zhang", "ZhangCalibrator", {}),
    "tsai": ("tsai", "TsaiCalibrator", {}),
    "bouguet": ("bouguet", "BouguetCalibrator", {}),
    "opencv": ("opencv_ref", "OpenCVCalibrator", {"rational": False}),
    "opencv-rational": ("opencv_ref", "OpenCVCalibrator", {"rational": True}),
}


def available_methods() -> list[str]:
    return list(_METHODS)


def get_calibrator(name: str, **options) -> Calibrator:
    """A calibrator by registry name; ``options`` go to its constructor."""
    if name not in _METHODS:
        raise ValueError(f"unknown calibration method {name!r}; available: {available_methods()}")
    module, cls, fixed = _METHODS[name]
    return getattr(import_module(f".{module}", __name__), cls)(**fixed, **options)


__all__ = ["CalibrationResult", "Calibrator", "Observations", "available_methods",
           "get_calibrator"]
