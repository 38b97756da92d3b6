"""Calibration methods behind one registry: ``get_calibrator(name, **options)``.

A name is ``BASE`` or ``BASE-MODEL`` (``lens_models.py``): ``zhang-brown`` is Zhang's algorithm
fitting k1, k2, p1, p2, k3. Each calibrator declares the lens models it can fit
(``lens_models``; empty for a method with a model of its own, Tsai's) and a one-line
``own_model``, what plain ``BASE`` fits.

Methods are imported on first use, so one method's module (or its optional dependencies) failing
to import does not take the others down.
"""

from __future__ import annotations

from importlib import import_module

from .base import CalibrationResult, Calibrator, Observations
from .lens_models import LENS_MODELS, describe_lens_models, method_name

# base name -> (module, class)
_BASES = {
    "zhang": ("zhang", "ZhangCalibrator"),
    "tsai": ("tsai", "TsaiCalibrator"),
    "bouguet": ("bouguet", "BouguetCalibrator"),
    "opencv": ("opencv_ref", "OpenCVCalibrator"),
}
# What a run lists and uses for its defaults: the four algorithms with their own models and the
# 8-coefficient OpenCV reference. Every other BASE-MODEL name is accepted (``check_methods``) but
# not listed, so a run's default method list does not grow with the lens-model family.
_LISTED = ("zhang", "tsai", "bouguet", "opencv", "opencv-rational")


def available_methods() -> list[str]:
    return list(_LISTED)


def _calibrator_class(base: str):
    module, cls = _BASES[base]
    return getattr(import_module(f".{module}", __name__), cls)


def _lens_bases() -> list[str]:
    return [b for b in _BASES if _calibrator_class(b).lens_models]


def describe_methods() -> str:
    """Every accepted name, in words, for messages and help texts."""
    return (f"{', '.join(_LISTED)}, or BASE-MODEL with BASE one of {', '.join(_lens_bases())} "
            f"and MODEL one of {describe_lens_models()}")


def parse_method(name: str) -> tuple[str, str | None]:
    """(base, lens model or None) of a method name; a ValueError says why a name is refused."""
    base, dash, model = str(name).partition("-")
    if base not in _BASES:
        raise ValueError(f"unknown calibration method {name!r}; available: {describe_methods()}")
    if not dash:
        return base, None
    if model not in LENS_MODELS:
        raise ValueError(f"unknown lens model {model!r} in method {name!r}; lens models: "
                         f"{describe_lens_models()}")
    cls = _calibrator_class(base)
    if model not in cls.lens_models:
        fits = (f"lens models {', '.join(cls.lens_models)}" if cls.lens_models
                else f"{cls.own_model}; lens models apply to {', '.join(_lens_bases())}")
        raise ValueError(f"method {name!r}: {base} fits {fits}")
    return base, model


def is_method(name: str) -> bool:
    try:
        parse_method(name)
    except ValueError:
        return False
    return True


def check_methods(names) -> None:
    """Raise the ValueError of the first refused name in ``names`` (a grid's or a CLI's list)."""
    for name in names:
        parse_method(name)


def methods_for_lens(names, lens_model: str) -> list[str]:
    """``names`` made to fit ``lens_model``: a plain ``BASE`` becomes ``BASE-lens_model``, a name
    that already fits it stays. ValueError naming the method that cannot fit it (Tsai's has a
    model of its own) or that names another lens model."""
    from .lens_models import free_coefficients

    free_coefficients(lens_model)  # an unknown lens model is refused with the list
    out = []
    for name in names:
        base, model = parse_method(name)
        if model not in (None, lens_model):
            raise ValueError(f"method {name!r} fits the {model} lens model, not {lens_model}")
        out.append(method_name(base, lens_model))
        parse_method(out[-1])  # refuses a base that cannot fit it, saying which models it fits
    return list(dict.fromkeys(out))


def fits_board_warp(name: str) -> bool:
    """Whether method ``name`` can fit the board's warp (``board_warp=True``)."""
    return bool(getattr(_calibrator_class(parse_method(name)[0]), "fits_board_warp", False))


def get_calibrator(name: str, **options) -> Calibrator:
    """A calibrator by registry name; ``options`` go to its constructor."""
    base, model = parse_method(name)
    cls = _calibrator_class(base)
    return cls(**options) if model is None else cls(lens_model=model, **options)


__all__ = ["CalibrationResult", "Calibrator", "Observations", "available_methods",
           "check_methods", "describe_methods", "fits_board_warp", "get_calibrator", "is_method",
           "methods_for_lens",
           "parse_method"]
