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
                    preprocess_config=None, metadata={"image_size": [200, 360], "threshold": 0.5})
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


#: The cache folders of a run directory that hold rendered work, keyed by content
#: (sweep chunks, real-loop outcome chunks, datasets): what `seed_caches` copies.
RENDERED_CACHES = ("sweeps", "outcomes", "datasets")


def _shared_root(tmp_path_factory):
    """The session's temporary folder, shared by pytest-xdist's workers."""
    root = tmp_path_factory.getbasetemp()
    return root.parent if os.environ.get("PYTEST_XDIST_WORKER") else root


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory):
    """The whole tiny run (tests/tiny_run.py), rendered from nothing once per session
    (once for all xdist workers): ``(folder, log)``. Tests read it and never write it;
    a test that changes a run copies the folder, or seeds a new run folder with its
    rendered caches (`seed_caches`), whose content keys make them safe to share."""
    import json
    from filelock import FileLock
    from reachwatch.pipeline.run import run_pipeline
    from reachwatch.pipeline.spec import load_run_spec
    from tiny_run import TINY
    root = _shared_root(tmp_path_factory)
    out, record = root / "tiny_run", root / "tiny_run.log.json"
    with FileLock(str(root / "tiny_run.lock")):
        if not record.exists():
            log = []
            run_pipeline(load_run_spec(data=TINY), out, progress=False, log=log.append)
            record.write_text(json.dumps(log))
    return out, json.loads(record.read_text())


@pytest.fixture(scope="session")
def seed_caches(tiny_run):
    """``seed_caches(folder)``: copy the tiny run's rendered caches into a new run
    folder, so that a test of the pipeline's logic does not render again what the
    session's tiny run rendered (anything else it needs is rendered as usual)."""
    import shutil

    def seed(folder):
        for name in RENDERED_CACHES:
            if (tiny_run[0] / name).is_dir():
                shutil.copytree(tiny_run[0] / name, folder / name, dirs_exist_ok=True)
        return folder
    return seed


def pytest_collection_modifyitems(config, items):
    """The tests that read the session's tiny run go first: under pytest-xdist the
    first worker renders it at once while the other runs the rest, and no worker
    waits on it later (the order is otherwise the files' own)."""
    items.sort(key=lambda item: "tiny_run" not in getattr(item, "fixturenames", ()))
