"""The one chunked runner (`reach.chunks.run_chunks`) behind sweeps, rollout batches and
dataset images: finished chunks are kept when a later one fails and a re-run runs only
the rest; a chunk file whose numbers changed is run again; a pool whose worker died is
started again and the chunks lost with it run again, a fixed number of times, then a
dead pool is one line naming the caller, and an executor the runner made is stopped at
once."""

import concurrent.futures as cf
import functools
import logging
import multiprocessing
import os
import signal
import traceback
from pathlib import Path

import numpy as np
import pytest

from reachwatch.reach.chunk_files import (FolderStore, chunk_path, read_chunk_file, split,
                                          store_chunk_file)
from reachwatch.reach.chunks import row_done, run_chunks
from reachwatch.reach.executors import RESPAWNS, InlineExecutor, RespawningPool, stop_executor
from reachwatch.reach.sweep import default_executor


def _squares(start, stop, fail_at=None):
    if start == fail_at:
        raise RuntimeError(f"chunk at {start} failed")
    rows = np.arange(start, stop)
    for _ in rows:
        row_done()
    return {"x": rows, "y": rows ** 2}


def _run(folder, calls, fail_at=None, **kw):
    def args(chunk):
        calls.append(chunk.index)
        return chunk.start, chunk.stop, fail_at
    store = FolderStore(folder, keep=True)
    ran = run_chunks(_squares, split(10, 3), store, args=args, **kw)
    return ran, store


def test_a_failed_chunk_keeps_those_before_it_and_a_rerun_runs_the_rest(tmp_path):
    calls = []
    with pytest.raises(RuntimeError, match="chunk at 6 failed"):
        _run(tmp_path, calls, fail_at=6)
    assert calls == [0, 1, 2] and sorted(p.name for p in tmp_path.iterdir()) == [
        "chunk_000000.npz", "chunk_000001.npz"]
    calls.clear()
    ran, store = _run(tmp_path, calls)
    assert calls == [2, 3] and [c.index for c in ran] == [2, 3]
    y = np.concatenate([store.read(c)["y"] for c in split(10, 3)])
    np.testing.assert_array_equal(y, np.arange(10) ** 2)
    calls.clear()
    assert _run(tmp_path, calls)[0] == [] and calls == []          # all stored: nothing runs


def test_a_window_that_is_not_a_whole_number_of_chunks_is_one_line(tmp_path):
    """-1 waited for ever and 0 was read as "the default"; neither runs a chunk now."""
    for bad in (-1, 0, 2.5, True):
        calls = []
        with pytest.raises(ValueError, match=r"^run_chunks: max_in_flight must be a whole "
                                             r"number >= 1 .*, got " + repr(bad).replace(".", r"\.")):
            _run(tmp_path, calls, max_in_flight=bad)
        assert calls == [] and not any(tmp_path.iterdir())


def test_a_chunk_file_whose_numbers_changed_is_run_again(tmp_path):
    _run(tmp_path, [])
    path = chunk_path(tmp_path, 1)
    with np.load(path) as data:
        edited = {k: data[k] for k in data.files}
    edited["y"] = edited["y"] + 1                    # same shape, its old checksum kept
    np.savez(path, **edited)
    chunk_path(tmp_path, 3).write_bytes(b"torn")     # and a torn write
    calls = []
    ran, store = _run(tmp_path, calls)
    assert calls == [1, 3]
    np.testing.assert_array_equal(store.read(split(10, 3)[1])["y"], [9, 16, 25])
    store_chunk_file(path, {"x": np.arange(3)})      # a chunk that does not fit its rows
    fits = lambda chunk, arrays: len(arrays["x"]) == chunk.rows and "y" in arrays  # noqa: E731
    assert not FolderStore(tmp_path, fits).valid(split(10, 3)[1])
    assert FolderStore(tmp_path, fits).valid(split(10, 3)[0])


