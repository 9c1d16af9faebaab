"""Bounds on a swept output between its nodes, for robust BRTs.

A swept table knows the controller's output at its nodes only; between them the solver
interpolates, and a vision controller's output there can be anything (at night an
estimate from the camera can jump from state to state). `local_range` bounds it by the
range the output takes around each node, where that range is wide; `solve_brt` with
``control_bounds`` then solves for the worst output within the bounds."""

import numpy as np
from scipy.ndimage import maximum_filter, minimum_filter

from .grid import Grid


def local_range(grid: Grid, table, *, size: int = 3, min_spread: float = 0.0):
    """``(lo, hi)`` per node of ``grid``: the minimum and maximum of ``table`` (shaped
    ``grid.shape`` or ``grid.shape + (m,)``, per component) over the ``size``-wide
    neighbourhood of nodes centred on it (fewer at the box's faces). Where no component
    ranges over more than ``min_spread`` there, both equal the table: the output varies
    slowly and its interpolation is trusted."""
    table = np.asarray(table, float)
    if table.shape[:grid.ndim] != grid.shape or table.ndim > grid.ndim + 1:
        raise ValueError(f"table shaped {table.shape} does not match the grid {grid.shape} "
                         f"(give grid.shape or grid.shape + (m,))")
    if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or size < 3 \
            or size % 2 == 0:
        raise ValueError(f"size must be an odd whole number of nodes >= 3 (a neighbourhood "
                         f"centred on the node), got {size!r}")
    if not (np.isfinite(min_spread) and min_spread >= 0):
        raise ValueError(f"min_spread must be a finite number >= 0, got {min_spread!r}")
    window = (size,) * grid.ndim + (1,) * (table.ndim - grid.ndim)
    lo = minimum_filter(table, size=window, mode="nearest")
    hi = maximum_filter(table, size=window, mode="nearest")
    spread = (hi - lo).reshape(grid.shape + (-1,)).max(axis=-1)
    wide = (spread > min_spread).reshape(grid.shape + (1,) * (table.ndim - grid.ndim))
    return np.where(wide, lo, table), np.where(wide, hi, table)


def control_bounds(table, port: str, min_spread_deg, *, neighbourhood: int = 3):
    """``control_bounds`` for a robust `solve_brt` of a swept ``table`` (a `SweepTable`):
    the `local_range` of its control output ``port`` (rad) where that ranges over more
    than ``min_spread_deg`` across a node's ``neighbourhood``; None (a nominal solve)
    when ``min_spread_deg`` is None."""
    if min_spread_deg is None:
        return None
    return local_range(table.grid, table[port], size=neighbourhood,
                       min_spread=np.deg2rad(min_spread_deg))
