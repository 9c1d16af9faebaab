"""Sweep a closed-loop diagram over a grid: set the plant state in a reused Context
and evaluate the control output port (and any others) at every node.

Works for any diagram: name the subsystem whose continuous state is the grid state
and the ports to read (``"system.port"``). Chunked; each finished chunk is written
atomically under ``cache_dir/key/``, so a killed sweep resumes and a repeated one
costs nothing. Chunks run on any `concurrent.futures.Executor` (`reach.chunks`)."""

import concurrent.futures as cf
import dataclasses as dc
import functools
import hashlib
import json
import logging
import multiprocessing
import os
import signal
import sys
import threading
import uuid
import warnings
from pathlib import Path
from typing import Callable, Tuple

import numpy as np
from tqdm import tqdm

from reachwatch.systems.files import cache_join, cache_location, make_folder, read_location, write_location

from .chunk_files import FolderStore, checksum_ok, chunk_checksum, chunk_path, read_chunk_file, split
from .chunks import row_done, run_chunks, set_row_hook
from .executors import (RESPAWNS, InlineExecutor, RespawningPool,  # noqa: F401
                        executor_threads, in_flight, stop_executor, WorkerLost)
from .fingerprint import Unfingerprintable, fingerprint, loop_code_digest
from .grid import Grid
from .thread_kept import KEPT_DIAGRAMS, ThreadKept

_log = logging.getLogger(__name__)


@dc.dataclass(frozen=True)
class Probe:
    """Where to write the state and what to read in a diagram: the subsystem whose
    continuous state is the grid state, and ports named ``"system.port"``."""
    plant: str
    control_port: str
    extra_ports: Tuple[str, ...] = ()

    @property
    def ports(self):
        return (self.control_port,) + tuple(self.extra_ports)


def _count_state(counter):
    with counter.get_lock():
        counter.value += 1


#: The pool's initializer, run by `exec` in each spawned worker before anything of
#: reachwatch is imported there: importing it loads Drake and torch (about 1 GB and
#: seconds), and a worker whose driver dies meanwhile must not live on. It starts a
#: thread that ends the worker within ``interval`` seconds of the driver's death
#: (however it died, SIGKILL too: the worker is then re-parented), then imports
#: `_init_worker` and runs it. Text, so that unpickling the initializer imports nothing.
_WORKER_START = """
import os, threading, time

def watch_parent(parent_pid, interval):
    while os.getppid() == parent_pid:
        time.sleep(interval)
    os._exit(3)

threading.Thread(target=watch_parent, args=(parent_pid, interval), daemon=True,
                 name="reachwatch-parent-watchdog").start()
from reachwatch.reach.sweep import _init_worker
_init_worker(counter, threads)
"""


def _init_worker(counter, threads: int = None):
    """In each spawned worker (after `_WORKER_START`'s watchdog): count evaluated
    states into the shared ``counter``, leave Ctrl-C to the driver (it stops the pool),
    and (``threads``) cap the worker's OpenMP / torch threads, and Mesa llvmpipe's
    render threads unless ``LP_NUM_THREADS`` is set, so that the workers together do
    not oversubscribe the cores (`render_threads`)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    set_row_hook(functools.partial(_count_state, counter))
    if threads is not None:
        render_threads(threads)
        os.environ["OMP_NUM_THREADS"] = str(threads)      # read when torch is imported
        torch = sys.modules.get("torch")
        if torch is not None:                              # imported already (spawn's main)
            torch.set_num_threads(threads)


def render_threads(threads: int):
    """Give this process's CPU renderer (Mesa's llvmpipe) ``threads`` threads, unless
    ``LP_NUM_THREADS`` says otherwise; call before its first render. llvmpipe takes a
    thread per core by default, so several rendering processes on one machine
    oversubscribe its cores: on 2 cores, two single-thread Dask workers with one render
    thread each swept 1.07 times as fast as with two each, and ran the real loop as
    fast (0.99; docs/scale.md). Pixels do not depend on it."""
    os.environ.setdefault("LP_NUM_THREADS", str(max(1, int(threads))))


def usable_cores() -> int:
    """The CPU cores this process may run on (its affinity mask where the OS has one)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:       # macOS, Windows
        return max(1, os.cpu_count() or 1)


