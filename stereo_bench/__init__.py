"""SynthCal: camera calibration benchmarked against exact synthetic ground truth."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("synthcal-bench")
except PackageNotFoundError:  # a source tree that is not installed
    __version__ = "0+unknown"
