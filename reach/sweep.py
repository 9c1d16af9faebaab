"""Sweep a closed-loop diagram over a grid: set the plant state in a reused Context
and evaluate the control output port (and any others) at every node.

Works for any diagram: name the subsystem whose continuous state is the grid state
and the ports to read (``"system.port"``). Chunked; each finished chunk is written
atomically under ``cache_dir/key/``, so a killed sweep resumes and a repeated one
costs nothing. Chunks run on any `concurrent.futures.Executor`."""

import concurrent.futures as cf
import concurrent.futures.process  # noqa: F401  (BrokenProcessPool)
import dataclasses as dc
import io
import multiprocessing
import threading
from pathlib import Path
from typing import Callable, Tuple

import numpy as np
from tqdm import tqdm

from reachwatch.systems.files import atomic_write_bytes

from .grid import Grid


@dc.dataclass(frozen=True)
class Probe:
    """Where to write the state and what to read in a diagram."""
    plant: str = "taxi_plant"
    control_port: str = "p_controller.steering_angle"
    extra_ports: Tuple[str, ...] = ("taxinet.estimate",)

    @property
    def ports(self):
        return (self.control_port,) + tuple(self.extra_ports)


class InlineExecutor(cf.Executor):
    """Runs each task at submit time in this process (small sweeps, tests)."""

    def submit(self, fn, /, *args, **kwargs):
        future = cf.Future()
        try:
            future.set_result(fn(*args, **kwargs))
        except BaseException as e:  # delivered through the future, like a pool would
            future.set_exception(e)
        return future


def default_executor() -> cf.Executor:
    """One spawned worker: it builds the diagram once (a second process adds nothing
    to CPU rendering, which already uses every core)."""
    return cf.ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"))


class _DiagramProbe:
    def __init__(self, factory, probe: Probe):
        self.diagram = factory()
        self.context = self.diagram.CreateDefaultContext()
        plant = self.diagram.GetSubsystemByName(probe.plant)
        self.plant_context = plant.GetMyMutableContextFromRoot(self.context)
        self.ports = []
        for name in probe.ports:
            system_name, port_name = name.split(".", 1)
            system = self.diagram.GetSubsystemByName(system_name)
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
            return out


_PROBES = {}     # per worker process: key -> _DiagramProbe, built once


def _chunk_path(folder: Path, index: int) -> Path:
    return folder / f"chunk_{index:06d}.npz"


def run_chunk(factory, probe: Probe, key: str, grid: Grid, index: int, start: int,
              stop: int, folder: str) -> str:
    """Evaluate nodes ``start:stop`` (flat C order) and write the chunk file."""
    if key not in _PROBES:
        _PROBES[key] = _DiagramProbe(factory, probe)
    arrays = _PROBES[key].evaluate(grid.states(np.arange(start, stop)))
    buffer = io.BytesIO()
    np.savez(buffer, start=start, stop=stop, **{f"port{k}": a for k, a in enumerate(arrays)})
    return str(atomic_write_bytes(_chunk_path(Path(folder), index), buffer.getvalue()))


@dc.dataclass
class SweepTable:
    """Port values at every grid node: ``tables[port]`` shaped ``grid.shape + (size,)``."""
    grid: Grid
    tables: dict
    key: str

    def __getitem__(self, port):
        return self.tables[port]


def _chunk_ok(path: Path, start: int, stop: int) -> bool:
    try:
        with np.load(path) as data:
            return int(data["start"]) == start and int(data["stop"]) == stop
    except Exception:   # truncated/corrupt: recompute it
        return False


def sweep(factory: Callable, grid: Grid, *, key: str, cache_dir, probe: Probe = Probe(),
          chunk_size: int = 1024, executor: cf.Executor = None, progress: bool = True,
          max_in_flight: int = 8) -> SweepTable:
    """Evaluate ``probe.ports`` of ``factory()``'s diagram at every node of ``grid``.

    ``factory`` must be picklable when ``executor`` runs elsewhere (e.g.
    ``functools.partial(make_closed_loop_diagram, scenario)``); ``key`` names the
    cache entry and must change whenever the diagram's output could."""
    folder = Path(cache_dir) / key
    folder.mkdir(parents=True, exist_ok=True)
    bounds = [(i, s, min(s + chunk_size, grid.size))
              for i, s in enumerate(range(0, grid.size, chunk_size))]
    todo = [b for b in bounds if not _chunk_ok(_chunk_path(folder, b[0]), b[1], b[2])]
    bar = tqdm(total=grid.size, initial=grid.size - sum(b[2] - b[1] for b in todo),
               desc=f"sweep {key[:24]}", unit="state", disable=not progress)
    owned = executor is None and todo
    executor = executor or (default_executor() if todo else None)
    pending = {}

    def finish(done):
        for future in done:
            future.result()                      # re-raises a worker's error
            s, e = pending.pop(future)
            bar.update(e - s)

    try:   # a bounded window of chunks in flight: progress shows, an abort stops soon
        for i, s, e in todo:
            pending[executor.submit(run_chunk, factory, probe, key, grid, i, s, e,
                                    str(folder))] = (s, e)
            finish([f for f in pending if f.done()])
            if len(pending) >= max_in_flight:
                finish(cf.wait(pending, return_when=cf.FIRST_COMPLETED).done)
        finish(list(cf.as_completed(list(pending))))
    except cf.process.BrokenProcessPool as e:
        raise RuntimeError(
            "a sweep worker process died; finished chunks are kept and a re-run resumes. "
            "Workers are spawned: a script calling sweep must guard its top level with "
            "`if __name__ == '__main__':` (or pass executor=InlineExecutor())") from e
    finally:
        bar.close()
        if owned:
            executor.shutdown(cancel_futures=True)
    tables = None
    for i, s, e in bounds:
        with np.load(_chunk_path(folder, i)) as data:
            arrays = [data[f"port{k}"] for k in range(len(probe.ports))]
        if tables is None:
            tables = [np.empty((grid.size, a.shape[1])) for a in arrays]
        for table, a in zip(tables, arrays):
            table[s:e] = a
    return SweepTable(grid=grid, key=key, tables={
        name: t.reshape(grid.shape + (t.shape[1],)) for name, t in zip(probe.ports, tables)})
