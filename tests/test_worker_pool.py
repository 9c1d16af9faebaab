"""The default worker pool: one spawned worker per usable core, each with its share of
the cores' threads; tables and dataset images do not depend on the number of workers;
small batches of rollouts still split into chunks that the workers share."""

import functools
import os

import numpy as np
import pytest

from reachwatch.pipeline.executors import make_executor
from reachwatch.reach import InlineExecutor, default_executor, stop_executor, sweep
from reachwatch.reach.outcomes import default_chunk_size, run_outcomes
from reachwatch.reach.sweep import WORKER_MEMORY, default_worker_count, usable_cores
from reachwatch.taxi import paper_grid

from test_faults import FEEDBACK, _feedback_factory
from test_outcomes import drift_rollout
from tiny_run import taxi_application


def _worker_threads(_):
    import torch
    return os.getpid(), os.environ.get("OMP_NUM_THREADS"), torch.get_num_threads()


@pytest.fixture(scope="module")
def pool():
    """Two spawned workers, shared by the tests that need them (each imports Drake and
    torch when it starts: seconds)."""
    pool = default_executor(2)
    yield pool
    stop_executor(pool)


def test_two_workers_sweep_the_same_table_and_split_the_threads(tmp_path, pool):
    g = paper_grid(10.0, (4, 3, 3))
    inline = sweep(_feedback_factory(), g, key="inline", cache_dir=tmp_path, probe=FEEDBACK,
                   executor=InlineExecutor(), progress=False)
    counted = pool.progress_counter.value
    table = sweep(_feedback_factory(), g, key="pool", cache_dir=tmp_path, probe=FEEDBACK,
                  executor=pool, chunk_size=5, progress=False)
    assert pool.progress_counter.value - counted == g.size
    threads = [pool.submit(_worker_threads, i).result() for i in range(4)]
    for port in FEEDBACK.ports:
        np.testing.assert_array_equal(table[port], inline[port])
    share = max(1, usable_cores() // 2)
    assert {t[1:] for t in threads} == {(str(share), share)}
    assert all(pid != os.getpid() for pid, _, _ in threads)


def test_a_dataset_rendered_by_workers_has_the_pixels_of_one_rendered_here(tmp_path, pool):
    """Image chunks are tasks (`dataset_images.render_chunk`) whose arrays come back to
    the driver, which writes them: spawned workers render and estimate the same numbers,
    and the folder is the same, manifest and all."""
    from reachwatch.diagrams import load_scenario
    from reachwatch.reach import solve_brt
    from reachwatch.taxi import TaxiDynamics
    from reachwatch.training.dataset import DatasetSpec, build_dataset, load_dataset
    grid = paper_grid(10.0, (5, 3, 5))
    px, _, th = grid.mesh()
    brt = solve_brt(grid, TaxiDynamics(half_width=10.0),
                    np.deg2rad(-0.74 * px - 0.44 * np.rad2deg(th) + 8.0), horizon=2.0,
                    device="cpu")
    scenario, spec = load_scenario(data=""), DatasetSpec(samples=10, seed=5, height=24,
                                                          width=40, chunk_size=4)
    here = load_dataset(build_dataset(tmp_path / "here", scenario, brt, spec, progress=False, application=taxi_application()))
    there = load_dataset(build_dataset(tmp_path / "there", scenario, brt, spec,
                                       progress=False, executor=pool, application=taxi_application()), verify=True)
    assert here.folder.name == there.folder.name and here.manifest == there.manifest
    assert here.manifest["chunks_done"] == [0, 4, 8]
    for name in ("images", "estimates", "ensemble", "states", "labels"):
        np.testing.assert_array_equal(getattr(here, name), getattr(there, name))
    assert here.images.any() and here.estimates.shape == (10, 2)


@pytest.mark.parametrize("workers", [0, -1, 1.5, True])
def test_bad_worker_count_is_named(workers):
    with pytest.raises(ValueError, match="max_workers must be a whole number >= 1"):
        default_executor(workers)


def test_local_executor_spec_names_its_worker_count():
    executor, close = make_executor("local:2")
    try:
        assert len({executor.submit(_worker_threads, i).result()[0] for i in range(6)}) <= 2
        assert executor.submit(_worker_threads, 0).result()[1] == str(max(1, usable_cores() // 2))
    finally:
        close()
    for bad in ("local:0", "local:two", "local:-1"):
        with pytest.raises(ValueError, match="local:N needs a whole number of workers"):
            make_executor(bad)


def test_default_worker_count_is_capped_by_memory(monkeypatch):
    monkeypatch.delenv("REACHWATCH_WORKERS", raising=False)
    sweep_module = __import__("sys").modules["reachwatch.reach.sweep"]
    monkeypatch.setattr(sweep_module, "usable_cores", lambda: 16)
    pages = {"SC_PAGE_SIZE": 4096, "SC_PHYS_PAGES": 5 * WORKER_MEMORY // 4096}
    monkeypatch.setattr(sweep_module.os, "sysconf", lambda name: pages[name])
    assert default_worker_count() == 5
    pages["SC_PHYS_PAGES"] = 100 * WORKER_MEMORY // 4096
    assert default_worker_count() == 16
    pages["SC_PHYS_PAGES"] = 1
    assert default_worker_count() == 1
    monkeypatch.setenv("REACHWATCH_WORKERS", "3")                # the user's word wins
    assert default_worker_count() == 3
    for bad in ("0", "two", "-1"):
        monkeypatch.setenv("REACHWATCH_WORKERS", bad)
        with pytest.raises(ValueError, match="REACHWATCH_WORKERS must be a whole number >= 1"):
            default_worker_count()


@pytest.mark.parametrize("count, size", [(1, 1), (3, 1), (6, 2), (8, 2), (20, 5), (28, 7),
                                         (29, 8), (32, 8), (200, 8)])
def test_default_chunk_size(count, size):
    assert default_chunk_size(count) == size


def test_a_small_batch_makes_four_chunks(tmp_path):
    """Eight starts run as 4 chunks of 2 (a pool shares them); 200 as 25 of 8, as before."""
    rollout = functools.partial(drift_rollout, 0.5)
    for count, chunks in ((8, 4), (200, 25)):
        starts = np.column_stack([np.linspace(-0.9, 0.9, count), np.zeros(count)])
        out = run_outcomes(rollout, starts, cache_dir=tmp_path, progress=False)
        assert len(list((tmp_path / out.key).glob("chunk_*.npz"))) == chunks
        np.testing.assert_array_equal(out.failed, np.abs(starts[:, 0] + 0.5) >= 1.0)


_DRIVER = """
import time
from reachwatch.reach.sweep import default_executor
pool = default_executor(2)
for _ in range(2):                      # each submit to a busy pool spawns one worker
    pool.submit(time.sleep, 0)
print(" ".join(str(pid) for pid in pool._processes), flush=True)
time.sleep(120)
"""


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rpartition(")")[2].split()[0] != "Z"      # a zombie is gone
    except FileNotFoundError:
        return False


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="reads /proc")
def test_workers_exit_soon_after_the_driver_is_killed_even_while_importing():
    """SIGKILL the driver while its two fresh workers still import Drake and torch
    (seconds, ~1 GB each): both are gone within 1.5 s (they poll every 0.1 s)."""
    import signal
    import subprocess
    import sys
    import time
    driver = subprocess.Popen([sys.executable, "-c", _DRIVER], stdout=subprocess.PIPE, text=True)
    try:
        pids = [int(pid) for pid in driver.stdout.readline().split()]
    finally:
        driver.kill()
        driver.wait()
    assert len(pids) == 2 and all(_alive(pid) for pid in pids)     # still starting
    deadline = time.monotonic() + 1.5
    while any(_alive(pid) for pid in pids) and time.monotonic() < deadline:
        time.sleep(0.05)
    left = [pid for pid in pids if _alive(pid)]
    for pid in left:                    # leave nothing behind, even when failing
        os.kill(pid, signal.SIGKILL)
    assert not left, f"workers {left} outlived their killed driver by 1.5 s"
