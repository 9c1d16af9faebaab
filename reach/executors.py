"""The executors chunked work runs on (`reach.chunks.run_chunks`): `InlineExecutor` in
this process, `RespawningPool` (the local pool, which replaces itself when a worker
dies), any other `concurrent.futures.Executor` (a Dask client's); how many chunks each
runs at once, and how it is stopped."""

import concurrent.futures as cf
import concurrent.futures.process  # noqa: F401  (ProcessPoolExecutor)
import functools
import importlib
import pickle
import threading
import time
from typing import Callable

from reachwatch.systems.files import keyed_by_driver, keyed_digests


class InlineExecutor(cf.Executor):
    """Runs each task at submit time in this process (small sweeps, tests)."""

    def submit(self, fn, /, *args, **kwargs):
        future = cf.Future()
        try:
            future.set_result(fn(*args, **kwargs))
        except BaseException as e:  # delivered through the future, like a pool would
            future.set_exception(e)
        return future


#: How many times a `RespawningPool` replaces itself after a worker died, over its life.
RESPAWNS = 3


class RespawningPool(cf.Executor):
    """A process pool (``make()``, a `concurrent.futures.ProcessPoolExecutor`) that
    replaces itself when one of its workers dies: a dead worker breaks a process pool
    for good, and every chunk in flight with it. `run_chunks` then calls `respawn` and
    runs the lost chunks again on the fresh pool (chunks are pure functions of their
    inputs, so the results are the same), at most ``respawns`` times over the pool's
    life; after that a death is `run_chunks`' one-line error. ``new_counter``, when
    given, makes the shared counter a pool's workers count into (`progress_counter`;
    ``make(counter)`` then makes the pool): each pool gets its own, since a worker
    killed while it held a counter's lock would hold it for good, and every later
    worker and reader would wait on it. ``code``, when given
    (the driver's `reach.fingerprint.loop_code_digest`, which every key it computes
    carries), is checked by each task against its worker's own (`same_loop_code`): a
    worker started after the source was edited (a replacement, a later spawn) does not
    store results under keys of other code."""

    def __init__(self, make: Callable, *, respawns: int = RESPAWNS,
                 new_counter: Callable = None, code: str = None):
        self._make, self._new_counter, self._code = make, new_counter, code
        self._lock = threading.Lock()
        self.pool, self.progress_counter = self._new_pool()
        self.generation = 0             # how many times the pool was replaced
        self.respawns_left = int(respawns)
        self.closed = False             # shut down: never replaced again

    def _new_pool(self):
        """A fresh pool and the counter its workers count into (None without one)."""
        if self._new_counter is None:
            return self._make(), None
        counter = self._new_counter()
        return self._make(counter), counter

    @property
    def _max_workers(self) -> int:      # what `executor_threads` reads of a pool
        return self.pool._max_workers

    @property
    def _processes(self):               # the workers of the pool now (pid -> process)
        return self.pool._processes

    def submit(self, fn, /, *args, **kwargs):
        if self._code is not None:
            return self.pool.submit(same_loop_code, self._code, keyed_digests(), fn,
                                    *args, **kwargs)
        return self.pool.submit(fn, *args, **kwargs)

    def respawn(self, generation: int) -> bool:
        """Replace the pool that broke at ``generation`` (the `generation` its chunks
        were submitted at) with a fresh one, once however many callers saw it break;
        False, and nothing replaced, when no respawn is left."""
        with self._lock:
            if self.closed:                 # stopped (Ctrl-C, an error): not a death
                return False
            if generation != self.generation:
                return True                 # another caller replaced it already
            if self.respawns_left <= 0:
                return False
            self.respawns_left -= 1
            broken = self.pool
            self.pool, self.progress_counter = self._new_pool()
            self.generation += 1
        stop_executor(broken, abort=True)
        return True

    def close(self):
        """The pool now, marked so that it is never replaced again."""
        with self._lock:
            self.closed = True
            return self.pool

    def shutdown(self, wait=True, *, cancel_futures=False):
        self.close().shutdown(wait=wait, cancel_futures=cancel_futures)


def counter_value(counter) -> int:
    """A pool's shared counter (`RespawningPool.progress_counter`) read without its
    lock, which a worker killed while holding it would hold for good: a progress bar
    may read a count one row behind, never wait."""
    raw = getattr(counter, "get_obj", None)
    return int(raw().value if raw is not None else counter.value)


class WorkerLost(RuntimeError):
    """A chunk a worker could not finish for reasons outside the work itself: the worker
    died (killed, out of memory, a crash in native code), ran other code than the
    driver's, or the cluster lost it. Finished chunks are kept and a re-run resumes; the
    command line says it in one line."""


def same_loop_code(expected: str, keyed, fn, /, *args, **kwargs):
    """``fn(*args, **kwargs)`` in a pool worker whose loop code (`loop_code_digest`) is
    ``expected``, the driver's; else one line, before any result. A checkpoint or a
    user's code it loads must be content the driver keyed (``keyed``, its
    `keyed_digests`: `keyed_by_driver`)."""
    from .fingerprint import loop_code_digest
    mine = loop_code_digest()
    if mine != expected:
        raise WorkerLost(f"this worker's reachwatch source (loop code {mine[:12]}) is not the "
                           f"driver's ({expected[:12]}): it was edited after the driver "
                           f"started; start the run again (it resumes from its caches)")
    with keyed_by_driver(keyed):
        return run_portably(fn, *args, **kwargs)


