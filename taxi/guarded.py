"""Failure sets of the guarded loop, where speed becomes a state.

The image does not depend on speed, so the swept tables of steering and detector
score on the 3-D grid are enough: from every grid node at the nominal speed, the
sampled-data loop is rolled out tick by tick (steering and flag read from the tables,
speed updated by the fallback strategy, dynamics integrated with RK4 over the tick),
and a node fails if ``|px| >= B`` within the horizon."""

import numpy as np
import torch

from reachwatch.diagrams import CONTROL_PORT
from reachwatch.reach.dynamics import positive, rk4_step, split_horizon
from reachwatch.reach.grid import check_states
from reachwatch.reach.interpolate import GridInterpolator
from reachwatch.systems import STRATEGIES, next_speed

from .dynamics import dynamics_for


@torch.no_grad()
def guarded_failures(grid, dynamics, steering_table, score_table=None, *, threshold=0.5,
                      strategy="slow_down", horizon=8.0, period=0.05, substeps=2,
                      starts=None, **strategy_params):
    """Boolean failure per start (default: every grid node, C order) and the speed
    history's minimum per start. ``score_table=None`` = no detector (the controller alone)."""
    as_t = lambda a: torch.as_tensor(np.asarray(a, float), dtype=torch.float64)   # noqa: E731
    x = as_t(grid.states() if starts is None else check_states(starts, grid.ndim, "start")
             ).reshape(-1, grid.ndim)
    steer = as_t(steering_table).reshape(grid.shape)
    score = None if score_table is None else as_t(score_table).reshape(grid.shape)
    nominal = dynamics.speed
    v = torch.full((len(x),), nominal, dtype=torch.float64)
    lowest, slowest = dynamics.target(x), v.clone()
    whole, tail = split_horizon(horizon, period)
    substeps = positive("substeps", substeps, integer=True)
    for k in range(whole + (tail > 0)):       # a last partial period when it does not divide
        h = (period if k < whole else tail) / substeps
        interpolate = GridInterpolator(grid, x)
        u = interpolate(steer)[:, None]
        if score is not None:
            flagged = interpolate(score).numpy() >= threshold
            v = torch.as_tensor(next_speed(v.numpy(), flagged, strategy=strategy,
                                           nominal=nominal, period=period, **strategy_params))
        for _ in range(substeps):
            x = rk4_step(lambda y: dynamics.vector_field(y, u, speed=v), x, h)
        lowest = torch.minimum(lowest, dynamics.target(x))
        slowest = torch.minimum(slowest, v)
    return (lowest <= 0).numpy(), slowest.numpy()


#: The failure-set key of the controller alone (no detector, no fallback).
UNGUARDED = "unguarded"

def failure_sets(scenario, grid, tables, horizon, strategies=STRATEGIES):
    """{UNGUARDED | strategy: boolean failure per grid node (C order)} from the
    swept tables of the guarded diagram."""
    dynamics = dynamics_for(scenario)
    steering = tables[CONTROL_PORT]
    score = tables["anomaly_detector.score"]
    kw = dict(horizon=horizon, period=scenario.controller.period)
    out = {UNGUARDED: guarded_failures(grid, dynamics, steering, None, **kw)[0]}
    for strategy in strategies:
        out[strategy] = guarded_failures(
            grid, dynamics, steering, score, threshold=scenario.monitor.threshold,
            strategy=strategy, brake_deceleration=scenario.monitor.brake_deceleration, **kw)[0]
    return out
