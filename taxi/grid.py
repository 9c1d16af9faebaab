"""The TaxiNet paper's state grid over [px m, py m, theta rad]."""

import dataclasses as dc
from typing import List

import numpy as np

from reachwatch.reach import Grid

AXES = ("px", "py", "theta")


def paper_grid(half_width: float, shape=(101, 101, 101), *, theta_deg: float = 28.0,
               py_max: float = 250.0) -> Grid:
    """The paper's box: px in [-(B+1), B+1] m, py in [100, 250] m, theta in [-28, 28] deg;
    ``theta_deg`` and ``py_max`` widen it (a box that holds what the loop does)."""
    if len(tuple(shape)) != 3:
        raise ValueError(f"the taxi grid has 3 axes (px, py, theta), got shape {list(shape)}")
    return Grid(lo=[-(half_width + 1.0), 100.0, np.deg2rad(-theta_deg)],
                hi=[half_width + 1.0, py_max, np.deg2rad(theta_deg)], shape=shape, names=AXES)


@dc.dataclass
class TaxiGridSpec:
    """A taxi grid as configs write it (theta in degrees)."""
    px: List[float] = dc.field(default_factory=lambda: [-11.0, 11.0])
    py: List[float] = dc.field(default_factory=lambda: [100.0, 250.0])
    theta_deg: List[float] = dc.field(default_factory=lambda: [-28.0, 28.0])
    shape: List[int] = dc.field(default_factory=lambda: [101, 101, 101])

    def to_grid(self) -> Grid:
        return Grid(lo=[self.px[0], self.py[0], np.deg2rad(self.theta_deg[0])],
                    hi=[self.px[1], self.py[1], np.deg2rad(self.theta_deg[1])],
                    shape=self.shape, names=AXES)
