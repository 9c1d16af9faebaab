"""Solve the closed-loop HJB variational inequality on a grid.

``min{ D_t V + <grad V, f(x, u(x))>, l(x) - V } = 0``, ``V(x, T) = l(x)``, solved
backward from T to 0; the BRT is ``{V(x, 0) <= 0}``. ``u`` is a control table on the
grid (the swept controller output). Accuracy names:

- ``semi_lagrangian`` (default): dynamic programming on the sampled-data loop,
  ``V <- min(min_k l(F_k), V o F)``, where ``F`` flows ``periods_per_step`` control
  periods (RK4 sub-steps, control held within each period and re-read from the table
  at each period start, as the Drake loop does), ``F_k`` are the states at each period
  boundary and ``V o F`` is multilinear interpolation. Monotone (interpolation
  weights are non-negative) and stable at any step, so it needs 40 steps for 8 s
  instead of hundreds of CFL steps; the flow is computed once since the closed loop
  is autonomous, so each step is a single gather.
- ``low``: first-order upwind + forward Euler, CFL steps (continuous feedback).
- ``high`` / ``very_high``: WENO5 + TVD-RK2 / TVD-RK3, CFL steps (continuous feedback).
"""

import functools
import itertools

import numpy as np
import torch

from reachwatch.systems.checks import torch_device

from .dynamics import positive, rk4_step, split_horizon
from .grid import Grid
from .interpolate import GridInterpolator
from .levelset import hamiltonian_rate, rk_step
from .value_function import ValueFunction

ACCURACIES = {"low": ("first_order", 1), "high": ("weno5", 2), "very_high": ("weno5", 3),
              "semi_lagrangian": (None, None)}


def _held_flow(dynamics, x, u, period, substeps):
    """State after ``period`` s from ``x`` with the control ``u`` held (RK4)."""
    for _ in range(substeps):
        x = rk4_step(lambda y: dynamics.vector_field(y, u), x, period / substeps)
    return x


def _interpolate_table(grid, table, points):
    interpolate = GridInterpolator(grid, points)
    return torch.stack([interpolate(table[..., k]) for k in range(table.shape[-1])], dim=-1)


def _outside(grid, points, axes):
    """True where ``points`` lie outside ``grid``'s box on any of ``axes``."""
    out = torch.zeros(points.shape[:-1], dtype=torch.bool, device=points.device)
    for a in axes:
        out |= (points[..., a] < grid.lo[a] - 1e-9) | (points[..., a] > grid.hi[a] + 1e-9)
    return out


def _sampled_flow(grid, dynamics, x, u, target, periods, period, tail=0.0, exit_fails=()):
    """Foot of the sampled-data flow from the nodes ``x`` over ``periods`` whole
    control periods then ``tail`` s, and the minimum of the target at every period
    boundary (and the end) along the way; a boundary outside the box on one of
    ``exit_fails`` caps that minimum at 0 (a failure)."""
    foot, path_target = x, target
    for k in range(periods + (tail > 0)):
        held = u if k == 0 else _interpolate_table(grid, u, foot)
        foot = _held_flow(dynamics, foot, held, period if k < periods else tail, substeps=4)
        path_target = torch.minimum(path_target, dynamics.target(foot))
        if exit_fails:
            path_target = torch.where(_outside(grid, foot, exit_fails),
                                      torch.clamp(path_target, max=0.0), path_target)
    return foot, path_target


def _bound_corners(grid, table, control_bounds, accuracy):
    """The corner tables of ``control_bounds`` (every control component at its ``lo``
    or its ``hi``), each shaped ``grid.shape + (m,)``; none without bounds."""
    if control_bounds is None:
        return []
    if accuracy != "semi_lagrangian":
        raise ValueError(f"control_bounds needs accuracy 'semi_lagrangian', got '{accuracy}'")
    try:
        lo, hi = (np.asarray(b, dtype=float) for b in control_bounds)
    except (TypeError, ValueError):
        raise ValueError("control_bounds must be a pair (lo, hi) of tables") from None
    for name, bound in (("lo", lo), ("hi", hi)):
        if bound.shape != table.shape:
            raise ValueError(f"control_bounds {name} shaped {bound.shape} does not match the "
                             f"control table {table.shape}")
        if not np.all(np.isfinite(bound)):
            raise ValueError(f"control_bounds {name} has {np.sum(~np.isfinite(bound))} "
                             f"non-finite entries")
    outside = (lo > table) | (hi < table)
    if np.any(outside):
        raise ValueError(f"control_bounds must hold the control table (lo <= table <= hi); "
                         f"{int(np.sum(outside))} entries lie outside")
    lo, hi = (b.reshape(grid.shape + (-1,)) for b in (lo, hi))
    return [np.stack([(hi if pick else lo)[..., k] for k, pick in enumerate(choice)], axis=-1)
            for choice in itertools.product((0, 1), repeat=lo.shape[-1])]


