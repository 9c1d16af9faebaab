"""Failure sets and liveness of a guarded loop from its swept tables, whatever the
plant, where speed becomes a state.

The image does not depend on speed, so the swept tables of steering, estimate and
detector score on the grid are enough: from every start at the nominal speed, the
sampled-data loop is rolled out tick by tick (steering, estimate and flag read from the
tables, speed updated by the fallback strategy, the steering while flagged chosen by
the fallback's steering mode, dynamics integrated with RK4 over the tick). A start fails
where the dynamics' ``target`` drops to 0 within the horizon; what it did until then
(distance, stops, flagged ticks) is its liveness (`reach.liveness`). The fallback's
rules are `systems.Fallback`'s, the ones the Drake `FallbackSwitch` applies, so the
switch and these rollouts never disagree on what a fallback does."""

import dataclasses as dc
import inspect

import numpy as np
import torch

from reachwatch.systems import Fallback, check_k_of_n, confirmed_flags
from reachwatch.systems.detector import flags_at

from .dynamics import positive, rk4_step, split_horizon
from .grid import check_states
from .interpolate import GridInterpolator
from .liveness import UNGUARDED, MissionOutcomes, check_mission_limit


def takes_speed(dynamics) -> bool:
    """Whether ``dynamics`` can be driven at another speed than its nominal one: it has
    a ``speed`` (the nominal, m/s) and its ``vector_field`` takes ``speed=`` (a tensor
    per state), as a plant whose fallback slows it down or brakes must."""
    try:
        takes = "speed" in inspect.signature(dynamics.vector_field).parameters
    except (TypeError, ValueError):
        return False
    return takes and isinstance(getattr(dynamics, "speed", None), (int, float))


def check_takes_speed(dynamics):
    """A ValueError in one line unless `takes_speed`."""
    if not takes_speed(dynamics):
        raise ValueError(f"{type(dynamics).__name__} cannot be rolled out at the fallback's "
                         f"speed: give it a nominal 'speed' (m/s) and a vector_field(x, u, "
                         f"speed=None) that uses the speed given")


