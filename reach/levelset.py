"""Upwind spatial derivatives (first order and WENO5) and TVD Runge-Kutta steps for
the closed-loop HJB equation, in torch (CPU or CUDA).

Boundary: three ghost cells per side, extrapolated linearly from the edge."""

import torch

WENO_EPS = 1e-6


def _pad_linear(values: torch.Tensor, dim: int, ghost: int = 3) -> torch.Tensor:
    n = values.shape[dim]
    first, second = values.narrow(dim, 0, 1), values.narrow(dim, 1, 1)
    last, before = values.narrow(dim, n - 1, 1), values.narrow(dim, n - 2, 1)
    k = torch.arange(ghost, 0, -1, dtype=values.dtype, device=values.device)
    view = [1] * values.dim()
    view[dim] = ghost
    k = k.view(view)
    left = first - k * (second - first)                  # ghosts -3, -2, -1
    right = last + k.flip(dim) * (last - before)         # ghosts n, n+1, n+2
    return torch.cat([left, values, right], dim=dim)


def _weno5(v1, v2, v3, v4, v5):
    """Jiang-Shu WENO5 combination of five consecutive one-sided differences."""
    phi1 = v1 / 3 - 7 * v2 / 6 + 11 * v3 / 6
    phi2 = -v2 / 6 + 5 * v3 / 6 + v4 / 3
    phi3 = v3 / 3 + 5 * v4 / 6 - v5 / 6
    s1 = 13 / 12 * (v1 - 2 * v2 + v3) ** 2 + 0.25 * (v1 - 4 * v2 + 3 * v3) ** 2
    s2 = 13 / 12 * (v2 - 2 * v3 + v4) ** 2 + 0.25 * (v2 - v4) ** 2
    s3 = 13 / 12 * (v3 - 2 * v4 + v5) ** 2 + 0.25 * (3 * v3 - 4 * v4 + v5) ** 2
    a1 = 0.1 / (WENO_EPS + s1) ** 2
    a2 = 0.6 / (WENO_EPS + s2) ** 2
    a3 = 0.3 / (WENO_EPS + s3) ** 2
    return (a1 * phi1 + a2 * phi2 + a3 * phi3) / (a1 + a2 + a3)


def upwind_derivative(values, dim, spacing, velocity, scheme="weno5"):
    """dV/dx_dim taken from the side the information comes from.

    The backward-time equation ``dV/ds = <f, grad V>`` transports V along -f, so
    where ``f_dim > 0`` the right-sided derivative is the upwind one."""
    n = values.shape[dim]
    d = torch.diff(_pad_linear(values, dim), dim=dim) / spacing     # n + 5 differences
    s = lambda a: d.narrow(dim, a, n)                                # noqa: E731
    if scheme == "first_order":
        left, right = s(2), s(3)
    elif scheme == "weno5":
        left = _weno5(s(0), s(1), s(2), s(3), s(4))
        right = _weno5(s(5), s(4), s(3), s(2), s(1))
    else:
        raise ValueError(f"unknown derivative scheme '{scheme}'")
    return torch.where(velocity > 0, right, left)


def hamiltonian_rate(values, field, spacing, scheme):
    """``<f, grad V>`` with upwind derivatives; ``field`` is ``(3, *shape)``."""
    return sum(field[k] * upwind_derivative(values, k, float(spacing[k]), field[k], scheme)
               for k in range(values.dim()))


def rk_step(values, rate, dt, order):
    """One TVD (Shu-Osher) Runge-Kutta step of ``dV/ds = rate(V)``, order 1-3."""
    if order == 1:
        return values + dt * rate(values)
    v1 = values + dt * rate(values)
    if order == 2:
        return 0.5 * values + 0.5 * (v1 + dt * rate(v1))
    v2 = 0.75 * values + 0.25 * (v1 + dt * rate(v1))
    return values / 3 + 2 / 3 * (v2 + dt * rate(v2))
