"""Every environment's chunks at once (issue 56): `reach.chunk_jobs.run_together` runs a
stage's per-environment jobs together on one executor, their chunks in one window
sized to it; results, chunk files and log lines are those of one job after another;
a failing job names itself and stops the others' queued chunks, their finished ones
kept. The sweep stage on a 2-process pool gives the inline run's tables and files."""

import concurrent.futures as cf
import json
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from reachwatch.reach.chunk_files import FolderStore, read_chunk_file, split
from reachwatch.reach.chunk_jobs import ordered_log, run_together
from reachwatch.reach.chunks import run_chunks
from reachwatch.reach.executors import InlineExecutor, in_flight


def _rows(start, stop, delay=0.0, fail=False, gate=None):
    if gate is not None:
        gate.wait(10)
    if fail:
        raise RuntimeError(f"chunk at {start} failed")
    time.sleep(delay)
    return {"x": np.arange(start, stop) * 10}


class _Counting(cf.ThreadPoolExecutor):
    """A thread pool that records which jobs' chunks it holds at once."""

    def __init__(self, workers):
        super().__init__(workers)
        self.lock, self.held, self.most, self.both = threading.Lock(), {}, 0, False

    def submit(self, fn, /, *args, **kwargs):
        future = super().submit(fn, *args, **kwargs)
        with self.lock:
            self.held[future] = args[-1]              # the job's name (`_tagged`)
            self.most = max(self.most, len(self.held))
            self.both |= len(set(self.held.values())) > 1
        future.add_done_callback(self._release)
        return future

    def _release(self, future):
        with self.lock:
            self.held.pop(future, None)


def _tagged(start, stop, delay, job):
    return _rows(start, stop, delay)


def _job(folder, executor, name, lines, count=40, delay=0.01, log=None):
    def job():
        (log or lines.append)(f"[{name}] start")
        store = FolderStore(folder / name, keep=True)
        run_chunks(_tagged, split(count, 1), store, executor=executor, max_in_flight=count,
                   args=lambda c: (c.start, c.stop, delay, name))
        (log or lines.append)(f"[{name}] done")
        return np.concatenate([store.read(c)["x"] for c in split(count, 1)])
    return name, job


