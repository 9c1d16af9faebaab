"""A Dask worker that runs two threads, started in another directory (``dask worker
--nthreads 2``, as the cluster guide starts one, gets a thread per core): each thread
builds and keeps its own diagram and Context, so a sweep and real-loop runs through
``--executor dask://...`` equal the same run in this process. With one diagram per
process, renders on a thread other than the one that built it failed (eglMakeCurrent)
and left nodes with wrong steering, and runs sharing one Context broke each other's
Simulator ('Simulation time has changed since last Initialize()')."""

import os
import shutil
import subprocess
import sys
import time
import warnings

import numpy as np
import pytest

from reachwatch.diagrams import REFERENCE_TAXINET, load_scenario
from reachwatch.pipeline import executors
from reachwatch.pipeline.executors import make_executor
from reachwatch.diagrams.user_code import factory_code_hash
from reachwatch.reach import InlineExecutor
from reachwatch.systems.checks import is_file
from reachwatch.systems.files import local_copy
from reachwatch.taxi import on_runway_starts, paper_grid, sweep_closed_loop
from reachwatch.taxi.fidelity import real_outcomes
from lane_follower import FACTORY

distributed = pytest.importorskip("dask.distributed")

SCENARIO = "environment: {runway: KMWH, hour: 9.0, sky: clear}\n"


@pytest.fixture(scope="module")
def two_thread_worker(tmp_path_factory):
    """``(scheduler address, worker log path)``: a scheduler here and one ``dask worker
    --nthreads 2`` process whose working directory is a folder of its own."""
    root = tmp_path_factory.mktemp("threaded_worker")
    elsewhere = root / "elsewhere"
    elsewhere.mkdir()
    log_path = root / "worker.log"
    with distributed.LocalCluster(n_workers=0, processes=True, host="127.0.0.1",
                                  dashboard_address="127.0.0.1:0") as cluster:
        address = cluster.scheduler_address
        env = dict(os.environ, OMP_NUM_THREADS="1",
                   REACHWATCH_CACHE=str(root / "worker_cache"))
        with open(log_path, "wb") as log:
            worker = subprocess.Popen(
                [sys.executable, "-m", "distributed.cli.dask_worker", address,
                 "--nthreads", "2", "--nworkers", "1", "--no-nanny", "--host", "127.0.0.1",
                 "--no-dashboard", "--memory-limit", "0", "--death-timeout", "60"],
                cwd=elsewhere, env=env, stdout=log, stderr=subprocess.STDOUT)
        try:
            with distributed.Client(address) as client:
                deadline = time.monotonic() + 120
                while not client.nthreads() and worker.poll() is None \
                        and time.monotonic() < deadline:
                    time.sleep(0.2)
                assert list(client.nthreads().values()) == [2], log_path.read_text()[-3000:]
            yield address, log_path
        finally:
            worker.terminate()
            try:
                worker.wait(30)
            except subprocess.TimeoutExpired:
                worker.kill()
                worker.wait(10)


