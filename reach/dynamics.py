"""Closed-loop dynamics on a grid: ``f(x, u(x))`` with ``u`` a swept control table.

A `Dynamics` maps states ``(..., n)`` and controls ``(..., m)`` to derivatives; the
solver and the rollouts use nothing else, so any plant can be dropped in."""

import torch

from reachwatch.systems import NOMINAL_SPEED_MPS, WHEELBASE_M


def rk4_step(f, x, h):
    """One classical Runge-Kutta step of ``x' = f(x)`` with step ``h``."""
    k1 = f(x)
    k2 = f(x + 0.5 * h * k1)
    k3 = f(x + 0.5 * h * k2)
    k4 = f(x + h * k3)
    return x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


class Dynamics:
    """Interface: ``vector_field(x, u)`` (torch, broadcasting) and the failure margin
    ``target(x)`` (``l(x) <= 0`` is failure)."""

    state_dim = 3
    control_dim = 1

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
