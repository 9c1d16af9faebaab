"""The taxiing aircraft as the solver sees it: kinematic bicycle at a set speed,
failure when it leaves the runway."""

import numpy as np
import torch

from reachwatch.reach import Dynamics
from reachwatch.systems import MAX_STEERING_RAD, NOMINAL_SPEED_MPS, WHEELBASE_M


class OffRunway:
    """The taxi's failure rule, as `reachwatch.diagrams.simulate` takes it: plant states
    ``(n, 3)`` -> ``(n,)`` bools, ``|px| >= half_width`` (m). A class, not a closure, so
    that it pickles with the settings it is part of."""

    def __init__(self, half_width: float):
        half_width = float(half_width)
        if not (np.isfinite(half_width) and half_width > 0):
            raise ValueError(f"half_width must be a finite number > 0 m, got {half_width}")
        self.half_width = half_width

    def __call__(self, states) -> np.ndarray:
        return np.abs(np.asarray(states, float)[:, 0]) >= self.half_width

    def __repr__(self):
        return f"OffRunway(half_width={self.half_width:g})"


class TaxiDynamics(Dynamics):
    """``px' = v sin(theta)``, ``py' = v cos(theta)``, ``theta' = (v/L) tan(phi)``;
    failure ``|px| >= half_width``, so ``l(x) = half_width - |px|`` (m)."""

    state_dim = 3
    control_dim = 1

    def __init__(self, *, half_width: float, speed: float = NOMINAL_SPEED_MPS,
                 wheelbase: float = WHEELBASE_M):
        self.half_width, self.speed, self.wheelbase = float(half_width), float(speed), float(wheelbase)

    def vector_field(self, x, u, speed=None):
        """``speed`` (m/s, tensor broadcasting with ``x[..., 0]``) overrides the
        nominal one, for the guarded loop whose speed is a state."""
        v = self.speed if speed is None else speed
        theta = x[..., 2]
        phi = u[..., 0]
        return torch.stack([v * torch.sin(theta), v * torch.cos(theta),
                            v / self.wheelbase * torch.tan(phi)], dim=-1)

    def target(self, x):
        return self.half_width - x[..., 0].abs()

    def safe_box(self):
        inf = float("inf")
        return [-self.half_width, -inf, -inf], [self.half_width, inf, inf]

    def control_limits(self):
        """The steering angle within +-pi/2 rad: tan(phi) turns the other way past it."""
        return [-MAX_STEERING_RAD], [MAX_STEERING_RAD]


def dynamics_for(scenario) -> TaxiDynamics:
    """The taxi dynamics of a scenario: its runway's half-width, its controller's speed."""
    return TaxiDynamics(half_width=scenario.environment.half_width,
                        speed=scenario.controller.speed)
