"""Several jobs of chunks at once (`run_together`): a stage's environments, each a job
of `reach.chunks.run_chunks` calls, run together on one executor, their chunks in one
window sized to it, so none of its workers idles at the tail of one job while another
has work. A failing job stops the others at their next chunk (`Stopped`); their lines
come in the jobs' order (`ordered_log`)."""

import concurrent.futures as cf
import contextvars
import sys
import threading
from typing import Callable

from .executors import InlineExecutor, Window


class Stopped(RuntimeError):
    """What a job of `run_together` raises at its next chunk once another job failed
    (or the wait for them was interrupted): its queued chunks are cancelled, the ones
    that finished are stored."""


#: ``(_Together, index)`` of the `run_together` job running in this thread, else None.
_JOB = contextvars.ContextVar("reachwatch_together_job", default=None)


def current_job():
    """``(shared, index)`` of the `run_together` job running in this thread (``shared``:
    what its jobs share, whose window its `run_chunks` calls take slots of), else None."""
    return _JOB.get()


class _Together:
    """What the jobs of one `run_together` share: one window of chunks in flight on the
    executor (a `Window` of it, for all their `run_chunks` calls on it at once), the
    first failure (which stops the others) and their log lines, passed on in the jobs'
    order (a job's lines wait until every job before it has finished)."""

    def __init__(self, executor, names):
        self.executor, self.names = executor, list(names)
        self.slots, self.taken = Window(executor, least=8), 0
        self.failed = None                  # (index, why) of the first job that failed
        self.done = [False] * len(self.names)
        self.head = 0                       # the first job not finished: its lines go out
        self.held = [[] for _ in self.names]
        # [done now, stored before, known] of all their run_chunks calls
        self.rows = [0, 0, 0]
        self.cond = threading.Condition()

    def count_rows(self, *, known: int = 0, stored: int = 0, done: int = 0):
        """A job's `run_chunks` call knows of ``known`` more rows, ``stored`` of them
        already (by an earlier run), or has ``done`` more now."""
        with self.cond:
            self.rows[0] += done
            self.rows[1] += stored
            self.rows[2] += known

    def show_rows(self, bar):
        """``bar`` (a tqdm-like bar) at the rows done of those known so far: those
        stored before as its ``initial`` (not in its rate), those done now by
        ``update``."""
        with self.cond:
            done, stored, known = self.rows
        if stored != bar.initial:
            more = stored - bar.initial
            bar.initial += more
            bar.n += more
            bar.last_print_n = getattr(bar, "last_print_n", 0) + more
        if bar.total != known:
            bar.total = known
            bar.refresh()
        bar.update(done + stored - bar.n)

    def take(self, block: bool) -> bool:
        """A slot of the window for one chunk; without one, False (after up to 0.25 s
        waiting for one with ``block``). The window's size is read before the lock is
        taken: reading it may wait for the Dask client's event loop, which completes
        futures and so calls `give`, which takes the lock."""
        slots = self.slots.size()
        with self.cond:
            if self.taken < slots:
                self.taken += 1
                return True
            if block:
                self.cond.wait(0.25)
            return False

    def give(self, _future=None):
        with self.cond:
            self.taken -= 1
            self.cond.notify_all()

    def fail(self, index: int, why: str):
        with self.cond:
            if self.failed is None:
                self.failed = (index, why)
            self.cond.notify_all()

    def check(self):
        """Raise `Stopped` once a job failed."""
        if self.failed is not None:
            raise Stopped(f"stopped: {self.failed[1]}")

    def say(self, index: int, log: Callable, message):
        with self.cond:
            if index <= self.head:
                log(message)
            else:
                self.held[index].append((log, message))

    def finished(self, index: int = None):
        """Job ``index`` ended (None: all of them, as far as the log goes): pass on the
        lines held for the jobs now first."""
        with self.cond:
            if index is None:
                self.done = [True] * len(self.done)
            else:
                self.done[index] = True
            while self.head < len(self.done) and self.done[self.head]:
                self.head += 1
                if self.head < len(self.done):
                    for log, message in self.held[self.head]:
                        log(message)
                    self.held[self.head].clear()
            if index is None:
                for held in self.held:
                    for log, message in held:
                        log(message)
                    held.clear()


def together(executor, count: int) -> bool:
    """Whether `run_together` runs ``count`` jobs on ``executor`` at once (a pool, more
    than one job) rather than one after another here (inline)."""
    return count > 1 and executor is not None and not isinstance(executor, InlineExecutor)


def ordered_log(log: Callable) -> Callable:
    """``log``, passing on the lines of `run_together`'s jobs in the jobs' order (those
    of a job wait until every job before it has finished), so that jobs run together
    log what they log one after another; elsewhere ``log`` itself."""
    def say(message):
        job = _JOB.get()
        if job is None:
            log(message)
        else:
            job[0].say(job[1], log, message)
    return say