@torch.no_grad()
def guarded_rollouts(grid, dynamics, steering_table, score_table=None, *, threshold=0.5,
                     strategy="slow_down", steering="controller", estimate_table=None,
                     policy=None, truth=None, carry=None, horizon=8.0, period=0.05,
                     substeps=2, starts=None, flags_needed=1, flag_window=1,
                     mission_limit=None, score_noise=None, seed=0,
                     **strategy_params) -> MissionOutcomes:
    """`MissionOutcomes` per start (default: every grid node, C order) of the loop whose
    steering, score and estimate are interpolated from tables of ``grid``.
    ``score_table=None`` = no detector (the controller alone).

    ``strategy``, ``steering`` and ``strategy_params`` are the fields of the
    `systems.Fallback` applied, by the rules the Drake `FallbackSwitch` applies
    (`Fallback.next_speed`, `Fallback.steering_angle`). While flagged, ``steering`` is
    ``"controller"`` (the table's steering; also read as ``"taxinet"``), ``"oracle"``
    (``policy`` of ``truth(states)``, the true value of what the controller estimates)
    or ``"dead_reckoning"`` (``policy`` of the last unflagged estimate from
    ``estimate_table``, carried forward with the steering and speed applied since by
    ``carry(estimate, steering, speed, period)``). ``policy`` maps ``(n, k)`` estimates
    to steering (rad). ``dynamics`` is a `Dynamics` with a nominal ``speed`` whose
    ``vector_field`` takes ``speed=`` (`takes_speed`). A tick counts as flagged when at least
    ``flags_needed`` of the last ``flag_window`` ticks' scores reached the threshold,
    as `FlagFilter` confirms them.

    With ``mission_limit`` (a number >= 1), the rollouts also go on past the horizon, up
    to ``mission_limit * horizon`` s, until each start has covered the distance the
    controller alone covers within the horizon (nominal speed x horizon), and fill the
    same-distance fields of `MissionOutcomes`; the other fields stay the horizon's.

    ``score_noise`` (a `reach.score_noise.ScoreNoise`) adds, per start, the detector's
    variation between grid nodes to the interpolated score, as noise that moves with
    the distance travelled (seeded by ``seed``), as the real loop's score does."""
    flags_needed, flag_window = check_k_of_n(flags_needed, flag_window)
    fallback = Fallback(strategy, steering, **strategy_params)
    steering = fallback.steering
    check_takes_speed(dynamics)
    if fallback.takes_over_steering and policy is None:
        raise ValueError(f"steering '{steering}' needs a policy (estimate -> steering: an "
                         f"application's fallback_policy)")
    if steering == "oracle" and truth is None:
        raise ValueError("steering 'oracle' needs the true estimate of a state (truth: an "
                         "application's true_estimate)")
    if steering == "dead_reckoning" and (estimate_table is None or carry is None):
        raise ValueError("steering 'dead_reckoning' needs the estimate table and how an "
                         "estimate is carried forward (carry: an application's carry_estimate)")
    as_t = lambda a: torch.as_tensor(np.asarray(a, float), dtype=torch.float64)   # noqa: E731
    x = as_t(grid.states() if starts is None else check_states(starts, grid.ndim, "start")
             ).reshape(-1, grid.ndim).clone()      # updated in place: never the caller's array
    n = len(x)
    steer = as_t(steering_table).reshape(grid.shape)
    score = None if score_table is None else as_t(score_table).reshape(grid.shape)
    estimates = (None if estimate_table is None else
                 [as_t(column).reshape(grid.shape) for column in
                  np.asarray(estimate_table, float).reshape(int(np.prod(grid.shape)), -1).T])
    nominal = dynamics.speed
    v = np.full(n, nominal)
    alive = (dynamics.target(x) > 0).numpy()
    failed = ~alive
    distance, flagged_ticks, ticks = np.zeros(n), np.zeros(n, int), np.zeros(n, int)
    ever_stopped = np.zeros(n, bool)
    k_est = 0 if estimates is None else len(estimates)
    base, u_prev, v_prev, trusted = np.zeros((n, k_est)), np.zeros(n), v.copy(), np.zeros(n, bool)
    history = np.zeros((n, flag_window - 1), bool)
    whole, tail = split_horizon(horizon, period)
    steps = [period] * whole + ([tail] if tail > 0 else [])
    goal = nominal * horizon                      # the controller alone's distance
    if mission_limit is not None:
        limit = check_mission_limit(mission_limit)
        steps += [period] * max(0, int(np.ceil((limit - 1) * horizon / period - 1e-9)))
    covered, parked = np.zeros(n, bool), np.zeros(n, bool)
    rng, noise, moved = np.random.default_rng(seed), None, np.zeros(n)
    substeps = positive("substeps", substeps, integer=True)
    at_horizon = None
    for k, dt in enumerate(steps):       # a last partial period when it does not divide
        if k == whole + (tail > 0):      # the horizon's figures, before going on
            at_horizon = _snapshot(failed, v, ever_stopped, distance, flagged_ticks, ticks)
        active = alive & ~covered & ~parked
        if not active.any():
            break
        # Only the active starts are interpolated and integrated: an ended start's
        # state, score and speed no longer reach any figure (its outcome is settled,
        # and the horizon's snapshot holds its speed from its last active tick).
        rows = np.flatnonzero(active)
        index = torch.as_tensor(rows)
        interpolate = GridInterpolator(grid, x[index])
        u = np.zeros(n)
        u[rows] = interpolate(steer).numpy()
        flagged = np.zeros(n, bool)
        if score is not None:
            score_now = np.zeros(n)
            score_now[rows] = interpolate(score).numpy()
            if score_noise is not None:          # stepped for every start: the same draws
                noise = score_noise.step(noise, moved, rng)
                score_now[rows] = score_noise.apply(score_now[rows], noise[rows])
            flagged, history = confirmed_flags(flags_at(score_now, threshold), history,
                                               flags_needed)
        if score is not None:
            v = fallback.next_speed(v, flagged, nominal=nominal, period=period)
            taken = None                 # the fallback's steering mode's angle
            if steering == "oracle":
                taken = policy(truth(x.numpy()))
            elif steering == "dead_reckoning":
                seen = np.zeros((n, k_est))
                seen[rows] = np.stack([interpolate(e).numpy() for e in estimates], axis=-1)
                carried = carry(base, u_prev, v_prev, period)
                belief = np.where((flagged & trusted)[:, None], carried, seen)
                taken = policy(belief)
            u = fallback.steering_angle(flagged, u, taken)
            if steering == "dead_reckoning":
                base, u_prev, v_prev = belief, u, v.copy()
                trusted |= ~flagged
        ticks += active
        flagged_ticks += active & flagged
        ever_stopped |= active & (v <= 0)
        moved = np.where(active, v * dt, 0.0)
        distance += moved
        h = dt / substeps
        u_t, v_t, y = as_t(u[rows])[:, None], as_t(v[rows]), x[index]
        for _ in range(substeps):
            y = rk4_step(lambda z: dynamics.vector_field(z, u_t, speed=v_t), y, h)
        x[index] = y
        out = (dynamics.target(x) <= 0).numpy()
        failed |= active & out
        alive &= ~(active & out)
        if mission_limit is not None:
            covered |= alive & (distance >= goal * (1 - 1e-9))
            if k + 1 >= whole + (tail > 0):   # past the horizon: standing still while
                parked |= active & flagged & (v <= 0)     # flagged is for good
    if at_horizon is None:
        at_horizon = _snapshot(failed, v, ever_stopped, distance, flagged_ticks, ticks)
    h_failed, h_v, h_ever, h_distance, h_flagged, h_ticks = at_horizon
    same = {} if mission_limit is None else dict(failed_same_distance=failed,
                                                 short_of_distance=~failed & ~covered)
    return MissionOutcomes(failed=h_failed, stopped=~h_failed & (h_v <= 0), ever_stopped=h_ever,
                           distance=h_distance, flagged_ticks=h_flagged, ticks=h_ticks, **same)


