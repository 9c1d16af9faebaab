"""Run a job chunk by chunk on any `concurrent.futures.Executor`, each finished chunk
stored by this process: the one mechanism behind sweeps (`reach.sweep`), batches of
rollouts (`reach.outcomes.map_states`) and dataset images (`training.dataset`).

A task runs on the executor and *returns* its chunk's arrays (a worker shares no
filesystem with this process); the driver stores each finished chunk (`FolderStore`:
one ``.npz`` per chunk, written atomically with its `chunk_checksum`; or any object
with ``valid(chunk)`` and ``store(chunk, arrays)``) and skips the chunks stored
already, so a killed job resumes and a repeated one costs nothing. A bounded window
of chunks is in flight (progress shows, an abort stops soon). A store's folder may be
an fsspec URL (`reachwatch.systems.files.cache_location`): only this process reads it."""

import concurrent.futures as cf
import concurrent.futures.process  # noqa: F401  (BrokenProcessPool)
import dataclasses as dc
import functools
import hashlib
import io
from pathlib import Path
from typing import Callable

import numpy as np

from reachwatch.systems.files import cache_join, cache_location, read_location, write_location


class InlineExecutor(cf.Executor):
    """Runs each task at submit time in this process (small sweeps, tests)."""

    def submit(self, fn, /, *args, **kwargs):
        future = cf.Future()
        try:
            future.set_result(fn(*args, **kwargs))
        except BaseException as e:  # delivered through the future, like a pool would
            future.set_exception(e)
        return future


def stop_executor(executor, *, abort: bool = False):
    """Shut ``executor`` down; with ``abort``, cancel queued work and kill a process
    pool's workers now instead of waiting for their current chunk (finished chunks are
    on disk already)."""
    if executor is None or not hasattr(executor, "shutdown"):
        return
    if abort and isinstance(executor, cf.ProcessPoolExecutor):
        processes = list((getattr(executor, "_processes", None) or {}).values())
        for process in processes:
            process.terminate()
        executor.shutdown(wait=False, cancel_futures=True)
        for process in processes:
            process.join(5)
    else:
        executor.shutdown(wait=True, cancel_futures=abort)


def executor_threads(executor) -> int:
    """How many chunks ``executor`` runs at once: 1 inline, a pool's workers, a Dask
    cluster's threads (as connected now); 1 when it cannot tell."""
    if isinstance(executor, InlineExecutor) or executor is None:
        return 1
    workers = getattr(executor, "_max_workers", None)
    if workers:
        return int(workers)
    client = getattr(executor, "_client", None)
    if client is not None:
        try:
            return max(1, int(sum(client.nthreads().values())))
        except Exception:            # a client that cannot say: one at a time is safe
            return 1
    return 1


def in_flight(executor, least: int = 4) -> int:
    """Chunks to keep in flight on ``executor``: twice its threads (so none idles while
    a finished chunk comes back), at least ``least``."""
    return max(least, 2 * executor_threads(executor))


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


# --- chunks and their files ---------------------------------------------------------

@dc.dataclass(frozen=True)
class Chunk:
    """Rows ``start:stop`` of a job, its ``index``-th chunk."""
    index: int
    start: int
    stop: int

    @property
    def rows(self) -> int:
        return self.stop - self.start


def split(count: int, size: int) -> list:
    """``count`` rows as `Chunk` s of ``size`` rows (the last one shorter)."""
    if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or size < 1:
        raise ValueError(f"chunk_size must be a whole number >= 1, got {size!r}")
    return [Chunk(i, s, min(s + int(size), int(count)))
            for i, s in enumerate(range(0, int(count), int(size)))]


#: The entry of a chunk file holding `chunk_checksum` of its other arrays.
CHECKSUM = "checksum"


def chunk_checksum(arrays: dict) -> str:
    """SHA-256 (hex) of a chunk's arrays (all but `CHECKSUM`): names, dtypes, shapes and
    bytes. Stored in the chunk file when written and compared when it is read, so a
    chunk whose numbers changed since (its shape kept) is computed again."""
    digest = hashlib.sha256()
    for name in sorted(k for k in arrays if k != CHECKSUM):
        a = np.ascontiguousarray(arrays[name])
        digest.update(f"{name}:{a.dtype.str}:{a.shape};".encode())
        digest.update(a.tobytes())
    return digest.hexdigest()


def checksum_ok(arrays: dict) -> bool:
    """Whether a chunk's arrays match the `CHECKSUM` they were stored with (a chunk
    written before chunks carried one is taken as it is)."""
    return CHECKSUM not in arrays or str(arrays[CHECKSUM]) == chunk_checksum(arrays)


def store_chunk_file(path, arrays: dict):
    """Write a chunk's ``arrays`` (an ``.npz``, atomically: `write_location`) with their
    `chunk_checksum`; ``path`` is local or an fsspec URL."""
    buffer = io.BytesIO()
    np.savez(buffer, **arrays, **{CHECKSUM: np.asarray(chunk_checksum(arrays))})
    return write_location(path, buffer.getvalue())


def read_chunk_file(path, names=None) -> dict:
    """The arrays ``names`` (default: all, `CHECKSUM` too) of the chunk file ``path``:
    a local file is loaded as it lies, an fsspec URL's object read whole first. Raises
    what loading raises (missing, truncated, not an ``.npz``, an array it lacks)."""
    path = cache_location(path)
    source = path if isinstance(path, Path) else io.BytesIO(read_location(path))
    with np.load(source, allow_pickle=False) as data:
        return {k: data[k] for k in (data.files if names is None else names)}