def test_the_bar_moves_per_row_inline_and_per_chunk_otherwise(tmp_path):
    class Bar:
        def __init__(self, initial=0):
            self.n, self.updates = initial, []

        def update(self, k):
            self.n += k
            self.updates.append(k)

        def close(self):
            pass
    bars = []

    def bar(**kw):
        bars.append(Bar(**kw))
        return bars[-1]
    store = FolderStore(tmp_path / "a")
    run_chunks(_squares, split(10, 3), store, args=lambda c: (c.start, c.stop),
               executor=InlineExecutor(), bar=bar, per_row=True)
    assert bars[-1].updates == [1] * 10
    (tmp_path / "a" / "chunk_000002.npz").unlink()
    run_chunks(_squares, split(10, 3), store, args=lambda c: (c.start, c.stop),
               executor=InlineExecutor(), bar=bar)
    assert (bars[-1].n, bars[-1].updates) == (10, [3])     # began at 7 stored rows


class _DeadPool(cf.Executor):
    """A pool whose workers died: every future fails as a broken process pool does."""

    def __init__(self):
        self.stopped = []

    def submit(self, fn, /, *args, **kwargs):
        future = cf.Future()
        future.set_exception(cf.process.BrokenProcessPool("a child process terminated"))
        return future

    def shutdown(self, wait=True, *, cancel_futures=False):
        self.stopped.append(cancel_futures)


def test_a_dead_pool_is_one_line_and_an_owned_executor_is_stopped_at_once(tmp_path):
    made = []

    def default():
        made.append(_DeadPool())
        return made[-1]
    with pytest.raises(RuntimeError, match=r"^a my_job worker process died \(killed, out of "
                                           r"memory, or a crash in native code\); finished "
                                           r"chunks are kept and a re-run resumes\. .*__main__"):
        run_chunks(_squares, split(10, 3), FolderStore(tmp_path),
                   args=lambda c: (c.start, c.stop), default=default, caller="my_job")
    assert len(made) == 1 and made[0].stopped == [True]          # cancelled, once
    given = _DeadPool()
    with pytest.raises(RuntimeError, match="a my_job worker process died"):
        run_chunks(_squares, split(10, 3), FolderStore(tmp_path),
                   args=lambda c: (c.start, c.stop), executor=given, caller="my_job")
    assert given.stopped == []                         # the caller's executor is left alone
    made.clear()
    store = FolderStore(tmp_path / "done")
    run_chunks(_squares, split(10, 3), store, args=lambda c: (c.start, c.stop))
    run_chunks(_squares, split(10, 3), store, args=lambda c: (c.start, c.stop), default=default)
    assert made == []                                  # nothing to run: no executor made


def _slow_squares(start, stop, fail_at=None, ran=None):
    import time
    ran.append(start)
    if start:                                # the first chunk is done at once
        time.sleep(0.3)
    if start == fail_at:
        raise RuntimeError(f"chunk at {start} failed")
    return {"x": np.arange(start, stop)}


def test_after_a_failed_chunk_the_finished_ones_are_stored_and_the_rest_cancelled(tmp_path):
    """A caller's executor: the chunks that finished are stored, the chunks still
    waiting in its queue never run (before, all 40 ran after the failure)."""
    ran = []
    store = FolderStore(tmp_path)
    with cf.ThreadPoolExecutor(2) as pool, pytest.raises(RuntimeError, match="at 1 failed"):
        run_chunks(_slow_squares, split(40, 1), store, executor=pool, max_in_flight=40,
                   args=lambda c: (c.start, c.stop, 1, ran))
    stored = {int(p.stem.split("_")[1]) for p in tmp_path.iterdir()}
    assert 0 in stored and stored <= set(ran) - {1} and len(ran) < 20   # about 5


def _dies(folder, start, stop, always=False):
    """`_squares`; the chunk at 3 kills its worker (once, or ``always``)."""
    marker = Path(folder) / "died"
    if start == 3 and (always or not marker.exists()):
        marker.touch()
        os.kill(os.getpid(), signal.SIGKILL)
    return _squares(start, stop)