#: Memory a sweep worker may use (about 0.95 GiB measured: Drake, VTK, torch, TaxiNet).
WORKER_MEMORY = 2 << 30


def default_worker_count() -> int:
    """``$REACHWATCH_WORKERS`` when set; else one worker per usable core, but no more
    than the machine's memory holds at `WORKER_MEMORY` each."""
    given = os.environ.get("REACHWATCH_WORKERS", "").strip()
    if given:
        if not given.isdigit() or int(given) < 1:
            raise ValueError(f"REACHWATCH_WORKERS must be a whole number >= 1, got '{given}'")
        return int(given)
    try:
        memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, ValueError, OSError):       # not POSIX: cores alone
        return usable_cores()
    return max(1, min(usable_cores(), memory // WORKER_MEMORY))


def default_executor(max_workers: int = None) -> cf.Executor:
    """A pool of spawned workers, `default_worker_count` by default (``max_workers``).
    CPU rendering alone does not keep the cores busy: around each render a worker
    runs Python, the controller's network and the readback, so on 2 cores two
    workers sweep about 1.7 times as fast as one (``benchmarks/sweep.py
    --workers``); results do not depend on the count. Each worker builds its diagram
    once, reports every evaluated state to ``executor.progress_counter``, runs its
    share of the cores' OpenMP / torch threads, ignores SIGINT and, from its first moment,
    checks every 0.1 s that this process is alive and exits when it is not. A
    `RespawningPool`: when a worker dies, the chunks lost with it run again on a fresh
    pool (`RESPAWNS` times at most)."""
    if max_workers is None:
        max_workers = default_worker_count()
    if isinstance(max_workers, bool) or not isinstance(max_workers, (int, np.integer)) \
            or max_workers < 1:
        raise ValueError(f"max_workers must be a whole number >= 1, got {max_workers!r}")
    context = multiprocessing.get_context("spawn")
    threads = max(1, usable_cores() // int(max_workers))
    return RespawningPool(functools.partial(
        _spawned_pool, max_workers=int(max_workers), context=context, threads=threads,
        parent_pid=os.getpid()), new_counter=functools.partial(context.Value, "q", 0),
        code=loop_code_digest())


def _spawned_pool(counter, *, max_workers: int, context, threads: int, parent_pid: int):
    """`default_executor`'s process pool whose workers count their rows into
    ``counter``."""
    return cf.ProcessPoolExecutor(
        max_workers=max_workers, mp_context=context, initializer=exec,
        initargs=(_WORKER_START, {"counter": counter, "threads": threads,
                                  "parent_pid": parent_pid, "interval": 0.1}))


def _subsystem(diagram, name):
    if not diagram.HasSubsystemNamed(name):
        names = sorted(s.get_name() for s in diagram.GetSystems())
        raise ValueError(f"the diagram '{diagram.get_name()}' has no subsystem '{name}'; "
                         f"it has {names}")
    return diagram.GetSubsystemByName(name)


class _DiagramProbe:
    def __init__(self, factory, probe: Probe, state_dim: int):
        self.diagram = factory()
        self.context = self.diagram.CreateDefaultContext()
        plant = _subsystem(self.diagram, probe.plant)
        self.plant_context = plant.GetMyMutableContextFromRoot(self.context)
        size = self.plant_context.num_continuous_states()
        if size != state_dim:
            raise ValueError(f"probe.plant '{probe.plant}' has {size} continuous states, the "
                             f"grid {state_dim} axes")
        self.ports = []
        for name in probe.ports:
            system_name, _, port_name = name.partition(".")
            system = _subsystem(self.diagram, system_name)
            if not system.HasOutputPort(port_name):
                ports = [system.get_output_port(i).get_name()
                         for i in range(system.num_output_ports())]
                raise ValueError(f"subsystem '{system_name}' has no output port "
                                 f"'{port_name}'; it has {ports}")
            port = system.GetOutputPort(port_name)
            self.ports.append((port, system.GetMyContextFromRoot(self.context)))
        self.lock = threading.Lock()

    def evaluate(self, states):
        with self.lock:
            out = [np.empty((len(states), port.size())) for port, _ in self.ports]
            for i, x in enumerate(states):
                self.plant_context.SetContinuousState(x)
                for k, (port, ctx) in enumerate(self.ports):
                    out[k][i] = port.Eval(ctx)
                row_done()
            return out


#: Per worker *thread*: probe key -> `_DiagramProbe`, built by the thread that uses it.
#: A Drake Context is not thread-safe, and a VTK/EGL render context works only on the
#: thread that created it (on any other, eglMakeCurrent fails and the camera returns a
#: stale or blank image: wrong steering, no error), so a worker that runs several
#: threads (``dask worker`` runs one per core) gives each its own diagram.
_PROBES = ThreadKept(KEPT_DIAGRAMS)


def probe_key(factory, probe: Probe, fallback: str = None) -> str:
    """What a worker thread keeps one diagram for: the factory and probe's content
    fingerprint, whatever grid they sweep (a sweep, its refinement and other grids of
    the same loop share it); when they cannot be fingerprinted, ``fallback`` (e.g. a
    sweep's given key) with a suffix of its own to this call, so that another sweep
    under the same key, from another closure, never runs this one's diagram; without
    ``fallback``, `Unfingerprintable` is raised."""
    try:
        return f"states_{fingerprint(factory, probe)[:20]}"
    except Unfingerprintable:
        if fallback is None:
            raise
        return f"{fallback}_{uuid.uuid4().hex[:12]}"


def _thread_probe(factory, probe: Probe, key: str, state_dim: int) -> "_DiagramProbe":
    """This thread's `_DiagramProbe` for ``key``, built on first use; the thread keeps
    the `KEPT_DIAGRAMS` most recently used."""
    # the diagram checks the grid's dimension once
    return _PROBES.get((key, int(state_dim)), lambda: _DiagramProbe(factory, probe, state_dim))


def run_chunk(factory, probe: Probe, key: str, grid: Grid, start: int, stop: int) -> dict:
    """The chunk of nodes ``start:stop`` (flat C order): its arrays, which the driver
    writes (a worker needs no filesystem shared with it)."""
    arrays = _thread_probe(factory, probe, key, grid.ndim).evaluate(
        grid.states(np.arange(start, stop)))
    return {"start": np.asarray(start), "stop": np.asarray(stop),
            **{f"port{k}": np.asarray(a) for k, a in enumerate(arrays)}}


def evaluate_states(factory, probe: Probe, key: str, states) -> dict:
    """``probe.ports`` at each of ``states`` ``(n, ndim)`` as ``{"port0": (n, size),
    ...}`` (in ``probe.ports`` order); the diagram is built once per worker thread and
    ``key``. For `reach.outcomes.map_states` (cached, chunked, on any executor)."""
    states = np.asarray(states, float)
    arrays = _thread_probe(factory, probe, key, states.shape[1]).evaluate(states)
    return {f"port{k}": a for k, a in enumerate(arrays)}


@dc.dataclass
class SweepTable:
    """Port values at every grid node: ``tables[port]`` shaped ``grid.shape + (size,)``."""
    grid: Grid
    tables: dict
    key: str
    computed: int = 0       # states evaluated by the call that returned it (0: all cached)
    #: Nodes whose values were evaluated in the diagram (``None``: all of them); the
    #: others were interpolated from a coarser table (`reach.refine`).
    rendered: np.ndarray = None

    def __getitem__(self, port):
        return self.tables[port]


def _fits(ports: int):
    """Whether a chunk file covers its chunk's rows with every port's (it is used only
    then, and when its arrays match the checksum they were written with)."""
    def fits(chunk, arrays) -> bool:
        return (int(arrays["start"]) == chunk.start and int(arrays["stop"]) == chunk.stop
                and all(len(arrays[f"port{k}"]) == chunk.rows for k in range(ports)))
    return fits


def cached_table_digest(cache_dir, key: str, size: int):
    """SHA-256 (hex) of the content of the sweep ``key`` as cached under ``cache_dir``
    now: every chunk's `chunk_checksum`, in order. None unless its chunks cover the
    ``size`` nodes one after another and each matches the checksum stored with it.
    What a stage that reads the table keys on (an edited table is read again, not the
    result made from the old one adopted), found without evaluating anything.
    ``cache_dir``: a local folder or an fsspec URL, as `sweep` takes."""
    folder, digest, stop, index = cache_join(cache_dir, key), hashlib.sha256(), 0, 0
    while stop < size:
        try:
            arrays = read_chunk_file(chunk_path(folder, index))
            start, end = int(arrays["start"]), int(arrays["stop"])
        except Exception:      # missing, truncated or not a chunk
            return None
        if start != stop or end <= start or not checksum_ok(arrays):
            return None
        digest.update(chunk_checksum(arrays).encode())
        stop, index = end, index + 1
    return digest.hexdigest() if stop == size else None


def cached_chunk_size(folder, size: int, tries: int = 3):
    """The states per chunk of the sweep cached in ``folder``, read off the first whole,
    checked chunk among its first ``tries`` (chunk ``i`` of ``n`` states starts at
    ``i * n`` and, unless it is the last, holds ``n``), for a sweep of ``size`` states;
    None when none says (a chunk size read off a damaged file only chunks the sweep
    otherwise: every chunk is checked when read). A table does not depend on how it was
    chunked, so a sweep asked
    for another chunk size goes on in the cache's (files named by their index would
    otherwise hold other rows, and each sweep would take the other's for damaged and
    compute them again)."""
    for index in range(tries):
        try:            # its rows alone: the store checks every chunk whole when it reads it
            arrays = read_chunk_file(chunk_path(folder, index), ("start", "stop"))
            start, stop = int(arrays["start"]), int(arrays["stop"])
        except Exception:      # none, or damaged: the next may say
            continue
        if not 0 <= start < stop <= size:
            continue
        if index == 0:
            return stop
        if start % index == 0 and (stop - start == start // index or stop == size):
            return start // index
    return None


def sweep_key(factory: Callable, grid: Grid, probe: Probe, *, name: str = None) -> str:
    """The cache folder name of a sweep: ``name`` (default: the factory's function
    name), the grid shape, and the first 20 hex digits of the content fingerprint of
    factory, grid and probe (`reach.fingerprint`)."""
    base = getattr(factory, "func", factory)
    name = name or getattr(base, "__name__", "sweep")
    return f"{name}_{'x'.join(map(str, grid.shape))}_{fingerprint(factory, grid.key(), probe)[:20]}"


def _check_fingerprint(folder, factory, grid, probe, key):
    """Records what a user-keyed cache folder was filled from, and refuses to reuse it
    for anything else; returns the fingerprint (None when it cannot be taken)."""
    try:
        mine = fingerprint(factory, grid.key(), probe)
    except Unfingerprintable as e:
        warnings.warn(f"sweep key '{key}' cannot be checked against its cache ({e}); a "
                      f"changed controller under the same key would reuse a stale table")
        mine = None
    path = cache_join(folder, "fingerprint.json")
    try:
        recorded = read_location(path)
    except OSError:                       # none yet (or unreadable: written again below)
        recorded = None
    if recorded is not None:
        try:
            theirs = json.loads(recorded).get("fingerprint")
        except (ValueError, AttributeError):
            raise ValueError(f"sweep key '{key}': the cache's fingerprint.json ({path}) is not "
                             f"readable, so its tables cannot be checked against this sweep; "
                             f"delete {folder}, or use another key") from None
        if mine is not None and theirs is not None and theirs != mine:
            raise ValueError(f"sweep key '{key}' names a cache ({folder}) filled from another "
                             f"factory, grid or probe (fingerprint {theirs[:12]}, this sweep "
                             f"{mine[:12]}); use another key, or key=None to derive one")
    if mine is not None and recorded is None:
        write_location(path, json.dumps({"fingerprint": mine}).encode())
    return mine


def sweep(factory: Callable, grid: Grid, *, probe: Probe, cache_dir, key: str = None,
          chunk_size: int = 1024, executor: cf.Executor = None, progress: bool = True,
          max_in_flight: int = None, label: str = None, name: str = None) -> SweepTable:
    """Evaluate ``probe.ports`` of ``factory()``'s diagram at every node of ``grid``.

    ``factory`` must be picklable when ``executor`` runs elsewhere (e.g.
    ``functools.partial(make_closed_loop_diagram, scenario)``). The cache folder
    under ``cache_dir`` is `sweep_key` of its content fingerprint, so a changed
    controller, gain or checkpoint never returns a stale table; a ``key`` you give
    names the folder instead, and is checked against the fingerprint recorded in it
    (``name`` starts a derived key; default: the factory's function name).
    Each chunk's arrays come back to this process, which writes the cache (workers need
    no filesystem shared with it); at most ``max_in_flight`` chunks are in flight
    (default: `in_flight`, twice the executor's threads, at least 8).
    The progress bar (``label``, default the key) moves per state on this process and
    on `default_executor`, per chunk on others. ``table.computed`` counts the states
    evaluated by this call (0 when every chunk was cached). ``cache_dir`` is a local
    folder or an fsspec URL (``memory://...``, ``s3://bucket/sweeps`` with s3fs): only
    this process reads and writes it."""
    if isinstance(chunk_size, bool) or not isinstance(chunk_size, (int, np.integer)) or chunk_size < 1:
        raise ValueError(f"chunk_size must be a whole number >= 1, got {chunk_size!r}")
    if len(probe.ports) < 1:
        raise ValueError("the probe names no port to read")
    checked, key = key is not None, key or sweep_key(factory, grid, probe, name=name)
    base = cache_location(cache_dir)
    local = isinstance(base, Path)
    folder = cache_join(base.absolute() if local else base, key)
    make_folder(folder)
    stamp = None
    if checked:            # a derived key is the fingerprint; a given one must match it
        mine = _check_fingerprint(folder, factory, grid, probe, key)
        # in each chunk too: two sweeps given one key at once, both before either wrote
        # fingerprint.json, would else each read the other's chunks
        stamp = {"_fingerprint": mine} if mine is not None else None
    cached = cached_chunk_size(folder, grid.size)
    if cached is not None and cached != chunk_size:
        _log.info("sweep %s: its cache holds chunks of %d states; it goes on in them (asked: "
                  "%d; delete the folder to chunk it otherwise)", key, cached, chunk_size)
    chunk_size = cached or chunk_size
    chunks, nports = split(grid.size, chunk_size), len(probe.ports)
    # Local chunks are loaded again at the end (memory stays one table); a URL's are
    # kept as read or stored, so no object is downloaded twice (but the first, read once
    # more above for its size).
    store = FolderStore(folder, _fits(nports), keep=not local, stamp=stamp)
    diagram_key = probe_key(factory, probe, key)
    ran = run_chunks(
        run_chunk, chunks, store,
        args=lambda c: (factory, probe, diagram_key, grid, c.start, c.stop),
        executor=executor, default=default_executor, per_row=True,
        bar=functools.partial(tqdm, total=grid.size, unit="state",
                              desc=f"sweep {label or key}", disable=not progress),
        max_in_flight=max_in_flight, least=8, caller="sweep")
    computed = sum(c.rows for c in ran)
    tables = None
    names = [f"port{k}" for k in range(nports)]
    for chunk in chunks:
        kept = store.read(chunk)        # checked again: another writer may have replaced it
        if kept is None:
            raise WorkerLost(f"chunk {chunk.index} of {key} did not finish (its file is "
                             f"missing or damaged after its worker stored it); a re-run "
                             f"computes it again")
        arrays = [kept[name] for name in names]
        if tables is None:
            tables = [np.empty((grid.size, a.shape[1])) for a in arrays]
        for table, a in zip(tables, arrays):
            table[chunk.start:chunk.stop] = a
    return SweepTable(grid=grid, key=key, computed=computed, tables={
        name: t.reshape(grid.shape + (t.shape[1],)) for name, t in zip(probe.ports, tables)})
