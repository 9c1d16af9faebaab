"""A regular state grid over [px m, py m, theta rad], with multilinear interpolation."""

import dataclasses as dc
from typing import List

import numpy as np

AXES = ("px", "py", "theta")


@dc.dataclass
class GridSpec:
    """A grid as configs write it (theta in degrees)."""
    px: List[float] = dc.field(default_factory=lambda: [-11.0, 11.0])
    py: List[float] = dc.field(default_factory=lambda: [100.0, 250.0])
    theta_deg: List[float] = dc.field(default_factory=lambda: [-28.0, 28.0])
    shape: List[int] = dc.field(default_factory=lambda: [101, 101, 101])

    def to_grid(self) -> "Grid":
        return Grid(lo=[self.px[0], self.py[0], np.deg2rad(self.theta_deg[0])],
                    hi=[self.px[1], self.py[1], np.deg2rad(self.theta_deg[1])],
                    shape=self.shape)


class Grid:
    """Nodes ``lo + i * spacing`` for ``i`` in ``range(shape)`` per axis (ends included).

    ``lo``/``hi`` in state units [px m, py m, theta rad]."""

    def __init__(self, *, lo, hi, shape):
        lo, hi = np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)
        shape = tuple(int(n) for n in np.atleast_1d(shape))
        if lo.shape != (3,) or hi.shape != (3,) or len(shape) != 3:
            raise ValueError(f"a grid needs 3 lower bounds, 3 upper bounds and 3 sizes "
                             f"({', '.join(AXES)}), got {lo.tolist()}, {hi.tolist()}, {shape}")
        for axis, a, b, n in zip(AXES, lo, hi, shape):
            if not (np.isfinite(a) and np.isfinite(b) and a < b):
                raise ValueError(f"grid axis {axis}: lower bound {a} must be finite and below "
                                 f"the upper bound {b}")
            if n < 2:
                raise ValueError(f"grid axis {axis}: needs at least 2 nodes, got {n}")
        self.lo, self.hi, self.shape = lo, hi, shape

    @classmethod
    def paper(cls, half_width: float, shape=(101, 101, 101)) -> "Grid":
        """The paper's grid: px in [-(B+1), B+1] m, py in [100, 250] m, theta in
        [-28, 28] deg."""
        return cls(lo=[-(half_width + 1.0), 100.0, np.deg2rad(-28.0)],
                   hi=[half_width + 1.0, 250.0, np.deg2rad(28.0)], shape=shape)

    def __eq__(self, other):
        return (isinstance(other, Grid) and self.shape == other.shape
                and np.array_equal(self.lo, other.lo) and np.array_equal(self.hi, other.hi))

    def __repr__(self):
        return (f"Grid(lo={self.lo.tolist()}, hi={self.hi.tolist()}, shape={list(self.shape)})")

    def key(self) -> str:
        """A stable text id (for cache keys)."""
        return repr(self)

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
        """``(N, 3)`` node states in C order (all nodes, or the given flat indices)."""
        if flat_indices is None:
            flat_indices = np.arange(self.size)
        idx = np.stack(np.unravel_index(np.asarray(flat_indices), self.shape), axis=-1)
        return self.lo + idx * self.spacing

    def mesh(self):
        """Per-axis coordinate arrays of shape ``self.shape`` (``indexing='ij'``)."""
        return np.meshgrid(*self.axes, indexing="ij")

    def contains(self, states, atol=1e-9) -> np.ndarray:
        states = np.atleast_2d(states)
        return np.all((states >= self.lo - atol) & (states <= self.hi + atol), axis=-1)

    def interpolate(self, values: np.ndarray, states, *, outside="raise") -> np.ndarray:
        """Multilinear interpolation of node ``values`` (shape ``self.shape`` + trailing)
        at ``states`` ``(..., 3)``. ``outside``: ``raise`` (naming the state), ``clamp``
        to the box, or ``nan``."""
        values = np.asarray(values)
        if values.shape[:3] != self.shape:
            raise ValueError(f"values shaped {values.shape} do not match grid {self.shape}")
        states = np.asarray(states, dtype=float)
        flat = states.reshape(-1, 3)
        inside = self.contains(flat)
        if outside == "raise" and not inside.all():
            bad = flat[np.argmin(inside)]
            raise ValueError(f"state [px={bad[0]:.3f} m, py={bad[1]:.3f} m, "
                             f"theta={np.rad2deg(bad[2]):.2f} deg] is outside the grid "
                             f"px [{self.lo[0]:g}, {self.hi[0]:g}] m, py [{self.lo[1]:g}, "
                             f"{self.hi[1]:g}] m, theta [{np.rad2deg(self.lo[2]):g}, "
                             f"{np.rad2deg(self.hi[2]):g}] deg")
        u = (np.clip(flat, self.lo, self.hi) - self.lo) / self.spacing
        i0 = np.clip(np.floor(u).astype(int), 0, np.asarray(self.shape) - 2)
        w = u - i0
        out = 0.0
        for corner in range(8):
            bits = [(corner >> k) & 1 for k in range(3)]
            weight = np.prod([w[:, k] if b else 1.0 - w[:, k] for k, b in enumerate(bits)], axis=0)
            node = values[i0[:, 0] + bits[0], i0[:, 1] + bits[1], i0[:, 2] + bits[2]]
            out = out + weight.reshape((-1,) + (1,) * (node.ndim - 1)) * node
        out = np.asarray(out, dtype=float)
        if outside == "nan":
            out[~inside] = np.nan
        return out.reshape(states.shape[:-1] + values.shape[3:])