def check_controls(grid: Grid, dynamics, table: np.ndarray, *, where: str = ""):
    """A ValueError, naming how many nodes and the first one (and ``where``: the
    environment and port, say), where the swept control ``table`` (``grid.shape`` or
    ``grid.shape + (m,)``) is NaN or infinite, or lies outside the plant's
    `Dynamics.control_limits` (open: a saturated actuator's own limit lies outside;
    give the bound just past it), a controller's mistake the flow would read as another
    command, such as degrees for radians."""
    u = np.asarray(table, float).reshape(grid.size, -1)
    limits = getattr(dynamics, "control_limits", lambda: None)()
    checks = [(~np.all(np.isfinite(u), axis=1), "NaN or infinite")]
    if limits is not None:
        lo, hi = (np.atleast_1d(np.asarray(b, float)) for b in limits)
        if lo.shape != (u.shape[1],) or hi.shape != (u.shape[1],):
            raise ValueError(f"{type(dynamics).__name__}.control_limits gives {lo.size} and "
                             f"{hi.size} bounds for {u.shape[1]} control components")
        with np.errstate(invalid="ignore"):
            outside = np.any((u <= lo) | (u >= hi), axis=1) & ~checks[0][0]
        checks.append((outside, "outside the plant's controls (" + ", ".join(
            f"{a:g} < u{k} < {b:g}" for k, (a, b) in enumerate(zip(lo, hi))) + ")"))
    for bad, what in checks:
        if np.any(bad):
            first = int(np.argmax(bad))
            state = ", ".join(f"{n}={v:.4g}" for n, v in zip(grid.names, grid.states([first])[0]))
            raise ValueError(f"{where + ': ' if where else ''}the swept control is {what} at "
                             f"{int(bad.sum())} of {grid.size} grid states, the first [{state}] "
                             f"(control {u[first].tolist()}): look at the controller's output "
                             f"there")


def check_plant(grid: Grid, dynamics, bad, what: str, *, where: str = ""):
    """A ValueError, naming how many nodes and the first one (and ``where``), where
    ``bad`` (a boolean tensor or array of ``grid.shape``) holds: the plant's ``what``
    is NaN (or, for a flow, infinite) from there. Left alone, a NaN value reads as safe
    (``V <= 0`` is false) and a NaN foot indexes the grid at random. An infinite target
    is a state that never fails (or always has): not refused."""
    bad = np.asarray(bad.cpu() if isinstance(bad, torch.Tensor) else bad, bool).reshape(-1)
    if np.any(bad):
        first = int(np.argmax(bad))
        state = ", ".join(f"{n}={v:.4g}" for n, v in zip(grid.names, grid.states([first])[0]))
        raise ValueError(f"{where + ': ' if where else ''}{type(dynamics).__name__}.{what} is "
                         f"NaN or infinite from {int(bad.sum())} of {grid.size} grid states, "
                         f"the first [{state}]: look at the plant's dynamics there")