def _snapshot(*arrays):
    return tuple(np.array(a, copy=True) for a in arrays)


def fallback_rollouts(tables, grid, horizon, fallbacks, *, dynamics, period, monitor,
                      control_port, score_port, estimate_port=None, policy=None, truth=None,
                      carry=None, threshold=None, starts=None, mission_limit=None,
                      scores=None, alone=None, score_noise=None, seed=0) -> dict:
    """{UNGUARDED | fallback name: `MissionOutcomes`} from the swept tables of a guarded
    loop (``tables[port]`` per grid node, `reach.sweep` with ``guarded``), at every grid
    node or at ``starts``. A fallback name is a speed strategy with an optional steering
    (`systems.Fallback.parse`), with the braking and resuming rates of ``monitor`` (a
    `MonitorConfig`: also the threshold when ``threshold`` is None, and the k-of-n flag
    rule). ``control_port``, ``score_port``, ``estimate_port``: the tables' steering,
    detector score and (optional) controller's estimate; ``policy``, ``truth``,
    ``carry``: the fallback's own steering (`guarded_rollouts`). ``mission_limit``: also
    the same-distance figures. ``scores`` (per grid node) replaces the swept detector's
    scores, e.g. with a perfect detector's (`reach.guard.perfect_detector_scores`).
    ``alone``: the controller alone's outcomes from the same starts and settings when
    already computed (they do not depend on the detector), reused instead of rolled out
    again. ``score_noise``, ``seed``: the detector's variation between nodes."""
    if threshold is not None:           # given: the checkpoint's own is not needed
        monitor = dc.replace(monitor, threshold=float(threshold))
    monitor = monitor.with_checkpoint_defaults()    # a null threshold or rule: the checkpoint's
    if monitor.threshold is None:
        raise ValueError("monitor.threshold: the monitor names no checkpoint to take a "
                         "threshold from; set monitor.threshold")
    kw = dict(horizon=horizon, period=period, starts=starts, mission_limit=mission_limit)
    estimates = (tables[estimate_port] if estimate_port and estimate_port in tables.tables
                 else None)
    out = {UNGUARDED: alone if alone is not None else
           guarded_rollouts(grid, dynamics, tables[control_port], None, **kw)}
    for name in fallbacks:
        fallback = Fallback.parse(name, brake_deceleration=monitor.brake_deceleration,
                                  resume_acceleration=monitor.resume_acceleration)
        if fallback.steering == "dead_reckoning" and estimates is None:
            raise ValueError(f"fallback '{name}' needs the controller's estimate, and the "
                             f"swept tables have none ({estimate_port or 'no estimate port'})")
        out[name] = guarded_rollouts(
            grid, dynamics, tables[control_port], tables[score_port] if scores is None else scores,
            threshold=monitor.threshold,
            **dc.asdict(fallback), policy=policy, truth=truth, carry=carry,
            estimate_table=estimates, flags_needed=monitor.flags_needed,
            flag_window=monitor.flag_window, score_noise=score_noise, seed=seed, **kw)
    return out
