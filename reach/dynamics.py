"""Closed-loop dynamics on a grid: ``f(x, u(x))`` with ``u`` a swept control table.

A `Dynamics` maps states ``(..., n)`` and controls ``(..., m)`` to derivatives; the
solver and the rollouts use nothing else, so any plant can be dropped in. Also the
small helpers they share: an RK4 step and the checks of horizons and periods."""

import abc

import numpy as np
import torch


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


class Dynamics(abc.ABC):
    """A closed loop's plant, as the solver and the rollouts see it.

    Subclasses set ``state_dim`` and ``control_dim`` and implement
    ``vector_field(x, u)`` (torch, broadcasting over leading dimensions: states
    ``(..., state_dim)`` and controls ``(..., control_dim)`` to derivatives) and the
    failure margin ``target(x)`` (``l(x) <= 0`` is failure).

    ``control_limits()`` may say the open range of each control (a steering angle
    within +-pi/2 rad, say, past which tan turns back).

    ``safe_box()`` may say where failure is known without the grid: ``(lo, hi)`` per
    state axis (``-inf``/``inf`` where unbounded) such that a state not strictly inside
    is a failure. BRT queries use it to answer for states outside the solved grid;
    ``None`` (the default) = not known."""

    state_dim: int
    control_dim: int

    @abc.abstractmethod
    def vector_field(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """dx/dt at states ``x`` under controls ``u``."""

    @abc.abstractmethod
    def target(self, x: torch.Tensor) -> torch.Tensor:
        """The failure margin ``l(x)``; ``l <= 0`` is failure."""

    def safe_box(self):
        return None

    def control_limits(self):
        """``(lo, hi)`` per control component: the open range a control of this plant
        lies in (a table outside it is refused before a solve, `solver.check_controls`);
        None (the default): any finite number."""
        return None
