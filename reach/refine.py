"""Adaptive refinement of a swept table: evaluate the diagram at new nodes only where
the BRT's verdict is uncertain or the swept output varies fast, and interpolate the
coarse table everywhere else.

Each level halves the spacing (`finer_grid`): the old nodes are nodes of the new
grid, so nothing is evaluated twice. `uncertain_cells` picks the cells to refine
from the value function (its zero level set passes within ``band``) and from the
swept output (its range over a cell's corners exceeds ``variation``); the new nodes
of those cells are evaluated with `reach.outcomes.map_states`, so a refinement is
chunked, cached by content, resumable after a kill and runs on any executor. The
table's ``rendered`` mask says which nodes were evaluated. `refine_adaptively` runs
the levels with any solver."""

import dataclasses as dc
import functools
import hashlib
import itertools
from typing import Callable, List

import numpy as np

from .grid import Grid
from .outcomes import map_states
from .sweep import Probe, SweepTable, evaluate_states, probe_key


def finer_grid(grid: Grid, factor: int = 2) -> Grid:
    """The same box with ``factor`` times as many intervals per axis (``(n - 1) *
    factor + 1`` nodes): every node of ``grid`` is a node of the result."""
    if isinstance(factor, bool) or not isinstance(factor, (int, np.integer)) or factor < 2:
        raise ValueError(f"the refinement factor must be a whole number >= 2, got {factor!r}")
    return Grid(lo=grid.lo, hi=grid.hi, shape=[(n - 1) * factor + 1 for n in grid.shape],
                names=grid.names)


def cell_range(values: np.ndarray, ndim: int):
    """Per cell of a grid with node ``values`` (``shape`` + trailing): the minimum and
    maximum over the cell's ``2**ndim`` corners, each shaped ``(n - 1 per axis)`` +
    trailing."""
    values = np.asarray(values, float)
    lo = hi = None
    for corner in itertools.product((0, 1), repeat=ndim):
        part = values[tuple(slice(b, n - 1 + b) for b, n in zip(corner, values.shape[:ndim]))]
        lo = part if lo is None else np.minimum(lo, part)
        hi = part if hi is None else np.maximum(hi, part)
    return lo, hi


def uncertain_cells(grid: Grid, values, *, band: float, output=None,
                    variation: float = None) -> np.ndarray:
    """Cells (boolean, ``n - 1`` per axis) to refine: those whose corner values of
    ``values`` come within ``band`` of zero from both sides (the BRT's boundary may pass
    through them, give or take ``band``), and, with ``output`` (node values, ``shape`` +
    trailing) and ``variation``, those where any output component ranges over more
    than ``variation`` across the corners (interpolating it there is least
    trustworthy)."""
    values = np.asarray(values, float)
    if values.shape != grid.shape:
        raise ValueError(f"values shaped {values.shape} do not match the grid {grid.shape}")
    if not np.isfinite(band) or band < 0:
        raise ValueError(f"band must be a finite number >= 0, got {band!r}")
    lo, hi = cell_range(values, grid.ndim)
    cells = (lo <= band) & (hi >= -band)
    if variation is not None:
        if output is None:
            raise ValueError("variation needs the output table it measures")
        output = np.asarray(output, float)
        if output.shape[:grid.ndim] != grid.shape:
            raise ValueError(f"output shaped {output.shape} does not match the grid {grid.shape}")
        olo, ohi = cell_range(output, grid.ndim)
        spread = (ohi - olo).reshape(cells.shape + (-1,)).max(axis=-1)
        cells |= spread > variation
    return cells


def cell_nodes(cells: np.ndarray, factor: int = 2) -> np.ndarray:
    """The nodes of `finer_grid` (boolean) lying in the closed ``cells``."""
    cells = np.asarray(cells, bool)
    shape = tuple((n * factor) + 1 for n in cells.shape)
    nodes = np.zeros(shape, bool)
    for offset in itertools.product(range(factor + 1), repeat=cells.ndim):
        nodes[tuple(slice(o, o + (n - 1) * factor + 1, factor)
                    for o, n in zip(offset, cells.shape))] |= cells
    return nodes


