"""`ValueFunction`: V(x, 0) on a grid, BRT queries, and its on-disk form."""

import dataclasses as dc
import io
import json
import zipfile
from typing import Optional, Tuple

import numpy as np

from reachwatch.systems.files import atomic_write_bytes

from .grid import Grid, check_states

#: What `ValueFunction.in_brt` does with a state outside the grid that is not a known
#: failure: ``raise`` an error naming it, ``clamp`` it to the box (a guess), or count it
#: as ``unsafe`` (conservative).
BRT_OUTSIDE_MODES = ("raise", "clamp", "unsafe")


@dc.dataclass
class ValueFunction:
    """V(x, 0) on ``grid`` (m for the taxi target); the BRT is ``{V <= 0}``.

    ``safe_box`` (``(lo, hi)`` per axis, from `Dynamics.safe_box`): a state not strictly
    inside it is a failure, in the BRT wherever it lies; ``None`` = not recorded."""
    grid: Grid
    values: np.ndarray
    horizon: float
    accuracy: str
    metadata: dict = dc.field(default_factory=dict)
    safe_box: Optional[Tuple[np.ndarray, np.ndarray]] = None

    def at(self, states, *, outside="raise") -> np.ndarray:
        """Interpolated V at ``states`` ``(..., ndim)`` (``outside``: see `Grid.interpolate`)."""
        return self.grid.interpolate(self.values, states, outside=outside)

    def known_failure(self, states) -> np.ndarray:
        """True where a state is outside ``safe_box`` (a failure already)."""
        return self._outside_safe_box(check_states(states, self.grid.ndim))

    def _outside_safe_box(self, states):
        if self.safe_box is None:
            return np.zeros(states.shape[:-1], bool)
        lo, hi = (np.asarray(b, float) for b in self.safe_box)
        return ~np.all((states > lo) & (states < hi), axis=-1)

    def in_brt(self, states, *, outside="raise") -> np.ndarray:
        """True where a start state leads to failure within the horizon.

        A non-finite state is an error. A state outside ``safe_box`` is in the BRT
        wherever it lies. Any other state outside the grid follows ``outside``
        (`BRT_OUTSIDE_MODES`): it is never silently called safe."""
        if outside not in BRT_OUTSIDE_MODES:
            raise ValueError(f"in_brt: outside must be one of {BRT_OUTSIDE_MODES}, got "
                             f"{outside!r}")
        states = check_states(states, self.grid.ndim)
        flat = states.reshape(-1, self.grid.ndim)
        failed = self._outside_safe_box(flat)
        inside = self.grid.contains(flat)
        unknown = ~failed & ~inside
        if outside == "raise" and unknown.any():
            raise ValueError(self.grid.describe(flat[np.argmax(unknown)]) +
                             " and not a known failure (pass outside='unsafe' or 'clamp')")
        answer = failed | (unknown if outside == "unsafe" else False)
        ask = ~answer & (inside | (outside == "clamp"))
        if ask.any():
            answer[ask] = self.grid.interpolate(self.values, flat[ask], outside="clamp") <= 0.0
        return answer.reshape(states.shape[:-1])

    @property
    def brt_fraction(self) -> float:
        """Fraction of the nodes of the grid it was solved on in the BRT (the paper's
        "volume" where that grid is the paper's box; `brt_fraction_of` for another)."""
        return float(np.mean(self.values <= 0.0))

    def brt_fraction_of(self, grid) -> float:
        """Fraction of ``grid``'s nodes in the BRT (`in_brt`; a node outside the grid
        solved on counts as in it): the "volume" over a box narrower than the one
        solved, such as the paper's inside a widened one."""
        nodes = np.stack([axis.ravel() for axis in grid.mesh()], axis=-1)
        return float(np.mean(self.in_brt(nodes, outside="unsafe")))

    def save(self, path):
        """Write ``.npz`` atomically (values, grid, horizon, accuracy, safe box,
        metadata JSON)."""
        buffer = io.BytesIO()
        box = {} if self.safe_box is None else {"safe_lo": np.asarray(self.safe_box[0], float),
                                                 "safe_hi": np.asarray(self.safe_box[1], float)}
        np.savez_compressed(buffer, values=self.values.astype(np.float32), lo=self.grid.lo,
                            hi=self.grid.hi, shape=np.asarray(self.grid.shape),
                            names=np.asarray(self.grid.names), horizon=self.horizon,
                            accuracy=self.accuracy, metadata=json.dumps(self.metadata), **box)
        return atomic_write_bytes(path, buffer.getvalue())

    @classmethod
    def load(cls, path) -> "ValueFunction":
        try:
            with np.load(path, allow_pickle=False) as data:
                names = [str(n) for n in data["names"]] if "names" in data else None
                if names is None and len(data["shape"]) == 3:
                    names = ["px", "py", "theta"]          # files from before names were kept
                grid = Grid(lo=data["lo"], hi=data["hi"], shape=data["shape"], names=names)
                values = data["values"].astype(float)
                if values.shape != grid.shape:
                    raise ValueError(f"values {values.shape} do not match grid {grid.shape}")
                box = ((data["safe_lo"], data["safe_hi"]) if "safe_lo" in data else None)
                return cls(grid, values, float(data["horizon"]), str(data["accuracy"]),
                           json.loads(str(data["metadata"])), box)
        except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile) as e:
            raise ValueError(f"{path} is not a readable value function: "
                             f"{type(e).__name__}: {e}") from None
