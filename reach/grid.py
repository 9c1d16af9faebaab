"""A regular N-dimensional state grid with multilinear interpolation."""

import numpy as np

#: What a query does with a state outside the grid box.
OUTSIDE_MODES = ("raise", "clamp", "nan")


def check_states(states, dim: int, what: str = "state") -> np.ndarray:
    """``states`` as a float array ``(..., dim)``; raises ValueError naming the first
    non-finite state or a wrong trailing size."""
    states = np.asarray(states, dtype=float)
    if states.ndim == 0 or states.shape[-1] != dim:
        raise ValueError(f"{what}s must be shaped (..., {dim}), got {states.shape}")
    flat = states.reshape(-1, dim)
    bad = ~np.all(np.isfinite(flat), axis=-1)
    if bad.any():
        raise ValueError(f"{what} {flat[np.argmax(bad)].tolist()} is not finite "
                         f"({int(bad.sum())} of {len(flat)} such)")
    return states


class Grid:
    """Nodes ``lo + i * spacing`` for ``i`` in ``range(shape)`` per axis (ends included),
    in any number of dimensions. ``names`` label the axes in messages (default
    ``x0, x1, ...``); they are not part of the grid's identity."""

    def __init__(self, *, lo, hi, shape, names=None):
        lo, hi = np.atleast_1d(np.asarray(lo, dtype=float)), np.atleast_1d(np.asarray(hi, dtype=float))
        shape = tuple(int(n) for n in np.atleast_1d(shape))
        names = tuple(names) if names is not None else tuple(f"x{k}" for k in range(len(shape)))
        if lo.ndim != 1 or not (len(lo) == len(hi) == len(shape) == len(names)) or not shape:
            raise ValueError(f"a grid needs as many lower bounds, upper bounds, sizes and names "
                             f"as it has axes, got lo {lo.tolist()}, hi {hi.tolist()}, shape "
                             f"{list(shape)}, names {list(names)}")
        for axis, a, b, n in zip(names, lo, hi, shape):
            if not (np.isfinite(a) and np.isfinite(b) and a < b):
                raise ValueError(f"grid axis {axis}: lower bound {a} must be finite and below "
                                 f"the upper bound {b}")
            if n < 2:
                raise ValueError(f"grid axis {axis}: needs at least 2 nodes, got {n}")
        self.lo, self.hi, self.shape, self.names = lo, hi, shape, names

    @property
    def ndim(self) -> int:
        return len(self.shape)

    def __eq__(self, other):
        return (isinstance(other, Grid) and self.shape == other.shape
                and np.array_equal(self.lo, other.lo) and np.array_equal(self.hi, other.hi))

    def __repr__(self):
        return (f"Grid(lo={self.lo.tolist()}, hi={self.hi.tolist()}, shape={list(self.shape)})")

    def key(self) -> str:
        """A stable text id (for cache keys)."""
        return repr(self)

    def __fingerprint__(self):
        return self.key()

    @property
    def spacing(self) -> np.ndarray:
        return (self.hi - self.lo) / (np.asarray(self.shape) - 1)

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))

    @property
    def axes(self):
        """The node coordinates of each axis."""
        return [np.linspace(a, b, n) for a, b, n in zip(self.lo, self.hi, self.shape)]

    def states(self, flat_indices=None) -> np.ndarray:
        """``(N, ndim)`` node states in C order (all nodes, or the given flat indices)."""
        if flat_indices is None:
            flat_indices = np.arange(self.size)
        idx = np.stack(np.unravel_index(np.asarray(flat_indices), self.shape), axis=-1)
        return self.lo + idx * self.spacing

    def mesh(self):
        """Per-axis coordinate arrays of shape ``self.shape`` (``indexing='ij'``)."""
        return np.meshgrid(*self.axes, indexing="ij")

    def contains(self, states, atol=1e-9) -> np.ndarray:
        states = np.asarray(states, dtype=float).reshape(-1, self.ndim)
        return np.all((states >= self.lo - atol) & (states <= self.hi + atol), axis=-1)

    def describe(self, state) -> str:
        """``state`` and the box, in words (for error messages)."""
        return (f"state [{', '.join(f'{n}={v:.4g}' for n, v in zip(self.names, state))}] is "
                f"outside the grid " + ", ".join(f"{n} [{a:g}, {b:g}]" for n, a, b in
                                                 zip(self.names, self.lo, self.hi)))

    def interpolate(self, values: np.ndarray, states, *, outside="raise") -> np.ndarray:
        """Multilinear interpolation of node ``values`` (shape ``self.shape`` + trailing)
        at ``states`` ``(..., ndim)``. ``outside``: ``raise`` (naming the state),
        ``clamp`` to the box, or ``nan``. A non-finite state is always an error."""
        if outside not in OUTSIDE_MODES:
            raise ValueError(f"outside must be one of {OUTSIDE_MODES}, got {outside!r}")
        values = np.asarray(values)
        if values.shape[:self.ndim] != self.shape:
            raise ValueError(f"values shaped {values.shape} do not match grid {self.shape}")
        states = check_states(states, self.ndim)
        flat = states.reshape(-1, self.ndim)
        inside = self.contains(flat)
        if outside == "raise" and not inside.all():
            raise ValueError(self.describe(flat[np.argmin(inside)]))
        u = (np.clip(flat, self.lo, self.hi) - self.lo) / self.spacing
        i0 = np.clip(np.floor(u).astype(int), 0, np.asarray(self.shape) - 2)
        w = u - i0
        out = 0.0
        for corner in range(2 ** self.ndim):
            bits = [(corner >> k) & 1 for k in range(self.ndim)]
            weight = np.prod([w[:, k] if b else 1.0 - w[:, k] for k, b in enumerate(bits)], axis=0)
            node = values[tuple(i0[:, k] + b for k, b in enumerate(bits))]
            out = out + weight.reshape((-1,) + (1,) * (node.ndim - 1)) * node
        out = np.asarray(out, dtype=float)
        if outside == "nan":
            out[~inside] = np.nan
        return out.reshape(states.shape[:-1] + values.shape[self.ndim:])
