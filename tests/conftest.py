import os

import numpy as np
import pytest

from reachwatch.systems import CameraConfig

# Generated textures go to a per-session folder so tests never depend on ~/.cache.
os.environ.setdefault("REACHWATCH_CACHE", os.path.join(
    os.environ.get("PYTEST_CACHE_ROOT", "/tmp"), f"reachwatch-test-cache-{os.getuid()}"))
# Tests sweep tiny grids: one worker, whose start-up a second would only double
# (tests/test_worker_pool.py asks for its pools' sizes explicitly).
os.environ.setdefault("REACHWATCH_WORKERS", "1")


@pytest.fixture
def small_camera():
    """64x128 keeps renders fast in tests."""
    return CameraConfig(width=128, height=64)


@pytest.fixture
def tiny_camera():
    return CameraConfig(width=64, height=32)


def deg(x):
    return np.deg2rad(x)


@pytest.fixture(scope="session")
def detector_path(tmp_path_factory):
    """An untrained tiny detector checkpoint (seeded) for the 200x360 default camera."""
    import torch
    from reachwatch.diagrams import save_checkpoint
    from reachwatch.systems import DetectorConfig, build_detector
    config = DetectorConfig(height=24, width=40, channels=[4, 8])
    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("det") / "detector.pt"
    save_checkpoint(path, kind="detector", model=build_detector(config), model_config=config,
                    preprocess_config=None, metadata={"image_size": [200, 360]})
    return path


@pytest.fixture(scope="session")
def kmwh_day_brt():
    """``(scenario, value function)`` of a small real loop for label tests: KMWH 9 h
    clear (the default camera and TaxiNet), the paper's box at 5x3x5, the P-controller's
    steering on the true state as the table, a 1 s horizon."""
    from reachwatch.diagrams import load_scenario
    from reachwatch.reach import solve_brt
    from reachwatch.taxi import TaxiDynamics, paper_grid
    scenario = load_scenario(data="environment: {runway: KMWH, hour: 9.0, sky: clear}\n")
    B = scenario.environment.half_width
    grid = paper_grid(B, (5, 3, 5))
    px, _, th = grid.mesh()
    table = np.deg2rad(-0.74 * px - 0.44 * np.rad2deg(th))
    return scenario, solve_brt(grid, TaxiDynamics(half_width=B), table, horizon=1.0,
                               device="cpu")
