"""`ValueFunction`: V(x, 0) on a grid, BRT queries, and its on-disk form."""

import dataclasses as dc
import io
import json

import numpy as np

from reachwatch.systems.files import atomic_write_bytes

from .grid import Grid


@dc.dataclass
class ValueFunction:
    """V(x, 0) on ``grid`` (m for the taxi target); the BRT is ``{V <= 0}``."""
    grid: Grid
    values: np.ndarray
    horizon: float
    accuracy: str
    metadata: dict = dc.field(default_factory=dict)

    def at(self, states, *, outside="raise") -> np.ndarray:
        """Interpolated V at ``states`` ``(..., 3)`` [px m, py m, theta rad]."""
        return self.grid.interpolate(self.values, states, outside=outside)

    def in_brt(self, states, *, outside="raise") -> np.ndarray:
        """True where a start state leads to failure within the horizon."""
        return self.at(states, outside=outside) <= 0.0

    @property
    def brt_fraction(self) -> float:
        """Fraction of grid nodes in the BRT (the paper's "volume")."""
        return float(np.mean(self.values <= 0.0))

    def save(self, path):
        """Write ``.npz`` atomically (values, grid, horizon, accuracy, metadata JSON)."""
        buffer = io.BytesIO()
        np.savez_compressed(buffer, values=self.values.astype(np.float32), lo=self.grid.lo,
                            hi=self.grid.hi, shape=np.asarray(self.grid.shape),
                            horizon=self.horizon, accuracy=self.accuracy,
                            metadata=json.dumps(self.metadata))
        return atomic_write_bytes(path, buffer.getvalue())

    @classmethod
    def load(cls, path) -> "ValueFunction":
        try:
            with np.load(path, allow_pickle=False) as data:
                grid = Grid(lo=data["lo"], hi=data["hi"], shape=data["shape"])
                values = data["values"].astype(float)
                if values.shape != grid.shape:
                    raise ValueError(f"values {values.shape} do not match grid {grid.shape}")
                return cls(grid, values, float(data["horizon"]), str(data["accuracy"]),
                           json.loads(str(data["metadata"])))
        except (OSError, KeyError, ValueError) as e:
            raise ValueError(f"{path} is not a readable value function: {e}") from None