def _named(error: BaseException, prefix: str) -> BaseException:
    """``error`` with ``prefix`` before its message (its type and traceback kept); an
    error whose message is not its one argument carries ``prefix`` as a note."""
    plain = (len(error.args) == 1 and isinstance(error.args[0], str)
             and not (isinstance(error, OSError) and error.errno is not None))
    if plain:
        error.args = (f"{prefix}: {error.args[0]}",)
    else:
        error.add_note(prefix)
    return error


#: Seconds an interrupted `run_together` waits for its jobs to store their finished
#: chunks and stop before it raises the interrupt.
JOBS_STOP_S = 10.0


def run_together(jobs, executor, *, what: str = "job", bar: Callable = None,
                 rows_bar: Callable = None) -> list:
    """``[fn() for name, fn in jobs]``, the jobs run at once, each in a thread of this
    process, when ``executor`` is a pool (`together`): every `run_chunks` call of a job
    on ``executor`` shares one window of chunks in flight with the others' (a `Window`
    of the executor, so a large cluster gets all jobs' chunks at once), draws its bar at
    the job's line (tqdm's ``position``, moving per chunk) and stops at its next chunk
    once another job failed: its queued chunks are cancelled, its finished ones stored.
    Inline, the jobs run one after another here.

    Results come in the jobs' order. A job's error is raised (once all have stopped)
    with ``"{what} {name}: "`` before its message, its type kept; with several, the
    first to fail. Lines logged through `ordered_log` come in the jobs' order. ``bar``:
    a tqdm-like factory of a bar counting the jobs done (below theirs). ``rows_bar``:
    one of a bar counting the rows all the jobs' `run_chunks` calls have done, of those
    they know of so far (below that), whose rate and time left are the whole machine's
    where each job's bar reads its share; drawn when the jobs run at once. On an
    interrupt the jobs are told to stop, and the interrupt is raised once they have
    stored their finished chunks and stopped (within 0.25 s of their chunk loop), or
    after `JOBS_STOP_S` (their threads are daemons; stopping the executor ends their
    chunks), with the names of those still running in its ``jobs_still_writing``: what
    they write may still change, so the caller must not copy it elsewhere."""
    jobs = list(jobs)
    at_once = together(executor, len(jobs))
    count = bar(total=len(jobs), **({"position": len(jobs)} if at_once
                                    else {})) if bar is not None else None
    rows = (rows_bar(total=0, position=len(jobs) + (count is not None))
            if rows_bar is not None and at_once else None)
    try:
        if not at_once:
            results = []
            for name, fn in jobs:
                try:
                    results.append(fn())
                except Exception as e:
                    raise _named(e, f"{what} {name}")
                if count is not None:
                    count.update(1)
            return results
        return _run_threads(jobs, executor, what, count, rows)
    finally:
        for drawn in (count, rows):
            if drawn is not None:
                drawn.close()


def _run_threads(jobs, executor, what, count, rows) -> list:
    shared = _Together(executor, [name for name, _ in jobs])
    futures = [cf.Future() for _ in jobs]

    def work(index, fn, future):
        _JOB.set((shared, index))          # this thread's own context (copied below)
        try:
            future.set_result(fn())
        except BaseException as e:
            if not isinstance(e, Stopped):
                shared.fail(index, f"{what} {jobs[index][0]} failed")
            future.set_exception(e)
        finally:
            shared.finished(index)

    for index, ((name, fn), future) in enumerate(zip(jobs, futures)):
        threading.Thread(target=contextvars.copy_context().run, args=(work, index, fn, future),
                         name=f"together-{index}", daemon=True).start()
    try:
        waiting = set(futures)
        while waiting:
            done, waiting = cf.wait(waiting, timeout=0.25)
            if count is not None and done:
                count.update(len(done))
            if rows is not None:
                shared.show_rows(rows)
    except BaseException:                 # an interrupt: the jobs stop at their next chunk
        shared.fail(-1, "interrupted")
        # and store what finished before it is raised: what the caller does next (a
        # push of the run directory) must not race their writes (a dataset's rows
        # written after its arrays were put, its manifest naming them after)
        still = cf.wait(futures, timeout=JOBS_STOP_S).not_done
        if still:
            error = sys.exc_info()[1]
            error.jobs_still_writing = [jobs[futures.index(f)][0] for f in still]
        raise
    finally:
        shared.finished(None)             # lines still held (a failure, an interrupt)
    if shared.failed is not None:
        index = shared.failed[0]
        error = futures[index].exception()
        raise _named(error, f"{what} {jobs[index][0]}")
    return [future.result() for future in futures]
