"""The studio both multi-camera references are checked on (tests/studio_scene.py)."""

import pytest
from studio_scene import exact_views, studio


@pytest.fixture(scope="module")
def rig():
    return studio()


@pytest.fixture(scope="module")
def exact(rig):
    return exact_views(rig)
