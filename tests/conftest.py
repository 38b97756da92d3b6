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