def solve_brt(grid: Grid, dynamics, control_table, *, horizon: float = 8.0,
              accuracy: str = "semi_lagrangian", period: float = 0.05,
              periods_per_step: int = 4, cfl: float = 0.75, exit_fails=(),
              control_bounds=None, device=None, dtype=torch.float32,
              progress=None, where: str = "") -> ValueFunction:
    """V(x, 0) of the closed loop ``f(x, control_table(x))`` over exactly ``horizon`` s.

    ``control_table``: ``grid.shape`` or ``grid.shape + (m,)``; ``period`` (s) is the
    control hold of ``semi_lagrangian`` and ``periods_per_step`` its step length in
    periods (a horizon that is no whole number of steps ends with a shorter step, and
    one that is no whole number of periods with a partial period); ``cfl`` (0, 1] sets
    the level-set schemes' step; ``device`` defaults to CUDA when present. The
    metadata records what was solved: steps, whole periods and tail.

    Where the flow leaves the grid box, the table and V are read at the box's edge
    (clamped): what the loop does out there is unknown. ``exit_fails`` (axis indices,
    ``semi_lagrangian`` only) makes leaving the box on those axes within the horizon a
    failure instead (V <= 0): conservative where clamping is optimistic.

    ``control_bounds`` (``(lo, hi)``, two tables shaped like ``control_table``;
    ``semi_lagrangian`` only) solves a robust BRT: the controller's output at a state
    may lie anywhere in ``[lo, hi]`` there (e.g. the range of the swept output around
    each node, `reach.robust.local_range`), and each step takes the worst of the flows
    under ``control_table`` and under each corner of the bounds (every component at its
    ``lo`` or ``hi``), the choice held for the step. It covers outputs the grid cannot
    see between its nodes, and it can only grow the BRT. The metadata records the share
    of nodes whose bounds are wider than the table (``bounded_nodes``).

    The table is checked first (`check_controls`; ``where`` names it in the error:
    the environment and port, say)."""
    if accuracy not in ACCURACIES:
        raise ValueError(f"accuracy must be one of {sorted(ACCURACIES)}, got '{accuracy}'")
    horizon = positive("horizon", horizon)
    whole, tail = split_horizon(horizon, period)
    periods_per_step = positive("periods_per_step", periods_per_step, integer=True)
    cfl = positive("cfl", cfl)
    if cfl > 1:
        raise ValueError(f"cfl must be in (0, 1] (explicit schemes are unstable above 1), got {cfl}")
    state_dim = getattr(dynamics, "state_dim", grid.ndim)
    if state_dim != grid.ndim:
        raise ValueError(f"dynamics has {state_dim} states but the grid {grid.ndim} axes")
    table = np.asarray(control_table, dtype=float)
    if table.shape[:grid.ndim] != grid.shape:
        raise ValueError(f"control table shaped {table.shape} does not match grid {grid.shape}")
    exit_fails = tuple(sorted({int(a) for a in exit_fails}))
    if any(not 0 <= a < grid.ndim for a in exit_fails):
        raise ValueError(f"exit_fails names axes {list(exit_fails)}; the grid has axes "
                         f"0..{grid.ndim - 1} ({', '.join(grid.names)})")
    if exit_fails and accuracy != "semi_lagrangian":
        raise ValueError(f"exit_fails needs accuracy 'semi_lagrangian', got '{accuracy}'")
    check_controls(grid, dynamics, table, where=where)
    corners = _bound_corners(grid, table, control_bounds, accuracy)
    device = torch_device(device)
    as_t = lambda a: torch.as_tensor(a, dtype=dtype, device=device)     # noqa: E731
    x = as_t(np.stack(grid.mesh(), axis=-1))                           # (*shape, n)
    u = as_t(table.reshape(grid.shape + (-1,)))
    controls = [u] + [as_t(c) for c in corners]
    target = dynamics.target(x)
    check_plant(grid, dynamics, torch.isnan(target), "target", where=where)
    values = target.clone()
    scheme, order = ACCURACIES[accuracy]
    if scheme is None:
        # Dynamic programming backward from the end of the horizon: the last step in
        # time (the shorter one, if any) is applied first. A step spans up to
        # `periods_per_step` control periods; the flow re-samples the control
        # (interpolated) every period and the target is checked at each boundary.
        full_steps, rest = divmod(whole, periods_per_step)
        schedule = ([(rest, tail)] if rest or tail else []) + [(periods_per_step, 0.0)] * full_steps
        maps = {}
        for periods, tail_s in set(schedule):
            maps[periods, tail_s] = []
            for control in controls:       # the nominal table, then any bounds' corners
                foot, path_target = _sampled_flow(grid, dynamics, x, control, target, periods,
                                                  period, tail_s, exit_fails)
                check_plant(grid, dynamics, ~torch.isfinite(foot).all(-1)
                            | ~torch.isfinite(path_target),
                            "vector_field (or target along the flow)", where=where)
                maps[periods, tail_s].append((path_target, GridInterpolator(grid, foot)))
        steps = len(schedule)
        for k in (progress(range(steps)) if progress else range(steps)):
            stepped = [torch.minimum(path_target, interpolate(values))
                       for path_target, interpolate in maps[schedule[k]]]
            values = functools.reduce(torch.minimum, stepped)
        metadata = {"steps": steps, "periods": whole, "tail": tail,
                    "dt": period * periods_per_step, "exit_fails": list(exit_fails),
                    "robust": bool(corners),
                    # nodes where the all-hi corner differs from the all-lo one
                    "bounded_nodes": float(np.mean(np.any(corners[-1] != corners[0], axis=-1)))
                    if corners else 0.0}
    else:
        field = dynamics.vector_field(x, u).movedim(-1, 0)                # (n, *shape)
        check_plant(grid, dynamics, ~torch.isfinite(field).all(0), "vector_field", where=where)
        spacing = grid.spacing
        rate_bound = sum(field[k].abs().max().item() / spacing[k] for k in range(grid.ndim))
        dt = cfl / max(rate_bound, 1e-12)
        steps = int(np.ceil(horizon / dt))
        dt = horizon / steps
        rate = lambda v: hamiltonian_rate(v, field, spacing, scheme)   # noqa: E731
        for _ in (progress(range(steps)) if progress else range(steps)):
            values = torch.minimum(rk_step(values, rate, dt, order), target)
        metadata = {"steps": steps, "dt": dt}
    metadata.update(solved_horizon=horizon, period=period, device=str(device))
    box = dynamics.safe_box() if hasattr(dynamics, "safe_box") else None
    return ValueFunction(grid=grid, values=values.cpu().double().numpy(), horizon=horizon,
                         accuracy=accuracy, metadata=metadata,
                         safe_box=None if box is None else tuple(np.asarray(b, float) for b in box))