def test_jobs_together_share_one_window_and_log_in_their_order(tmp_path):
    lines = []
    log = ordered_log(lines.append)
    with _Counting(2) as pool:
        jobs = [_job(tmp_path, pool, n, lines, delay=d, log=log) for n, d in (("a", 0.02),
                                                                              ("b", 0.0))]
        a, b = run_together(jobs, pool, what="job")
    np.testing.assert_array_equal(a, np.arange(40) * 10)
    np.testing.assert_array_equal(b, np.arange(40) * 10)
    # both jobs' chunks were in flight at once, never more than the executor's window
    # (each call alone would keep all its 40 in flight)
    assert pool.both and pool.most <= in_flight(pool, least=8) < 40
    # b (no delay) finished first, but its lines come after a's: one job after another
    assert lines == ["[a] start", "[a] done", "[b] start", "[b] done"]
    inline = []
    jobs = [_job(tmp_path / "inline", InlineExecutor(), n, inline) for n in "ab"]
    again = run_together(jobs, InlineExecutor())
    assert len(again) == 2 and all(np.array_equal(x, y) for x, y in zip(again, [a, b]))
    assert inline == lines
    files = {p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*.npz")}
    assert {f.removeprefix("inline/") for f in files if f.startswith("inline/")} == \
        {f for f in files if not f.startswith("inline/")}


def test_a_failing_job_names_itself_and_stops_the_others_queued_chunks(tmp_path):
    """Job b fails once a has finished four chunks: a's finished chunks are stored (those
    in flight then too, `STOPPED_GRACE_S`), its queued ones never run, and the error is
    b's, named, its type kept."""
    ran, finished, gate = [], [], threading.Event()

    def slow(start, stop):
        ran.append(start)
        time.sleep(0.05)
        finished.append(start)
        if len(finished) >= 4:
            gate.set()
        return {"x": np.arange(start, stop)}

    def a():
        run_chunks(slow, split(40, 1), FolderStore(tmp_path / "a"), executor=pool,
                   args=lambda c: (c.start, c.stop))

    def b():
        run_chunks(_rows, split(1, 1), FolderStore(tmp_path / "b"), executor=pool,
                   args=lambda c: (c.start, c.stop, 0.0, True, gate))   # holds one worker
    with cf.ThreadPoolExecutor(2) as pool, \
            pytest.raises(RuntimeError, match=r"^job b: chunk at 0 failed$"):
        run_together([("a", a), ("b", b)], pool, what="job")
    stored = {int(p.stem.split("_")[1]) for p in (tmp_path / "a").iterdir()}
    # the chunks in flight when it stopped finished within its short wait: stored too
    assert stored == set(finished) and len(finished) >= 4 and len(ran) < 20
    # inline: one after another, the failing job named the same way, those after it not run
    calls = []

    def fails():
        raise ValueError("bad input")
    with pytest.raises(ValueError, match=r"^job b: bad input$"):
        run_together([("a", lambda: calls.append("a")), ("b", fails),
                      ("c", lambda: calls.append("c"))], InlineExecutor(), what="job")
    assert calls == ["a"]


class _SlowStore(FolderStore):
    """A store that takes its time to write a chunk (a dataset's rows and manifest)."""

    def store(self, chunk, arrays):
        time.sleep(0.3)
        super().store(chunk, arrays)


class _InterruptedBar:
    """A jobs' bar whose first update is Ctrl-C in the thread that runs the jobs."""

    def __init__(self, **kwargs):
        pass

    def update(self, n):
        raise KeyboardInterrupt

    def close(self):
        pass


class _RowsBar:
    """A tqdm-like bar that keeps what it was shown."""
    made = []

    def __init__(self, total=0, position=None):
        self.total, self.n, self.position, self.totals = total, 0, position, []
        self.initial, self.updated = 0, 0
        _RowsBar.made.append(self)

    def refresh(self):
        self.totals.append(self.total)

    def update(self, n):
        self.n += n
        self.updated += n

    def close(self):
        pass


def test_a_bar_of_every_jobs_rows_counts_those_done_before_and_those_known_so_far(tmp_path):
    """The jobs' bars each read their share of the machine (hours left for a job that
    ends in minutes); the rows bar reads the whole: every job's rows, those stored by
    an earlier run included, below the jobs' bars."""
    lines, _RowsBar.made[:] = [], []
    earlier = FolderStore(tmp_path / "b", keep=True)
    for chunk in split(40, 1)[:10]:                   # b resumes: 10 of its rows stored
        earlier.store(chunk, _tagged(chunk.start, chunk.stop, 0.0, "b"))
    with _Counting(2) as pool:
        jobs = [_job(tmp_path, pool, n, lines) for n in "ab"]
        run_together(jobs, pool, what="job", rows_bar=_RowsBar)
    [bar] = _RowsBar.made
    assert bar.position == 2 and (bar.n, bar.total) == (80, 80) and bar.totals[-1] == 80
    # the rows an earlier run stored are the bar's start, not in its rate
    assert (bar.initial, bar.updated) == (10, 70)
    run_together([_job(tmp_path / "inline", InlineExecutor(), n, lines) for n in "ab"],
                 InlineExecutor(), rows_bar=_RowsBar)
    assert len(_RowsBar.made) == 1                    # one after another: the jobs' own


def test_an_interrupt_is_raised_once_the_jobs_have_stored_what_finished(tmp_path):
    """Ctrl-C while a job is storing a chunk: raised once that job has stopped, its
    finished chunks stored, so that what the caller does next (a push of the run
    directory to its URL) sees no file still being written."""
    def quick():
        time.sleep(0.2)              # the slow job is storing its first chunks by then
        return 1

    def slow():
        run_chunks(_rows, split(8, 1), _SlowStore(tmp_path / "slow"), executor=pool,
                   args=lambda c: (c.start, c.stop, 0.05))
    with cf.ThreadPoolExecutor(2) as pool:
        with pytest.raises(KeyboardInterrupt):
            run_together([("slow", slow), ("quick", quick)], pool, bar=_InterruptedBar)
        stored = sorted((tmp_path / "slow").iterdir())
        time.sleep(0.7)                          # more than two chunks' stores
        assert sorted((tmp_path / "slow").iterdir()) == stored   # nothing written since
    assert 1 <= len(stored) < 8


def test_an_interrupt_names_the_jobs_still_writing_after_the_wait(monkeypatch):
    """A job that has not stopped within `JOBS_STOP_S` is named on the interrupt
    (``jobs_still_writing``), so that the caller does not copy files it may still
    change; one that stopped is not."""
    from reachwatch.reach import chunk_jobs
    monkeypatch.setattr(chunk_jobs, "JOBS_STOP_S", 0.3)

    def stuck():
        time.sleep(1.5)              # no chunk loop: it does not see the stop
        return 1

    def quick():
        time.sleep(0.2)
        return 1
    with cf.ThreadPoolExecutor(2) as pool:
        with pytest.raises(KeyboardInterrupt) as raised:
            run_together([("stuck", stuck), ("quick", quick)], pool, bar=_InterruptedBar)
    assert raised.value.jobs_still_writing == ["stuck"]


TWO = """
name: two
train: [{runway: KMWH, hour: 9.0, sky: clear}]
test: [{runway: KSFO, hour: 17.0, sky: clear}]
grid: [3, 3, 3]
"""
NAMES = ["KMWH_9h_clear", "KSFO_17h_clear"]


def _sweep(root, executor):
    from reachwatch.pipeline.brt_stages import stage_sweep
    from reachwatch.pipeline.spec import load_run_spec
    from reachwatch.pipeline.stages import Run
    log = []
    run = Run(load_run_spec(data=TWO), root, executor=executor, progress=False,
              log=log.append, only=NAMES)
    return run, stage_sweep(run), [m.split(" done in ")[0] for m in log]


def _chunk_files(root) -> dict:
    out = {}
    for path in sorted((root / "sweeps").rglob("*.npz")):
        with np.load(path) as data:
            out[path.relative_to(root).as_posix()] = {k: data[k] for k in data.files}
    return out


@pytest.fixture(scope="module")
def pool():
    from reachwatch.pipeline.executors import make_executor
    executor, close = make_executor("local:2")
    yield executor
    close()


def test_two_environments_swept_together_on_a_pool_match_the_inline_run(tmp_path, pool):
    run, inline, inline_log = _sweep(tmp_path / "inline", InlineExecutor())
    run_pool, together, together_log = _sweep(tmp_path / "pool", pool)
    assert list(together) == NAMES and together_log == inline_log
    assert [k for k in run_pool.outputs] == [k for k in run.outputs] == [
        f"sweep_{n}" for n in NAMES]
    for name in NAMES:
        assert {**together[name], "sweep_seconds": 0} == {**inline[name], "sweep_seconds": 0}
    files, expected = _chunk_files(tmp_path / "pool"), _chunk_files(tmp_path / "inline")
    assert files.keys() == expected.keys() and len(files) == 2
    for name, arrays in expected.items():
        assert files[name].keys() == arrays.keys()
        for key, array in arrays.items():
            np.testing.assert_array_equal(files[name][key], array)


def test_a_failing_environment_names_itself_and_the_others_chunks_are_kept(tmp_path, pool,
                                                                           monkeypatch):
    """KSFO fails once KMWH's sweep is recorded (its chunks stored): one line naming
    KSFO, its type kept; a re-run skips KMWH and sweeps KSFO alone."""
    from reachwatch.pipeline import brt_stages
    real = brt_stages.sweep_env

    def sweep_env(run, env, **kw):
        if env.name == NAMES[0]:
            return real(run, env, **kw)
        record = run.path(f"stages/sweep_{NAMES[0]}.json")
        for _ in range(600):
            if record.exists():
                break
            time.sleep(0.1)
        raise ValueError("no room on the runway")
    monkeypatch.setattr(brt_stages, "sweep_env", sweep_env)
    with pytest.raises(ValueError, match=rf"^sweep of environment {NAMES[1]}: no room on the "
                                         rf"runway$"):
        _sweep(tmp_path, pool)
    assert [p.parent.name for p in (tmp_path / "sweeps").rglob("chunk_*.npz")] == [
        f"{NAMES[0]}_3x3x3_" + p.parent.name.rpartition("_")[2]
        for p in (tmp_path / "sweeps").rglob("chunk_*.npz")]
    monkeypatch.undo()
    _, out, log = _sweep(tmp_path, pool)
    assert log[0].startswith(f"[sweep_{NAMES[0]}] up to date") and out[NAMES[0]]["rendered"] == 27
    assert log[1].startswith(f"[sweep_{NAMES[1]}] running") and out[NAMES[1]]["rendered"] == 27


def _fake_loop(edge, states):
    """A stand-in real loop: fails where |px| >= ``edge`` (no edge: raises)."""
    if edge is None:
        raise RuntimeError("the renderer is gone")
    n = len(states)
    return {"failed": np.abs(states[:, 0]) >= edge, "left_box": np.zeros(n, bool),
            "max_abs_theta": np.abs(states[:, 2]), "ticks": np.full(n, 7)}


def _fidelity(root, executor, edges):
    """The fidelity stage of two environments whose real loop is `_fake_loop` (chunks of
    one start through `map_states` on ``executor``) and whose BRT is |px| >= 5 m."""
    import functools

    from reachwatch.pipeline.fidelity_stages import stage_fidelity
    from reachwatch.pipeline.spec import load_run_spec
    from reachwatch.pipeline.stages import Run
    from reachwatch.reach.outcomes import Outcomes, map_states
    from reachwatch.taxi.application import TaxiApplication

    class FakeLoop(TaxiApplication):
        def real_outcomes(self, scenario, states, *, cache_dir, executor=None, progress=True,
                          **kw):
            fields, key, computed = map_states(
                functools.partial(_fake_loop, edges[scenario.environment.name]), states,
                cache_dir=cache_dir, chunk_size=1, executor=executor, progress=progress)
            return Outcomes(fields, key, computed)

    class Map:
        def at(self, states):
            return 5.0 - np.abs(np.asarray(states)[:, 0])

        def in_brt(self, states):
            return self.at(states) <= 0

    class FakeRun(Run):
        def value_function(self, name):
            return Map()

        def steering_table(self, env):
            grid = self.solved_grid_for(env)
            return grid, np.zeros(grid.shape + (1,))
    log = []
    run = FakeRun(load_run_spec(data=TWO + "fidelity: {starts: 6}\n"), root, executor=executor,
                  progress=False, log=log.append, only=NAMES)
    run.application = FakeLoop()
    for name in NAMES:
        run.records[f"solve_{name}"] = {"key": name, "files": {}}
    return run, stage_fidelity(run), [m.split(" done in ")[0] for m in log]


def _outcome_files(root) -> dict:
    out = {}
    for path in sorted((root / "outcomes").rglob("*.npz")):
        with np.load(path) as data:
            out[path.relative_to(root).as_posix()] = {k: data[k] for k in data.files}
    return out


def test_the_fidelity_stage_checks_every_environment_together(tmp_path):
    edges = {NAMES[0]: 5.0, NAMES[1]: 0.0}
    run, inline, inline_log = _fidelity(tmp_path / "inline", InlineExecutor(), edges)
    with cf.ThreadPoolExecutor(2) as pool:
        run_pool, together, together_log = _fidelity(tmp_path / "pool", pool, edges)
    assert list(together) == NAMES and together_log == inline_log
    assert [k for k in run_pool.outputs if k.startswith("fidelity_")] == [
        f"fidelity_{n}" for n in NAMES]
    for name in NAMES:
        assert {**together[name], "seconds": 0} == {**inline[name], "seconds": 0}
    assert together[NAMES[0]]["brt"]["agree"] == 6 and together[NAMES[1]]["brt"]["agree"] < 6
    files, expected = _outcome_files(tmp_path / "pool"), _outcome_files(tmp_path / "inline")
    assert files.keys() == expected.keys() and len(files) == 12
    for name, arrays in expected.items():
        for key, array in arrays.items():
            np.testing.assert_array_equal(files[name][key], array)
    with cf.ThreadPoolExecutor(2) as pool, pytest.raises(
            RuntimeError, match=rf"^fidelity check of environment {NAMES[1]}: the renderer is "
                                rf"gone$"):
        _fidelity(tmp_path / "failing", pool, {**edges, NAMES[1]: None})


def _dataset(root, executor, monkeypatch, fail=None):
    """The dataset stage of two environments whose build (`dataset_stages._build`) is a
    stand-in running 40 chunks on ``executor`` (``fail``: an environment whose build
    raises)."""
    import types

    from reachwatch.pipeline import dataset_stages
    from reachwatch.pipeline.spec import load_run_spec
    from reachwatch.pipeline.stages import Run

    def build(root, scenario, value_path, spec, ensemble, progress, box, application,
              executor):
        name = scenario.environment.name
        if name == fail:
            raise ValueError("no images")
        folder = Path(root) / name
        store = FolderStore(folder, keep=True)
        run_chunks(_tagged, split(40, 1), store, executor=executor,
                   args=lambda c: (c.start, c.stop, 0.01 * (name == NAMES[0]), name))
        return folder

    def load(folder):
        x = np.concatenate([read_chunk_file(p)["x"] for p in sorted(Path(folder).iterdir())])
        return types.SimpleNamespace(labels=(x % 3 == 0), manifest={
            "labels": {"source": "brt"}, "label_counts": {"ones": int(np.sum(x % 3 == 0))}})
    monkeypatch.setattr(dataset_stages, "_build", build)
    monkeypatch.setattr(dataset_stages, "load_dataset", load)
    monkeypatch.setattr(dataset_stages, "label_summary", lambda m: m["label_counts"])
    log = []
    run = Run(load_run_spec(data=TWO + "ensemble: {seeds: []}\n"), root, executor=executor,
              progress=False, log=log.append)
    run.outputs["solve"] = {n: {"value": f"brt/{n}.npz"} for n in NAMES}
    return dataset_stages.stage_dataset(run), log


def test_the_dataset_stage_builds_every_environment_together(tmp_path, monkeypatch):
    inline, inline_log = _dataset(tmp_path / "inline", InlineExecutor(), monkeypatch)
    with _Counting(2) as pool:
        together, log = _dataset(tmp_path / "pool", pool, monkeypatch)
    assert pool.both and log == inline_log and len(log) == 2
    assert json.dumps(together) == json.dumps(inline)           # the same, in the same order
    assert list(together["folders"]) == NAMES and together["positives"][NAMES[0]] == 14 / 40
    with _Counting(2) as pool, pytest.raises(
            ValueError, match=rf"^dataset of environment {NAMES[1]}: no images$"):
        _dataset(tmp_path / "failing", pool, monkeypatch, fail=NAMES[1])


def test_jobs_together_on_a_dask_client_finish_while_the_window_is_read_again(
        tmp_path, monkeypatch):
    """The shared window reads a Dask cluster's threads again as the jobs run, a call
    that waits for the client's event loop, the thread that completes the chunks'
    futures and so calls their done-callbacks, which take the window's lock: it is read
    outside that lock, so a chunk finishing meanwhile cannot stop the jobs (read under
    it, they stopped for good, 3 times of 3 on 3 jobs of 2,000 chunks)."""
    distributed = pytest.importorskip("dask.distributed")
    from reachwatch.reach import executors
    monkeypatch.setattr(executors, "WINDOW_REFRESH", 0.0)          # read at every chunk
    finished = []
    with distributed.LocalCluster(n_workers=1, threads_per_worker=2, processes=False,
                                  dashboard_address=None) as cluster, \
            distributed.Client(cluster) as client:
        executor = client.get_executor()
        assert executors._threads_now(executor) == 2       # the scheduler answers
        jobs = [(f"j{i}", lambda i=i: run_chunks(
                    _rows, split(300, 1), FolderStore(tmp_path / f"j{i}"), executor=executor,
                    args=lambda c: (c.start, c.stop)))
                for i in range(3)]
        runner = threading.Thread(target=lambda: finished.append(run_together(jobs, executor)),
                                  daemon=True)
        runner.start()
        runner.join(120)
        assert finished, "the jobs did not finish in 120 s"
    assert [len(ran) for ran in finished[0]] == [300, 300, 300]