def test_a_two_thread_worker_sweeps_and_runs_the_real_loop_as_this_process_does(
        tmp_path, monkeypatch, two_thread_worker):
    address, log_path = two_thread_worker
    scenario = load_scenario(data=SCENARIO)
    B = scenario.environment.half_width
    grid = paper_grid(B, (3, 3, 3))
    starts = on_runway_starts(grid, 8, 0, half_width=B)
    driver = tmp_path / "driver"
    driver.mkdir()
    monkeypatch.chdir(driver)          # a relative sweep cache: the worker is elsewhere
    inline = sweep_closed_loop(scenario, grid, cache_dir="inline_sweeps",
                               executor=InlineExecutor(), chunk_size=3, progress=False)
    runs = real_outcomes(scenario, starts, grid=grid, duration=0.5, executor=InlineExecutor(),
                         cache_dir=driver / "inline_runs", progress=False)
    executor, close = make_executor("dask://" + address.split("://", 1)[1])
    try:     # 9 chunks of 3 nodes, 4 of 2 runs: both threads take some
        with distributed.Client(address) as watcher, \
                distributed.get_task_stream(watcher) as stream:
            dask = sweep_closed_loop(scenario, grid, cache_dir="dask_sweeps",
                                     executor=executor, chunk_size=3, progress=False)
        threads = {task["thread"] for task in stream.data
                   if str(task["key"]).startswith("run_on_worker")}
        assert len(threads) == 2, f"the sweep's chunks ran on {len(threads)} thread(s)"
        assert dask.computed == inline.computed == grid.size
        assert set(dask.tables) == set(inline.tables)
        for port, table in inline.tables.items():
            wrong = np.any(dask.tables[port] != table, axis=-1)
            assert not wrong.any(), (
                f"{port}: {int(wrong.sum())} of {grid.size} nodes differ, by up to "
                f"{np.max(np.abs(dask.tables[port] - table)):.3g}")
        dask_runs = real_outcomes(scenario, starts, grid=grid, duration=0.5,
                                  executor=executor, cache_dir=driver / "dask_runs",
                                  progress=False)
    finally:
        close()
    assert dask_runs.computed == runs.computed == len(starts)
    assert set(dask_runs.fields) == set(runs.fields)
    for name, values in runs.fields.items():
        assert np.array_equal(dask_runs[name], values, equal_nan=True), name
    assert runs["ticks"].min() > 1             # real runs, not starts already off the runway
    # The old failure (renders on a thread other than the one that built the diagram)
    # logged eglMakeCurrent warnings beside wrong nodes. In about one full-suite run in
    # four the worker logs such a warning (error 12290, EGL_BAD_ACCESS) while every node
    # and run above is identical. The same warning comes when a render window is
    # destroyed on a thread other than the one its context is current on (reproduced
    # with windows kept past their thread's end), so it is likely a diagram that Python's
    # cycle collector freed on another thread; which one was not found. It is reported,
    # with the log around it, and the identity above is what this test asserts.
    lines = log_path.read_text(errors="replace").splitlines()
    egl = [i for i, line in enumerate(lines) if "eglMakeCurrent" in line]
    if egl:
        warnings.warn(f"the worker logged {len(egl)} eglMakeCurrent warning(s), outputs "
                      f"identical:\n" + "\n".join(lines[max(0, egl[0] - 20):egl[0] + 5]))


def test_a_worker_elsewhere_runs_the_relative_files_it_was_sent(tmp_path, monkeypatch,
                                                                two_thread_worker):
    """A controller over two files and a checkpoint, named relative to the driver's
    directory: the worker, started in a directory of its own, has no such paths, and
    runs them from the copies its tasks brought, as this process does."""
    address, _ = two_thread_worker
    driver = tmp_path / "driver"
    (driver / "mine").mkdir(parents=True)
    (driver / "mine" / "follower.py").write_text(FACTORY)
    (driver / "mine" / "lane_vision.py").write_text("OFFSET = 0.05\n")
    shutil.copyfile(REFERENCE_TAXINET, driver / "taxinet.pt")
    monkeypatch.chdir(driver)
    mine = load_scenario(data=SCENARIO + "controller: {factory: 'mine/follower.py:make'}\n")
    taxinet = load_scenario(data=SCENARIO + "controller: {checkpoint: taxinet.pt}\n")
    B = mine.environment.half_width
    grid = paper_grid(B, (3, 3, 3))
    starts = on_runway_starts(grid, 4, 0, half_width=B)
    inline = sweep_closed_loop(mine, grid, cache_dir="inline_sweeps", executor=InlineExecutor(),
                               chunk_size=9, progress=False)
    runs = real_outcomes(taxinet, starts, grid=grid, duration=0.5, executor=InlineExecutor(),
                         cache_dir="inline_runs", progress=False)
    executor, close = make_executor("dask://" + address.split("://", 1)[1])
    try:     # the worker's directory has neither: it answers from the copies it was sent
        code = "mine/follower.py:make"
        assert executor.submit(factory_code_hash, code).result() == factory_code_hash(code)
        assert executor.submit(is_file, "taxinet.pt").result()
        copy = executor.submit(local_copy, "taxinet.pt").result()
        assert "/worker_cache/shipped/" in copy and copy.endswith("/taxinet.pt"), copy
        dask = sweep_closed_loop(mine, grid, cache_dir="dask_sweeps", executor=executor,
                                 chunk_size=9, progress=False)
        dask_runs = real_outcomes(taxinet, starts, grid=grid, duration=0.5, executor=executor,
                                  cache_dir="dask_runs", progress=False)
    finally:
        close()
    assert dask.computed == inline.computed == grid.size
    for port, table in inline.tables.items():
        assert np.array_equal(dask.tables[port], table), port
    assert dask_runs.computed == runs.computed == len(starts)
    for name, values in runs.fields.items():
        assert np.array_equal(dask_runs[name], values, equal_nan=True), name


