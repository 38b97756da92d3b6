"""SynthCal: camera calibration benchmarked against exact synthetic ground truth."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("synthcal-bench")
except PackageNotFoundError:  # a source tree that is not installed
    __version__ = "0+unknown"

# An image file may claim any size in its header; OpenCV decodes up to 2^30 pixels unless told
# otherwise, so a 100 kB PNG could ask for a gigabyte. Images are held to the rig file's bound
# on a camera (config.MAX_IMAGE_PIXELS, 64 M pixels); the variable is read at the first decode.
import os as _os

_os.environ.setdefault("OPENCV_IO_MAX_IMAGE_PIXELS", str(64_000_000))
