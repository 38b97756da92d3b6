"""Test-session settings.

One BLAS thread: scipy's sparse least-squares issues many small threaded dot products, which
stall when the machine is busier than its cores; tests measure numbers, not speed.
"""

import os

import pytest

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")


@pytest.fixture(scope="module")
def rays():
    """rays(camera): the camera's PixelRays, built once per test module (the slow part of a
    render)."""
    from stereo_bench.render import PixelRays

    cache = {}

    def get(cam):
        if cam.name not in cache:
            cache[cam.name] = PixelRays(cam)
        return cache[cam.name]
    return get


def _opencv_pair():
    """OpenCV's sample stereo pair (real photographs, /work/shared/real/opencv_stereo on these
    machines): $SYNTHCAL_REAL_IMAGES, else beside the repository, else that path."""
    from pathlib import Path

    here = Path(__file__).resolve().parents[2] / "shared" / "real" / "opencv_stereo"
    for path in (os.environ.get("SYNTHCAL_REAL_IMAGES"), here, "/work/shared/real/opencv_stereo"):
        if path and Path(path).is_dir():
            return Path(path)
    return None


OPENCV_PAIR = _opencv_pair()


@pytest.fixture(scope="session")
def opencv_pair():
    """The folder of OpenCV's real sample pair; the test skips, saying why, where it is absent."""
    if OPENCV_PAIR is None:
        pytest.skip("OpenCV's sample stereo pair is not on this machine (set SYNTHCAL_REAL_IMAGES "
                    "to its folder)")
    return OPENCV_PAIR