def chunk_path(folder, index: int):
    """The file of chunk ``index`` in a `FolderStore`'s ``folder`` (a `Path`, or a URL
    string for a folder given as one)."""
    return cache_join(folder, f"chunk_{index:06d}.npz")


#: The entry of a chunk file that holds the rows ``[start, stop)`` it covers (written by a
#: `FolderStore` made with ``rows=True``).
ROWS = "_rows"


class FolderStore:
    """Chunks as files ``folder/chunk_000000.npz``, ... (`store_chunk_file`); ``folder``
    is a local path or an fsspec URL (``memory://...``, ``s3://...``). A stored
    chunk is valid when it loads, matches its checksum, covers the chunk's rows where
    its file says which (`ROWS`), and ``fits(chunk, arrays)`` (default: always);
    ``rows``: write `ROWS` into each chunk file, so that a chunk written with another
    chunk size is run again rather than read into the wrong rows (for a job whose key
    does not hold its chunk size); ``keep``: hold the arrays read or stored, for `read`."""

    def __init__(self, folder, fits: Callable = None, keep: bool = False, rows: bool = False):
        self.folder, self.fits, self.rows = cache_location(folder), fits, rows
        self.kept = {} if keep else None

    def path(self, chunk: Chunk):
        return chunk_path(self.folder, chunk.index)

    def read(self, chunk: Chunk):
        """The chunk's arrays (without `CHECKSUM`), or None when its file is missing,
        truncated, corrupt, fails its checksum or does not fit."""
        if self.kept is not None and chunk.index in self.kept:
            return self.kept[chunk.index]
        try:
            arrays = read_chunk_file(self.path(chunk))
            if not checksum_ok(arrays):
                return None
            arrays.pop(CHECKSUM, None)
            covered = arrays.pop(ROWS, None)
            if covered is not None and covered.tolist() != [chunk.start, chunk.stop]:
                return None
            if self.fits is not None and not self.fits(chunk, arrays):
                return None
        except Exception:   # missing, truncated, corrupt or lacking an array: run it again
            return None
        if self.kept is not None:
            self.kept[chunk.index] = arrays
        return arrays

    def valid(self, chunk: Chunk) -> bool:
        return self.read(chunk) is not None

    def store(self, chunk: Chunk, arrays: dict):
        store_chunk_file(self.path(chunk), {**arrays, ROWS: np.array([chunk.start, chunk.stop])}
                         if self.rows else arrays)
        if self.kept is not None:
            self.kept[chunk.index] = arrays


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
    ``least``). ``bar``: a tqdm-like factory called with ``initial=`` (the rows stored
    already); it moves per chunk, or with ``per_row`` per row (the task calls
    `row_done`): here through the hook, on a pool with a ``progress_counter`` (see
    `reach.sweep.default_executor`) by its counter. A pool whose worker died is a
    one-line RuntimeError naming ``caller``; finished chunks are kept."""
    chunks = list(chunks)
    todo = [c for c in chunks if not store.valid(c)]
    rows = sum(c.rows for c in chunks)
    computed = sum(c.rows for c in todo)
    bar = bar(initial=rows - computed) if bar is not None else _NoBar()
    owned = executor is None and bool(todo)
    executor = executor or (default() if todo else None)
    max_in_flight = max_in_flight or in_flight(executor, least=least)
    counter = getattr(executor, "progress_counter", None) if per_row else None
    counted = counter.value if counter is not None else 0
    hooked = per_row and isinstance(executor, InlineExecutor)
    previous_hook = set_row_hook(functools.partial(bar.update, 1)) if hooked else None
    pending = {}

    def show():
        if counter is not None:
            bar.update(min(counter.value - counted, computed) - (bar.n - (rows - computed)))

    def finish(done):
        error = None
        for future in done:
            chunk = pending.pop(future)
            try:
                arrays = future.result()
            except BaseException as e:           # raised once the others done are stored
                error = error or e
                continue
            store.store(chunk, arrays)
            if counter is None and not hooked:
                bar.update(chunk.rows)
        show()
        if error is not None:
            raise error

    def keep_finished():
        """On an error: store the chunks that finished meanwhile, cancel the rest."""
        for future, chunk in list(pending.items()):
            if not future.cancel() and future.done() and future.exception() is None:
                store.store(chunk, future.result())
        pending.clear()

    def wait():
        finish(cf.wait(pending, timeout=0.25, return_when=cf.FIRST_COMPLETED).done)

    try:   # a bounded window of chunks in flight: progress shows, an abort stops soon
        for chunk in todo:
            pending[executor.submit(task, *args(chunk))] = chunk
            finish([f for f in pending if f.done()])
            while len(pending) >= max_in_flight:
                wait()
        while pending:
            wait()
    except cf.process.BrokenProcessPool as e:
        keep_finished()
        if owned:
            stop_executor(executor, abort=True)
            owned = False
        raise RuntimeError(
            f"a {caller} worker process died; finished chunks are kept and a re-run "
            f"resumes. Workers are spawned: a script calling {caller} must guard its top "
            f"level with `if __name__ == '__main__':` (or pass executor=InlineExecutor())"
        ) from e
    except BaseException:
        keep_finished()
        if owned:
            stop_executor(executor, abort=True)
            owned = False
        raise
    finally:
        if hooked:
            set_row_hook(previous_hook)
        bar.close()
        if owned:
            stop_executor(executor)
    return todo