def refine_table(factory: Callable, table: SweepTable, cells, *, probe: Probe, cache_dir,
                 factor: int = 2, chunk_size: int = 256, executor=None,
                 progress: bool = True, label: str = None) -> SweepTable:
    """``table`` on `finer_grid`: the diagram is evaluated at the nodes of ``cells``
    not evaluated before (``table.rendered``), every other node is interpolated from
    ``table``. ``factory`` and ``probe`` are the sweep's. ``computed`` counts the
    evaluations this call made (0 when cached)."""
    grid = table.grid
    cells = np.asarray(cells, bool)
    if cells.shape != tuple(n - 1 for n in grid.shape):
        raise ValueError(f"cells shaped {cells.shape} do not match the grid {grid.shape} "
                         f"(one per interval: {tuple(n - 1 for n in grid.shape)})")
    fine = finer_grid(grid, factor)
    states = fine.states()
    tables = {port: grid.interpolate(values, states).reshape(fine.shape + values.shape[grid.ndim:])
              for port, values in table.tables.items()}
    rendered = np.zeros(fine.shape, bool)
    rendered[tuple(slice(None, None, factor) for _ in grid.shape)] = (
        True if table.rendered is None else table.rendered)
    todo = np.flatnonzero(cell_nodes(cells, factor) & ~rendered)
    digest = hashlib.sha256(np.packbits(cells).tobytes() + str(cells.shape).encode()).hexdigest()[:10]
    key = f"{table.key}_x{factor}_{digest}"
    computed = 0
    if len(todo):
        fields, _, computed = map_states(
            functools.partial(evaluate_states, factory, probe,
                              probe_key(factory, probe)), states[todo],
            cache_dir=cache_dir, chunk_size=chunk_size, executor=executor, progress=progress,
            label=f"refine {label or table.key}", required=tuple(
                f"port{k}" for k in range(len(probe.ports))))
        for k, port in enumerate(probe.ports):
            flat = tables[port].reshape(fine.size, -1)
            flat[todo] = fields[f"port{k}"]
        rendered.flat[todo] = True
    return SweepTable(grid=fine, tables=tables, key=key, computed=computed, rendered=rendered)


@dc.dataclass
class RefineLevel:
    """One level of `refine_adaptively`: its table, the solver's result on it, and the
    cells of the previous level that were refined into it (``None`` at level 0)."""
    table: SweepTable
    solution: object
    cells: np.ndarray = None

    @property
    def rendered(self) -> int:
        """Nodes evaluated in the diagram up to this level."""
        return int(self.table.grid.size if self.table.rendered is None
                   else self.table.rendered.sum())


def refine_adaptively(factory: Callable, table: SweepTable, *, probe: Probe, solve: Callable,
                      values: Callable = None, levels: int, band: float,
                      variation: float = None, cache_dir, factor: int = 2,
                      chunk_size: int = 256, executor=None, progress: bool = True,
                      label: str = None) -> List[RefineLevel]:
    """Solve on ``table``, then ``levels`` times: refine the `uncertain_cells` of the
    last solution (``band``, and ``variation`` of ``probe.control_port``'s output) and
    solve again. ``solve(table)`` returns anything; ``values(solution)`` its node
    values (default: ``solution.values``). Returns every level, coarsest first."""
    if isinstance(levels, bool) or not isinstance(levels, (int, np.integer)) or levels < 0:
        raise ValueError(f"levels must be a whole number >= 0, got {levels!r}")
    values = values or (lambda solution: solution.values)
    out = [RefineLevel(table=table, solution=solve(table))]
    for level in range(levels):
        last = out[-1]
        cells = uncertain_cells(last.table.grid, values(last.solution), band=band,
                                output=last.table[probe.control_port], variation=variation)
        finer = refine_table(factory, last.table, cells, probe=probe, cache_dir=cache_dir,
                             factor=factor, chunk_size=chunk_size, executor=executor,
                             progress=progress, label=f"{label or table.key} level {level + 1}")
        out.append(RefineLevel(table=finer, solution=solve(finer), cells=cells))
    return out