def test_a_worker_that_died_is_replaced_and_the_chunks_lost_with_it_run_again(tmp_path, caplog):
    """Before: a worker's death broke the pool, and the whole run stopped on it."""
    pool = default_executor(2)
    try:
        with caplog.at_level(logging.WARNING, logger="reachwatch.reach.chunks"):
            run_chunks(functools.partial(_dies, str(tmp_path)), split(10, 3),
                       FolderStore(tmp_path / "out"), args=lambda c: (c.start, c.stop),
                       executor=pool, caller="my_job")
        assert (pool.generation, pool.respawns_left) == (1, RESPAWNS - 1)
        assert (tmp_path / "died").exists()                       # it did die, once
        for chunk in split(10, 3):
            got = read_chunk_file(chunk_path(tmp_path / "out", chunk.index))
            np.testing.assert_array_equal(got["y"], np.arange(chunk.start, chunk.stop) ** 2)
        assert "my_job: a worker process died" in caplog.text and "not stored yet run on it" in caplog.text
        assert pool.submit(abs, -2).result() == 2                 # the pool works on
    finally:
        pool.shutdown()


def _dies_holding_the_count(folder, start, stop):
    """`_squares`; the chunk at 3 takes its pool's row counter's lock and kills its
    worker (once), as a worker killed while counting a row would."""
    from reachwatch.reach import chunks
    marker = Path(folder) / "died"
    if start == 3 and not marker.exists():
        marker.touch()
        chunks._ON_ROW.args[0].get_lock().acquire()
        os.kill(os.getpid(), signal.SIGKILL)
    return _squares(start, stop)


HOLDING_THE_COUNT = """
import sys
sys.path.insert(0, {tests!r})
import functools
from pathlib import Path
from reachwatch.reach.chunk_files import FolderStore, split
from reachwatch.reach.chunks import run_chunks
from reachwatch.reach.sweep import default_executor
from test_chunks import _dies_holding_the_count
pool = default_executor(1)
folder = Path({folder!r})
try:
    run_chunks(functools.partial(_dies_holding_the_count, str(folder)), split(12, 3),
               FolderStore(folder / "out"), args=lambda c: (c.start, c.stop),
               executor=pool, per_row=True, bar=functools.partial(_Bar), caller="my_job")
finally:
    pool.shutdown()
print("done", pool.generation, pool.progress_counter.value)
"""


class _Bar:
    """A bar that only counts."""

    def __init__(self, initial=0, **kwargs):
        self.n = initial

    def update(self, n):
        self.n += n

    def close(self):
        pass


