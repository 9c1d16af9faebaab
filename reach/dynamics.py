"""Closed-loop dynamics on a grid: ``f(x, u(x))`` with ``u`` a swept control table.

A `Dynamics` maps states ``(..., n)`` and controls ``(..., m)`` to derivatives; the
solver and the rollouts use nothing else, so any plant can be dropped in."""

import numpy as np
import torch

from reachwatch.systems import NOMINAL_SPEED_MPS, WHEELBASE_M


def rk4_step(f, x, h):
    """One classical Runge-Kutta step of ``x' = f(x)`` with step ``h``."""
    k1 = f(x)
    k2 = f(x + 0.5 * h * k1)
    k3 = f(x + 0.5 * h * k2)
    k4 = f(x + h * k3)
    return x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


def positive(name: str, value, *, integer=False):
    """``value`` if it is a finite number > 0 (a whole one if ``integer``); else a
    ValueError naming ``name``."""
    ok = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)
    if not ok or not np.isfinite(value) or value <= 0 or (integer and int(value) != value):
        raise ValueError(f"{name} must be a finite {'whole ' if integer else ''}number > 0, "
                         f"got {value!r}")
    return int(value) if integer else float(value)


def split_horizon(horizon: float, period: float):
    """``(whole periods, tail s)`` of a horizon: a sampled-data loop re-reads its control
    at every period start, so a horizon that is not a whole number of periods ends
    with a partial period of ``tail`` s (0 when it divides exactly)."""
    horizon, period = positive("horizon", horizon), positive("period", period)
    whole = int(np.floor(horizon / period + 1e-9))
    tail = horizon - whole * period
    return whole, (tail if tail > 1e-9 * period else 0.0)


class Dynamics:
    """Interface: ``vector_field(x, u)`` (torch, broadcasting) and the failure margin
    ``target(x)`` (``l(x) <= 0`` is failure).

    ``safe_box()`` may say where failure is known without the grid: ``(lo, hi)`` per
    state axis (``-inf``/``inf`` where unbounded) such that a state not strictly inside
    is a failure. BRT queries use it to answer for states outside the solved grid
    (leaving the runway is failure wherever it happens); ``None`` = not known."""

    state_dim = 3
    control_dim = 1

    def safe_box(self):
        return None

    def vector_field(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def target(self, x: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def hamiltonian(self, grad_value: torch.Tensor, x, u) -> torch.Tensor:
        """Closed-loop Hamiltonian ``<grad V, f(x, u)>`` (``grad_value`` like ``x``)."""
        return (grad_value * self.vector_field(x, u)).sum(-1)

    def partial_max_magnitudes(self, x, u) -> torch.Tensor:
        """``|dH/dp_i| = |f_i|`` per state dimension (for the CFL condition)."""
        return self.vector_field(x, u).abs()


class TaxiDynamics(Dynamics):
    """``px' = v sin(theta)``, ``py' = v cos(theta)``, ``theta' = (v/L) tan(phi)``;
    failure ``|px| >= half_width``, so ``l(x) = half_width - |px|`` (m)."""

    def __init__(self, *, half_width: float, speed: float = NOMINAL_SPEED_MPS,
                 wheelbase: float = WHEELBASE_M):
        self.half_width, self.speed, self.wheelbase = float(half_width), float(speed), float(wheelbase)

    def vector_field(self, x, u, speed=None):
        """``speed`` (m/s, tensor broadcasting with ``x[..., 0]``) overrides the
        nominal one, for the fallback pipeline whose speed is a state."""
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
