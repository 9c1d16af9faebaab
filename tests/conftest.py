import os

import numpy as np
import pytest

from reachwatch.systems import CameraConfig

# Generated textures go to a per-session folder so tests never depend on ~/.cache.
os.environ.setdefault("REACHWATCH_CACHE", os.path.join(
    os.environ.get("PYTEST_CACHE_ROOT", "/tmp"), f"reachwatch-test-cache-{os.getuid()}"))


@pytest.fixture
def small_camera():
    """64x128 keeps renders fast in tests."""
    return CameraConfig(width=128, height=64)


@pytest.fixture
def tiny_camera():
    return CameraConfig(width=64, height=32)


def deg(x):
    return np.deg2rad(x)