def test_a_worker_killed_holding_the_row_counts_lock_does_not_stop_the_pool(tmp_path):
    """Before: the fresh pool's workers counted into the dead one's counter, whose lock
    the dead worker held for good, and the workers and the driver's bar waited on it
    for ever. Each pool now counts into a counter of its own, and the driver reads it
    without its lock. (In a process of its own, so that a regression fails in two
    minutes rather than hanging the suite.)"""
    import subprocess
    import sys
    code = HOLDING_THE_COUNT.format(tests=str(Path(__file__).parent), folder=str(tmp_path))
    code = code.replace("functools.partial(_Bar)", "functools.partial(__import__("
                        "'test_chunks')._Bar)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    generation, counted = done.stdout.split()[1:]
    assert generation == "1" and 0 < int(counted) <= 12
    for chunk in split(12, 3):
        got = read_chunk_file(chunk_path(tmp_path / "out", chunk.index))
        np.testing.assert_array_equal(got["y"], np.arange(chunk.start, chunk.stop) ** 2)


def test_a_worker_that_dies_every_time_ends_in_the_one_line_error(tmp_path):
    spawn = multiprocessing.get_context("spawn")
    pool = RespawningPool(functools.partial(cf.ProcessPoolExecutor, 1, mp_context=spawn),
                          respawns=1)
    try:
        with pytest.raises(RuntimeError, match=r"^a my_job worker process died \(killed"):
            run_chunks(functools.partial(_dies, str(tmp_path), always=True), split(10, 3),
                       FolderStore(tmp_path / "out"), args=lambda c: (c.start, c.stop),
                       executor=pool, caller="my_job")
        assert (pool.generation, pool.respawns_left) == (1, 0)
    finally:
        pool.shutdown()


def test_callers_that_saw_one_pool_break_replace_it_once():
    made = []

    def make():
        made.append(_DeadPool())
        return made[-1]
    pool = RespawningPool(make, respawns=2)
    assert pool.respawn(0) and pool.respawn(0) and len(made) == 2   # the second: no-op
    assert made[0].stopped == [True] and pool.generation == 1
    assert pool.respawn(1) and not pool.respawn(2) and len(made) == 3   # none left
    stopped = RespawningPool(make, respawns=2)
    stop_executor(stopped, abort=True)              # Ctrl-C: its workers' deaths are not
    assert not stopped.respawn(0) and len(made) == 4 and made[-1].stopped == [True]


class _GrowingCluster(cf.Executor):
    """Runs up to 32 tasks at once, but says it has ``threads`` (as a Dask cluster
    says how many threads its workers have now); counts the most tasks running at once
    before and after it grew."""

    def __init__(self):
        import threading
        self._pool, self._lock = cf.ThreadPoolExecutor(32), threading.Lock()
        self._max_workers, self.running, self.most = 1, 0, {False: 0, True: 0}

    def submit(self, fn, /, *args, **kwargs):
        def counted():
            with self._lock:
                self.running += 1
                grown = self._max_workers > 1
                self.most[grown] = max(self.most[grown], self.running)
            try:
                return fn(*args, **kwargs)
            finally:
                with self._lock:
                    self.running -= 1
        return self._pool.submit(counted)

    def shutdown(self, wait=True, **kwargs):
        self._pool.shutdown(wait=wait)


def _sleepy(start, stop, cluster=None, grow_at=None):
    import time
    if start == grow_at:
        cluster._max_workers = 8                   # workers joined: 8 threads now
    time.sleep(0.05)
    return {"x": np.arange(start, stop)}


def test_the_window_widens_as_the_cluster_grows(tmp_path, monkeypatch):
    """Chunks in flight follow the executor's threads as they are now, not as they were
    when the call began: a cluster that grows mid-run gets more at once."""
    from reachwatch.reach import executors
    monkeypatch.setattr(executors, "WINDOW_REFRESH", 0.0)
    cluster = _GrowingCluster()
    try:
        run_chunks(_sleepy, split(80, 1), FolderStore(tmp_path), executor=cluster,
                   args=lambda c: (c.start, c.stop, cluster, 12))
    finally:
        cluster.shutdown()
    assert cluster.most[False] <= 4              # 1 thread: the least window, 4
    assert cluster.most[True] > 8, cluster.most   # 8 threads: twice as many in flight


def test_a_pool_task_runs_only_on_a_worker_with_the_drivers_loop_code(tmp_path):
    """Each task of a pool given the driver's loop-code digest checks its worker's
    first: one whose source was edited after the driver started stores nothing."""
    from reachwatch.reach.fingerprint import loop_code_digest
    same = RespawningPool(functools.partial(cf.ThreadPoolExecutor, 1), code=loop_code_digest())
    other = RespawningPool(functools.partial(cf.ThreadPoolExecutor, 1), code="0" * 64)
    try:
        ran, store = _run(tmp_path / "same", [], executor=same)
        assert len(ran) == 4
        with pytest.raises(RuntimeError, match=r"^this worker's reachwatch source \(loop code "
                                               r"\w{12}\) is not the driver's \(000000000000\)"):
            _run(tmp_path / "other", [], executor=other)
        assert not list((tmp_path / "other").glob("chunk_*"))
    finally:
        stop_executor(same)
        stop_executor(other)


class KilledWorker(Exception):
    """Named as Dask's: its workers kept dying on the task."""


def _lost_on_the_cluster(start, stop):
    if start == 3:
        raise KilledWorker(f"task at {start}: its workers died 3 times")
    return _squares(start, stop)


def test_a_task_the_cluster_lost_is_one_worker_lost_line_and_the_rest_is_kept(tmp_path):
    from reachwatch.reach.executors import WorkerLost
    store = FolderStore(tmp_path, keep=True)
    with cf.ThreadPoolExecutor(1) as pool, pytest.raises(
            WorkerLost, match=r"^the cluster lost my_job chunk 1 \(KilledWorker: task at 3: its "
                              r"workers died 3 times\); finished chunks are kept"):
        run_chunks(_lost_on_the_cluster, split(10, 3), store, executor=pool,
                   args=lambda chunk: (chunk.start, chunk.stop), caller="my_job")
    assert store.valid(split(10, 3)[0])


class CommClosedError(OSError):
    """Named as Dask's: the connection to the scheduler closed."""


class ClosingCluster(cf.ThreadPoolExecutor):
    """A cluster's executor whose connection closes before the chunk at row 6 is
    submitted, once the chunks before it have finished: ``submit`` itself raises."""

    def __init__(self, workers):
        super().__init__(workers)
        self.futures = []

    def submit(self, fn, /, *args, **kwargs):
        if args[0] == 6:
            cf.wait(self.futures)
            raise CommClosedError("in <TCP (closed)>: Stream is closed")
        self.futures.append(super().submit(fn, *args, **kwargs))
        return self.futures[-1]


def test_a_cluster_gone_while_submitting_is_one_worker_lost_line(tmp_path):
    from reachwatch.reach.executors import WorkerLost
    store = FolderStore(tmp_path, keep=True)
    with ClosingCluster(1) as cluster, pytest.raises(
            WorkerLost, match=r"^the cluster lost my_job chunk 2 \(CommClosedError: in <TCP "
                              r"\(closed\)>: Stream is closed\); finished chunks are kept"):
        run_chunks(_squares, split(10, 3), store, executor=cluster,
                   args=lambda chunk: (chunk.start, chunk.stop), caller="my_job")
    assert store.valid(split(10, 3)[0])


class CancellingCluster(cf.ThreadPoolExecutor):
    """A cluster's executor that cancels the task of each chunk starting at a row of
    ``lost``, ``times`` times, as Dask's does when it lost the worker holding the task's
    input (`distributed.cfexecutor`: the future it returns is cancelled)."""

    def __init__(self, lost, times):
        super().__init__(1)
        self.left = {start: times for start in lost}
        self.calls = []

    def submit(self, fn, /, *args, **kwargs):
        self.calls.append(args[0])
        if self.left.get(args[0], 0) > 0:
            self.left[args[0]] -= 1
            future = cf.Future()
            future.cancel()
            future.set_running_or_notify_cancel()
            return future
        return super().submit(fn, *args, **kwargs)


def test_a_chunk_the_cluster_cancelled_is_submitted_again_and_said(tmp_path, caplog):
    store = FolderStore(tmp_path, keep=True)
    chunks = split(10, 3)
    with CancellingCluster(lost=[3, 6], times=2) as cluster, \
            caplog.at_level("WARNING", logger="reachwatch"):
        ran = run_chunks(_squares, chunks, store, executor=cluster,
                         args=lambda chunk: (chunk.start, chunk.stop), caller="my_job")
    assert len(ran) == 4 and all(store.valid(c) for c in chunks)
    assert sorted(cluster.calls) == [0, 3, 3, 3, 6, 6, 6, 9]
    assert caplog.text.count("my_job: the cluster cancelled chunk 1 (it lost the worker") == 2
    for chunk in chunks:
        assert store.read(chunk)["y"].tolist() == [i * i for i in range(chunk.start, chunk.stop)]


def test_chunks_cancelled_with_the_scheduler_gone_are_not_submitted_again(tmp_path):
    """A client that lost its scheduler cancels every task: one WorkerLost line, not a
    resubmission to a client that is reconnecting or closed."""
    from types import SimpleNamespace
    from reachwatch.reach.executors import WorkerLost
    store = FolderStore(tmp_path, keep=True)
    with CancellingCluster(lost=[3], times=1) as cluster, pytest.raises(
            WorkerLost, match=r"^the cluster lost my_job chunk 1 \(CancelledError"):
        cluster._client = SimpleNamespace(status="connecting")
        run_chunks(_squares, split(10, 3), store, executor=cluster,
                   args=lambda chunk: (chunk.start, chunk.stop), caller="my_job")
    assert cluster.calls.count(3) == 1


def test_a_chunk_cancelled_past_its_retries_is_one_worker_lost_line(tmp_path):
    from reachwatch.reach.chunks import CANCELLED_RETRIES
    from reachwatch.reach.executors import WorkerLost
    store = FolderStore(tmp_path, keep=True)
    with CancellingCluster(lost=[3], times=CANCELLED_RETRIES + 1) as cluster, pytest.raises(
            WorkerLost, match=r"^the cluster lost my_job chunk 1 \(CancelledError"):
        run_chunks(_squares, split(10, 3), store, executor=cluster,
                   args=lambda chunk: (chunk.start, chunk.stop), caller="my_job")
    assert cluster.calls.count(3) == CANCELLED_RETRIES + 1
    assert store.valid(split(10, 3)[0])


class RecordingExecutor(cf.Executor):
    """Runs tasks three at a time, when the third is submitted (so that several finish
    together), and records how it was shut down."""
    shutdowns = []

    def __init__(self):
        self.waiting = []

    def submit(self, fn, /, *args, **kwargs):
        future = cf.Future()
        self.waiting.append((future, fn, args))
        if len(self.waiting) == 3:
            for waiting, fn, args in self.waiting:
                waiting.set_result(fn(*args))
            self.waiting.clear()
        return future

    def shutdown(self, wait=True, *, cancel_futures=False):
        RecordingExecutor.shutdowns.append(cancel_futures)


class FullDisk(FolderStore):
    def store(self, chunk, arrays):
        raise OSError(28, "No space left on device")


def test_a_chunk_that_cannot_be_stored_stops_the_pool_at_once(tmp_path):
    RecordingExecutor.shutdowns.clear()
    with pytest.raises(OSError, match="No space left on device"):
        run_chunks(_squares, split(10, 2), FullDisk(tmp_path), default=RecordingExecutor,
                   max_in_flight=4, args=lambda chunk: (chunk.start, chunk.stop))
    assert RecordingExecutor.shutdowns == [True]     # queued work cancelled, not waited for


def test_the_command_line_says_a_lost_worker_in_one_line(monkeypatch, capsys, tmp_path):
    from reachwatch.pipeline import cli, reach_commands
    from reachwatch.reach.executors import WorkerLost

    def lost(args):
        raise WorkerLost("a sweep worker process died (killed, out of memory, or a crash in "
                         "native code); finished chunks are kept and a re-run resumes")
    monkeypatch.setattr(reach_commands, "sweep_command", lost)
    assert cli.main(["sweep", "--out", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert err.strip().splitlines() == ["reachwatch sweep: error: a sweep worker process died "
                                        "(killed, out of memory, or a crash in native code); "
                                        "finished chunks are kept and a re-run resumes; -v "
                                        "shows the traceback"]


def _one_slow_chunk(start, stop):
    import time
    time.sleep(0.6 if start == 3 else 0.0)
    return _squares(start, stop)


def test_a_chunk_in_flight_too_long_is_warned_of_once(tmp_path, monkeypatch, caplog):
    from reachwatch.reach import chunks
    monkeypatch.setattr(chunks, "STALL_WARNING_S", 0.3)
    store = FolderStore(tmp_path, keep=True)
    with cf.ThreadPoolExecutor(2) as pool, caplog.at_level("WARNING"):
        run_chunks(_one_slow_chunk, split(10, 3), store, executor=pool,
                   args=lambda chunk: (chunk.start, chunk.stop), caller="my_job")
    said = [r.getMessage() for r in caplog.records if "in flight for" in r.getMessage()]
    assert len(said) == 1 and said[0].startswith("my_job: chunk 1 has been in flight for")
    assert all(store.valid(c) for c in split(10, 3))


def test_a_store_that_keeps_rows_takes_no_chunk_file_silent_on_its_rows(tmp_path):
    """A `FolderStore` made with ``rows`` (a job whose key does not hold its chunk size)
    runs again a chunk whose file does not say which rows it holds (written without
    them), rather than read it into rows of the same count it may not be."""
    from reachwatch.reach.chunk_files import Chunk
    chunk = Chunk(index=2, start=4, stop=6)
    FolderStore(tmp_path).store(chunk, {"x": np.array([8.0, 9.0])})    # rows unsaid
    assert FolderStore(tmp_path).read(chunk) is not None
    assert FolderStore(tmp_path, rows=True).read(chunk) is None
    FolderStore(tmp_path, rows=True).store(chunk, {"x": np.array([4.0, 5.0])})
    np.testing.assert_array_equal(FolderStore(tmp_path, rows=True).read(chunk)["x"], [4, 5])
    assert FolderStore(tmp_path, rows=True).read(Chunk(index=2, start=8, stop=10)) is None


class DarkFrame(ValueError):
    """A user's exception whose __init__ takes other arguments than it passes on: it
    pickles, and fails to unpickle in the driver."""

    def __init__(self, tick, why):
        super().__init__(f"tick {tick}: {why}")


def _raises_dark_frame(start, stop):
    raise DarkFrame(7, "too dark")


def test_a_users_exception_the_driver_cannot_unpickle_is_its_message_not_a_dead_worker(
        tmp_path):
    """Before: the pool read as broken, the chunk ran 4 times (every respawn spent) and
    the error said a worker died; the user's message was lost."""
    from reachwatch.reach.fingerprint import loop_code_digest
    spawn = multiprocessing.get_context("spawn")
    pool = RespawningPool(functools.partial(cf.ProcessPoolExecutor, 1, mp_context=spawn),
                          respawns=2, code=loop_code_digest())
    try:
        with pytest.raises(ValueError, match=r"^DarkFrame: tick 7: too dark$") as info:
            run_chunks(_raises_dark_frame, split(4, 2), FolderStore(tmp_path / "out"),
                       args=lambda c: (c.start, c.stop), executor=pool, caller="my_job")
        assert pool.respawns_left == 2                         # no worker was thought dead
        assert "_raises_dark_frame" in str(info.value.__cause__)   # the worker's frames
    finally:
        pool.shutdown()


def test_an_error_the_driver_can_read_back_is_kept_and_another_made_portable():
    """(A class the driver cannot import by name is made portable in any process; one
    whose __init__ takes other arguments only where no exception pickler is installed:
    Dask's tblib reads it back, and the spawned pool above checks that case.)"""
    from reachwatch.reach.executors import portable_error, run_portably
    kept = KeyError("x")
    assert portable_error(kept) is kept

    class Local(LookupError):                 # its name leads nowhere: <locals>
        pass
    made = portable_error(Local("too dark"))
    assert type(made) is LookupError and str(made) == "Local: too dark"

    class Decoding(UnicodeDecodeError):       # a built-in base of five arguments
        pass
    made = portable_error(Decoding("utf-8", b"\xff", 0, 1, "bad"))
    assert type(made) is UnicodeError and str(made).startswith("Decoding: ")

    def calc():
        raise Local("too dark")
    with pytest.raises(LookupError) as info:
        run_portably(calc)
    # the user's frame stays in the traceback of what the driver gets
    assert any(frame.name == "calc" for frame in traceback.extract_tb(info.value.__traceback__))


def test_a_cluster_with_no_workers_is_said_and_its_chunks_run_once_one_joins(tmp_path, caplog,
                                                                              monkeypatch):
    """Before: chunks on a cluster whose workers had all gone waited for ever without a
    word (Dask waits for a worker to join), and the 30-minute warning then blamed a stuck
    worker. Waiting stays (clusters grow), but it is said, and the run goes on when a
    worker joins."""
    import threading
    import time
    distributed = pytest.importorskip("dask.distributed")
    from reachwatch.reach import chunks
    monkeypatch.setattr(chunks, "NO_WORKERS_CHECK_S", 0.2)
    with distributed.LocalCluster(n_workers=0, processes=False,
                                  dashboard_address=None) as cluster, \
            distributed.Client(cluster) as client, \
            caplog.at_level(logging.WARNING, logger="reachwatch.reach.chunks"):
        done = []
        runner = threading.Thread(target=lambda: done.append(run_chunks(
            _squares, split(6, 3), FolderStore(tmp_path / "out"),
            args=lambda c: (c.start, c.stop), executor=client.get_executor(),
            caller="my_job")))
        runner.start()
        deadline = time.monotonic() + 30
        while "no workers now" not in caplog.text and time.monotonic() < deadline:
            time.sleep(0.1)
        assert ("my_job: the cluster has no workers now; 2 chunk(s) in flight wait for one "
                "to join") in caplog.text
        assert not done
        cluster.scale(1)
        runner.join(60)
        assert not runner.is_alive() and len(done[0]) == 2
    for chunk in split(6, 3):
        got = read_chunk_file(chunk_path(tmp_path / "out", chunk.index))
        np.testing.assert_array_equal(got["y"], np.arange(chunk.start, chunk.stop) ** 2)