@pytest.mark.parametrize("name", ["drake", "numpy", "opencv"])
def test_a_worker_with_other_versions_is_refused_in_one_line(monkeypatch, two_thread_worker,
                                                             name):
    """Every version the cache keys carry is checked on the workers: numpy's and
    OpenCV's too (a worker's images and arrays are stored under the driver's key);
    OpenCV's as the ``cv2`` module says, whichever distribution installed it."""
    address, _ = two_thread_worker
    real, modules = executors._version, executors._module_versions_here()
    if name in modules:
        mine = modules[name]
        monkeypatch.setattr(executors, "_module_versions_here",
                            lambda: {**modules, name: "0.0.0"})
    else:
        mine = real(name)
        monkeypatch.setattr(executors, "_version",
                            lambda n: "0.0.0" if n == name else real(n))
    with pytest.raises(ValueError) as error:
        make_executor("dask://" + address.split("://", 1)[1])
    message = str(error.value)
    assert "\n" not in message and f"{name} {mine}" in message and f"{name} 0.0.0" in message
    assert "install the same versions on every worker" in message


def test_a_worker_that_renders_otherwise_is_refused_in_one_line(monkeypatch, two_thread_worker):
    """The worker renders the probe scene to the pixels this process does (one machine);
    told that this process renders otherwise, the driver refuses the worker."""
    address, _ = two_thread_worker
    from reachwatch.diagrams import render_stack as stack_module
    real = stack_module.render_stack()
    close = make_executor("dask://" + address.split("://", 1)[1])[1]
    close()                                       # the same stack: accepted
    monkeypatch.setattr(stack_module, "render_stack",
                        lambda: {**real, "probe": "0" * 32,
                                 "libraries": {"libnvidia-glcore.so.550": "0" * 16}})
    with pytest.raises(ValueError) as error:
        make_executor("dask://" + address.split("://", 1)[1])
    message = str(error.value)
    assert "\n" not in message and "renders with probe " in message
    assert "libnvidia-glcore" in message and "same GL driver" in message


def test_a_task_on_a_worker_unlike_the_driver_is_refused_in_one_line(two_thread_worker):
    """A worker that joins after the driver's check is refused at its first task: every
    task compares its worker's versions and render stack with the driver's."""
    address, _ = two_thread_worker
    executor, close = make_executor("dask://" + address.split("://", 1)[1])
    try:
        assert executor.submit(is_file, "no such file").result() is False
        executor._expected = {**executor._expected,         # as if it joined late
                              "render": {**executor._expected["render"], "probe": "0" * 32}}
        with pytest.raises(RuntimeError) as error:
            executor.submit(is_file, "no such file").result()
    finally:
        close()
    message = str(error.value)
    assert "\n" not in message and "joined with another install" in message
    assert "probe 000000000000" in message
    # another reachwatch source under the same version: refused the same way
    executor, close = make_executor("dask://" + address.split("://", 1)[1])
    try:
        executor._expected = {**executor._expected, "code": "f" * 64}
        with pytest.raises(RuntimeError) as error:
            executor.submit(is_file, "no such file").result()
    finally:
        close()
    assert "reachwatch source ffffffffffff" in str(error.value)


def test_a_scheduler_that_queues_chunks_on_busy_threads_is_named_in_one_warning(
        caplog, two_thread_worker):
    """The fixture's scheduler has Dask's default worker-saturation (1.1 unless the
    environment sets it): connecting says so in one line with the setting that fixes
    it; the results do not depend on it, so it is a warning, not a refusal."""
    address, _ = two_thread_worker
    with distributed.Client(address) as client:
        saturation = executors.scheduler_saturation(client)
    assert saturation == float(os.environ.get(executors.SATURATION_VARIABLE, 1.1))
    with caplog.at_level("WARNING", logger="reachwatch"):
        make_executor("dask://" + address.split("://", 1)[1])[1]()
    lines = [r.getMessage() for r in caplog.records if "worker-saturation" in r.getMessage()]
    if saturation > executors.SATURATION:
        assert len(lines) == 1 and "\n" not in lines[0], lines
        assert f"{executors.SATURATION_VARIABLE}=1" in lines[0]
    else:
        assert lines == []
