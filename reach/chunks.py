"""Run a job chunk by chunk on any `concurrent.futures.Executor`, each finished chunk
stored by this process: the one mechanism behind sweeps (`reach.sweep`), batches of
rollouts (`reach.outcomes.map_states`) and dataset images (`training.dataset`).
Several jobs (a stage's environments) run together on one executor through
`reach.chunk_jobs.run_together`: their chunks share its window, so none of its
workers idles at the tail of one job while another has work.

A task runs on the executor and *returns* its chunk's arrays (a worker shares no
filesystem with this process); the driver stores each finished chunk
(`reach.chunk_files.FolderStore`: one ``.npz`` per chunk, written atomically with its
checksum; or any object with ``valid(chunk)`` and ``store(chunk, arrays)``) and skips the chunks stored
already, so a killed job resumes and a repeated one costs nothing. A bounded window
of chunks is in flight (progress shows, an abort stops soon). A store's folder may be
an fsspec URL (`reachwatch.systems.files.cache_location`): only this process reads it."""

import collections
import concurrent.futures as cf
import concurrent.futures.process  # noqa: F401  (BrokenProcessPool)
import functools
import logging
import time
from typing import Callable

import numpy as np

from .chunk_jobs import Stopped, current_job
from .executors import (InlineExecutor, Window, WorkerLost, counter_value, has_no_workers,
                        stop_executor)

_log = logging.getLogger(__name__)


# --- per-row progress ---------------------------------------------------------------

_ON_ROW = None        # called once per finished row (progress), when set


def row_done():
    """A task that reports its progress row by row calls this once per row: it moves
    the bar of a job running here, or a pool's shared counter (`reach.sweep._init_worker`)."""
    if _ON_ROW is not None:
        _ON_ROW()


def set_row_hook(hook):
    """Make ``hook()`` what `row_done` calls in this process (None: nothing); returns
    the hook it replaces."""
    global _ON_ROW
    previous, _ON_ROW = _ON_ROW, hook
    return previous


# --- several jobs at once --------------------------------------------------------------

#: What a cluster raises for a task it lost (Dask's: its workers kept dying on it, or
#: the scheduler went away), by class name, so that no cluster package is imported here;
#: ``CancelledError``: a task the cluster cancelled more than `CANCELLED_RETRIES` times.
LOST_TASK_ERRORS = ("KilledWorker", "FutureCancelledError", "CommClosedError", "CancelledError")

#: Seconds `run_chunks` waits for its chunks in flight to finish, to store them, when it
#: stops because another job failed (`reach.chunk_jobs.Stopped`); an interrupt waits for
#: none.
STOPPED_GRACE_S = 2.0

#: How many times `run_chunks` submits again a chunk the cluster cancelled (Dask cancels
#: the tasks whose input it lost with a worker: the files scattered to it), before it is
#: a `WorkerLost`.
CANCELLED_RETRIES = 3


def _lost(error: BaseException, caller: str, chunk) -> BaseException:
    """``error``, or a `WorkerLost` saying so in one line when a cluster lost the task."""
    if type(error).__name__ not in LOST_TASK_ERRORS:
        return error
    lost = WorkerLost(f"the cluster lost {caller} chunk {chunk.index} ({type(error).__name__}: "
                      f"{str(error)[:200]}); finished chunks are kept and a re-run resumes")
    lost.__cause__ = error
    return lost


def _scheduler_lost(executor) -> bool:
    """Whether ``executor`` is a cluster client (Dask's) no longer connected to its
    scheduler: it cancels every task then, and nothing is submitted again."""
    status = getattr(getattr(executor, "_client", None), "status", "running")
    return status != "running"


#: Seconds a chunk may be in flight before `run_chunks` warns that its worker may be
#: stuck (once per chunk; it waits on).
STALL_WARNING_S = 1800.0

#: Seconds between two questions to a cluster's scheduler, while chunks are in flight,
#: whether it has any worker left (`has_no_workers`).
NO_WORKERS_CHECK_S = 60.0


# --- the runner -------------------------------------------------------------------------

class _NoBar:
    n = 0

    def update(self, k):
        self.n += k

    def close(self):
        pass


