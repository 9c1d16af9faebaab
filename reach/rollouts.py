"""Ground truth for the solver: integrate the closed loop from grid nodes (or any
states) and take the minimum of the target along each path."""

import math

import numpy as np
import torch

from .dynamics import positive, rk4_step, split_horizon
from .grid import check_states
from .interpolate import GridInterpolator


def rollout_steps(horizon: float, dt: float, hold=None) -> list:
    """The RK4 steps of a rollout over ``[0, horizon]``: ``(size, sample)`` pairs, where
    ``sample`` says that the held control is sampled anew at the step's start (every
    ``hold`` s; never with ``hold`` None). Steps of ``dt`` where ``horizon`` (and
    ``hold``) are whole numbers of them; otherwise each period, and the part of a period
    that ends the horizon, is split into the fewest equal steps no longer than ``dt``,
    so that any control period works (1/30 s, 0.025 s) and every sample falls on a
    tick of the loop."""
    horizon, dt = positive("horizon", horizon), positive("dt", dt)
    if hold is not None:
        hold = positive("hold", hold)
    whole = int(round(horizon / dt))
    per_hold = 1 if hold is None else int(round(hold / dt))
    if (abs(whole * dt - horizon) <= 1e-9 * max(1.0, horizon) and per_hold >= 1
            and (hold is None or abs(per_hold * dt - hold) <= 1e-9)):
        return [(dt, hold is not None and k % per_hold == 0) for k in range(whole)]

    def split(length):
        n = max(1, math.ceil(length / dt - 1e-9))
        return [length / n] * n
    if hold is None:
        return [(size, False) for size in split(horizon)]
    periods, tail = split_horizon(horizon, hold)         # as the solver splits it
    steps = [(size, k == 0) for _ in range(periods) for k, size in enumerate(split(hold))]
    if tail:
        steps += [(size, k == 0) for k, size in enumerate(split(tail))]
    return steps


@torch.no_grad()
def min_target_along_rollouts(grid, dynamics, control_table, starts, *, horizon=8.0,
                              dt=0.01, hold=None, batch=200_000, device="cpu",
                              progress=None, box_axes=None):
    """``min_t l(x(t))`` over ``[0, horizon]`` from each start ``(N, ndim)``; with
    ``box_axes`` (axis indices), also whether each rollout left ``grid``'s box on any of
    them (where the table is clamped to its edge), as a second array.

    The control comes from multilinear interpolation of ``control_table`` at the
    current state (``hold=None``: continuous feedback, RK4 with step ``dt``), or is
    sampled every ``hold`` s and held (the Drake loop's zero-order hold); the steps are
    `rollout_steps`'."""
    table = torch.as_tensor(np.asarray(control_table, float).reshape(grid.shape + (-1,)),
                            dtype=torch.float64, device=device)
    columns = [table[..., k] for k in range(table.shape[-1])]
    starts = torch.as_tensor(check_states(starts, grid.ndim, "start").reshape(-1, grid.ndim),
                             device=device)
    steps = rollout_steps(horizon, dt, hold)

    def control(x):
        interpolate = GridInterpolator(grid, x)
        return torch.stack([interpolate(c) for c in columns], dim=-1)

    lo, hi = (torch.as_tensor(b, dtype=torch.float64, device=device) for b in (grid.lo, grid.hi))
    axes = list(box_axes or [])

    def outside(y):
        return ((y[..., axes] < lo[axes] - 1e-9) | (y[..., axes] > hi[axes] + 1e-9)).any(-1)

    out, exits = [], []
    chunks = range(0, len(starts), batch)
    for s in (progress(chunks) if progress else chunks):
        x = starts[s:s + batch]
        lowest = dynamics.target(x)
        left = outside(x)
        u = control(x)
        for size, sample in steps:
            if hold is None:
                f = lambda y: dynamics.vector_field(y, control(y))    # noqa: E731
            else:
                if sample:
                    u = control(x)
                f = lambda y, u=u: dynamics.vector_field(y, u)     # noqa: E731
            x = rk4_step(f, x, size)
            lowest = torch.minimum(lowest, dynamics.target(x))
            left |= outside(x)
        out.append(lowest.cpu().numpy())
        exits.append(left.cpu().numpy())
    if box_axes is None:
        return np.concatenate(out)
    return np.concatenate(out), np.concatenate(exits)


def sign_agreement(values, reference) -> float:
    """Fraction of entries on which ``values <= 0`` and ``reference <= 0`` agree."""
    return float(np.mean((np.asarray(values) <= 0) == (np.asarray(reference) <= 0)))