def run_portably(fn, /, *args, **kwargs):
    """``fn(*args, **kwargs)`` in a worker, an exception it raises made one the driver
    can read back (`portable_error`), the original its cause (a process pool's traceback
    text keeps the original's frames)."""
    try:
        return fn(*args, **kwargs)
    except Exception as e:
        portable = portable_error(e)
        if portable is e:
            raise
        # the original's frames, the user's among them, are the new one's too
        raise portable.with_traceback(e.__traceback__) from e


def portable_error(error: Exception) -> Exception:
    """``error`` when the driver can read it back (its class importable by name there,
    and pickled and unpickled whole); else an instance of its first built-in base
    class (`ValueError`, `KeyError`, ...) saying ``Type: message``. A user's exception
    of a helper module the driver never imports, or whose ``__init__`` takes other
    arguments than it passes on, would fail to unpickle in the driver: the pool then
    reads as broken (a dead worker), the chunk runs again on a fresh one, and the
    user's message is lost."""
    cls = type(error)
    try:
        module = importlib.import_module(cls.__module__)
        same = functools.reduce(getattr, cls.__qualname__.split("."), module) is cls
        if same and type(pickle.loads(pickle.dumps(error))) is cls:
            return error
    except Exception:       # noqa: BLE001 (any failure to read it back is the answer)
        pass
    try:
        text = f"{cls.__name__}: {error}" if str(error) else cls.__name__
    except Exception:       # noqa: BLE001 (a __str__ that fails)
        text = cls.__name__
    for base in cls.__mro__:                    # the first built-in made from one message
        if base.__module__ == "builtins":
            try:
                return base(text)
            except Exception:   # noqa: BLE001 (UnicodeDecodeError takes five arguments)
                continue
    return Exception(text)


def stop_executor(executor, *, abort: bool = False):
    """Shut ``executor`` down; with ``abort``, cancel queued work and kill a process
    pool's workers now instead of waiting for their current chunk (finished chunks are
    on disk already)."""
    if executor is None or not hasattr(executor, "shutdown"):
        return
    if isinstance(executor, RespawningPool):
        executor = executor.close()
    if abort and isinstance(executor, cf.ProcessPoolExecutor):
        processes = list((getattr(executor, "_processes", None) or {}).values())
        for process in processes:
            process.terminate()
        executor.shutdown(wait=False, cancel_futures=True)
        for process in processes:
            process.join(5)
    else:
        executor.shutdown(wait=True, cancel_futures=abort)


#: Seconds a Dask client may take to say how many threads its cluster has.
ASK_TIMEOUT = 5.0


def _threads_now(executor):
    """How many chunks ``executor`` runs at once (0: a Dask cluster with no workers
    now), or None when it cannot tell (a Dask scheduler that did not answer within
    `ASK_TIMEOUT`)."""
    if isinstance(executor, InlineExecutor) or executor is None:
        return 1
    workers = getattr(executor, "_max_workers", None)
    if workers:
        return int(workers)
    client = getattr(executor, "_client", None)
    if client is not None:
        try:
            return int(sum(client.nthreads(callback_timeout=ASK_TIMEOUT).values()))
        except Exception:            # a client that cannot say now
            return None
    return 1


def has_no_workers(executor) -> bool:
    """Whether ``executor`` is a cluster whose scheduler says it has no workers now
    (its chunks wait for one to join)."""
    return getattr(executor, "_client", None) is not None and _threads_now(executor) == 0


def executor_threads(executor) -> int:
    """How many chunks ``executor`` runs at once: 1 inline, a pool's workers, a Dask
    cluster's threads (as connected now); 1 when it cannot tell."""
    return _threads_now(executor) or 1


def in_flight(executor, least: int = 4) -> int:
    """Chunks to keep in flight on ``executor``: twice its threads (so none idles while
    a finished chunk comes back), at least ``least``."""
    return _window_for(executor_threads(executor), least)


def _window_for(threads: int, least: int) -> int:
    return max(least, 2 * threads)


#: Seconds between two readings of an executor's threads by a `Window`.
WINDOW_REFRESH = 2.0


class Window:
    """How many chunks to keep in flight on ``executor``: ``fixed`` when given, else
    `in_flight` of it (at least ``least``), read again at most every `WINDOW_REFRESH`
    s, so that chunks spread over a cluster that grows while they run (workers started
    after the driver; an adaptive cluster grows by steps, since the driver never queues
    more than this window) and not only over the threads there were at the start.

    Reading a Dask cluster's threads asks its scheduler and waits for the client's
    event loop, the thread that also completes the chunks' futures: never call `size`
    while holding a lock that a future's done-callback takes. One thread reads at a
    time (the others go on with the size read last), and a reading that fails keeps
    that size."""

    def __init__(self, executor, *, least: int, fixed: int = None):
        self.executor, self.least, self.fixed = executor, least, fixed
        self._size, self._read = None, -float("inf")
        self._reading = threading.Lock()

    def size(self) -> int:
        if self.fixed:
            return self.fixed
        if self._size is not None and time.monotonic() - self._read < WINDOW_REFRESH:
            return self._size
        if not self._reading.acquire(blocking=self._size is None):
            return self._size                       # another thread reads it now
        try:
            if self._size is None or time.monotonic() - self._read >= WINDOW_REFRESH:
                threads = _threads_now(self.executor)
                if threads is not None or self._size is None:
                    self._size = _window_for(threads or 1, self.least)
                self._read = time.monotonic()
            return self._size
        finally:
            self._reading.release()