def run_chunks(task: Callable, chunks, store, *, args: Callable, executor=None,
               default: Callable = InlineExecutor, bar: Callable = None,
               max_in_flight: int = None, least: int = 4, per_row: bool = False,
               caller: str = "run_chunks") -> list:
    """Run ``task(*args(chunk))`` on ``executor`` for every chunk of ``chunks`` that
    ``store`` does not hold valid yet, and ``store.store(chunk, arrays)`` the arrays each
    returns, here, as it finishes; returns the chunks it ran.

    ``task`` and ``args(chunk)`` (the chunk's own inputs: its rows' states, say, not all
    of them) must be picklable when the executor runs elsewhere (a module-level
    function; a `functools.partial` of one). ``executor`` None: ``default()``, made
    only when there is work and shut down at the end (stopped at once on an error).
    At most ``max_in_flight`` chunks are in flight (default: `in_flight`, at least
    ``least``, read again as it runs: a `Window`). ``bar``: a tqdm-like factory called
    with ``initial=`` (the rows stored already); it moves per chunk, or with ``per_row``
    per row (the task calls `row_done`): here through the hook, on a pool with a
    ``progress_counter`` (see `reach.sweep.default_executor`) by its counter. When a
    worker dies, a `RespawningPool` is replaced and the chunks lost with it run again
    (a warning says so); on any other pool, or with no respawn left, it is a one-line
    RuntimeError naming ``caller``; finished chunks are kept. A chunk a cluster cancelled
    (it lost the worker holding the task's input) is submitted again, up to
    `CANCELLED_RETRIES` times, a warning saying so each time.

    In a job of `reach.chunk_jobs.run_together` on ``executor``, the chunks in flight
    also count against the window all its jobs share, the bar is drawn at the job's line
    and moves per chunk (a pool's counter counts every job's rows), and once another
    job failed the call stops at its next chunk (`reach.chunk_jobs.Stopped`)."""
    if max_in_flight is not None and (isinstance(max_in_flight, bool) or not isinstance(
            max_in_flight, (int, np.integer)) or max_in_flight < 1):
        raise ValueError(f"{caller}: max_in_flight must be a whole number >= 1 (or None: "
                         f"twice the executor's threads), got {max_in_flight!r}")
    chunks = list(chunks)
    todo = [c for c in chunks if not store.valid(c)]
    rows = sum(c.rows for c in chunks)
    computed = sum(c.rows for c in todo)
    job = current_job()
    bar = (bar(initial=rows - computed, **({} if job is None else {"position": job[1]}))
           if bar is not None else _NoBar())
    owned = executor is None and bool(todo)
    executor = executor or (default() if todo else None)
    shared = job[0] if job is not None and executor is job[0].executor else None
    if shared is not None:
        shared.count_rows(known=rows, stored=rows - computed)
    window = Window(executor, least=least, fixed=max_in_flight)
    def pool_counter():
        return (getattr(executor, "progress_counter", None) if per_row and shared is None
                else None)
    counter = pool_counter()
    counted = counter_value(counter) if counter is not None else 0
    hooked = per_row and isinstance(executor, InlineExecutor) and job is None
    previous_hook = set_row_hook(functools.partial(bar.update, 1)) if hooked else None
    pending, submitted, stalled = {}, {}, set()
    cancelled, retries = [], collections.Counter()     # chunks the cluster cancelled

    def show():
        if counter is not None:
            bar.update(min(counter_value(counter) - counted, computed)
                       - (bar.n - (rows - computed)))

    def finish(done):
        error = None
        for future in done:
            chunk = pending.pop(future)
            submitted.pop(future, None)
            stalled.discard(future)
            try:
                arrays = future.result()
            except cf.CancelledError as e:       # not by this call: it cancels none it keeps
                if (retries[chunk.index] < CANCELLED_RETRIES and error is None
                        and not _scheduler_lost(executor)):
                    retries[chunk.index] += 1
                    cancelled.append(chunk)
                    _log.warning("%s: the cluster cancelled chunk %d (it lost the worker "
                                 "running it or holding its input); it is submitted again",
                                 caller, chunk.index)
                else:
                    error = error or _lost(e, caller, chunk)
                continue
            except BaseException as e:           # raised once the others done are stored
                error = error or _lost(e, caller, chunk)
                continue
            store.store(chunk, arrays)
            if shared is not None:
                shared.count_rows(done=chunk.rows)
            if counter is None and not hooked:
                bar.update(chunk.rows)
        show()
        if error is not None:
            raise error

    def keep_finished(grace: float = 0.0):
        """On an error: store the chunks that finished meanwhile (waiting up to ``grace``
        s for those in flight), cancel the rest. Done ones are stored before anything is
        cancelled: a cluster's future cancels even when its task has finished and only
        its result is still on the way."""
        if grace and pending:
            cf.wait(pending, timeout=grace)
        for future, chunk in list(pending.items()):
            if future.done() and not future.cancelled() and future.exception() is None:
                try:                # the error being raised is the one to see
                    store.store(chunk, future.result())
                    if shared is not None:
                        shared.count_rows(done=chunk.rows)
                    if counter is None and not hooked:
                        bar.update(chunk.rows)
                except Exception as e:
                    _log.warning("%s: chunk %d finished but could not be stored (%s: %s); "
                                 "a re-run computes it again", caller, chunk.index,
                                 type(e).__name__, e)
            else:
                future.cancel()
        pending.clear()
        submitted.clear()
        stalled.clear()

    def wait():
        if shared is not None:
            shared.check()
        finish(cf.wait(pending, timeout=0.25, return_when=cf.FIRST_COMPLETED).done)
        warn_no_workers()
        warn_stalled()

    no_workers = {"asked": time.monotonic(), "said": False}

    def warn_no_workers():
        """A warning, once while it lasts, when the cluster has no worker left (all
        died or were stopped: its chunks wait for one to join, which Dask does for
        ever), asked every `NO_WORKERS_CHECK_S` s."""
        now = time.monotonic()
        if not pending or now - no_workers["asked"] < NO_WORKERS_CHECK_S:
            return
        no_workers["asked"] = now
        if not has_no_workers(executor):
            no_workers["said"] = False
        elif not no_workers["said"]:
            no_workers["said"] = True
            _log.warning("%s: the cluster has no workers now; %d chunk(s) in flight wait "
                         "for one to join (start one with `dask worker`, or Ctrl-C: "
                         "finished chunks are kept, and a re-run resumes)", caller,
                         len(pending))

    def warn_stalled():
        """A warning, once per chunk, for a chunk in flight longer than
        `STALL_WARNING_S` (a worker stuck in a GL driver or on a stalled mount would
        else wait for ever without a word)."""
        now = time.monotonic()
        for future, chunk in list(pending.items()):
            waited = now - submitted.get(future, now)
            if waited > STALL_WARNING_S and future not in stalled and not future.done():
                stalled.add(future)
                _log.warning("%s: chunk %d has been in flight for %.0f min; a worker may be "
                             "stuck (a GL driver, a stalled mount). Finished chunks are "
                             "kept: Ctrl-C stops the run, and a re-run resumes",
                             caller, chunk.index, waited / 60)

    def submit(chunk):
        if shared is not None:    # a slot of the window the jobs run together share
            while True:
                shared.check()
                if shared.take(block=not pending):
                    break
                if pending:
                    wait()
        try:
            future = executor.submit(task, *args(chunk))
        except BaseException as e:
            if shared is not None:
                shared.give()
            lost = _lost(e, caller, chunk)     # a cluster gone while submitting: one line
            if lost is e:
                raise
            raise lost from e
        if shared is not None:
            future.add_done_callback(shared.give)
        pending[future] = chunk
        submitted[future] = time.monotonic()

    respawn = getattr(executor, "respawn", None)
    try:   # a bounded window of chunks in flight: progress shows, an abort stops soon
        left = todo
        while True:
            generation = getattr(executor, "generation", 0)
            try:
                for chunk in left:
                    submit(chunk)
                    finish([f for f in pending if f.done()])
                    while len(pending) >= window.size():
                        wait()
                while pending:
                    wait()
                if not cancelled:
                    break
                left, cancelled[:] = list(cancelled), []
            except cf.process.BrokenProcessPool:
                keep_finished()
                if shared is not None:
                    shared.check()          # the jobs were stopped: not a death to mend
                if respawn is None or not respawn(generation):
                    raise
                left = [c for c in todo if not store.valid(c)]
                cancelled.clear()
                counter = pool_counter()    # the fresh pool's own
                if counter is not None:     # the lost chunks' rows count again
                    counted = counter_value(counter) - (computed - sum(c.rows for c in left))
                _log.warning("%s: a worker process died (killed, out of memory, or a crash "
                             "in native code); the pool was started again, and the %d "
                             "chunk(s) not stored yet run on it", caller, len(left))
    except BaseException as e:
        try:      # another job failed: what is in flight is worth its short wait
            keep_finished(STOPPED_GRACE_S if isinstance(e, Stopped) else 0.0)
        finally:                            # a chunk that cannot be stored stops the rest
            if owned:
                stop_executor(executor, abort=True)
                owned = False
        if isinstance(e, cf.process.BrokenProcessPool):
            raise WorkerLost(
                f"a {caller} worker process died (killed, out of memory, or a crash in "
                f"native code); finished chunks are kept and a re-run resumes. A script "
                f"calling {caller} without `if __name__ == '__main__':` dies so too: workers "
                f"are spawned (or pass executor=InlineExecutor())") from e
        raise
    finally:
        if hooked:
            set_row_hook(previous_hook)
        bar.close()
        if owned:
            stop_executor(executor)
    return todo
