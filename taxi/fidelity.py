"""The taxi's real Drake closed loop (rendering at every tick) run from given starts:
the rollout function behind rollout labels and every fidelity check."""

import functools

import numpy as np

from reachwatch.diagrams import make_closed_loop_diagram, simulate
from reachwatch.reach.fidelity import Fidelity, compare_verdicts, left_box
from reachwatch.reach.fingerprint import fingerprint
from reachwatch.reach.outcomes import Outcomes, run_outcomes

from .sweeps import resolved

#: The taxi grid axes where leaving the box is not a failure (py, theta): past |px| = B
#: the run has failed, and it stops there.
OPEN_AXES = (1, 2)

_LOOPS = {}         # per process: scenario fingerprint -> (diagram, context), built once


def on_runway_starts(grid, count: int, seed: int, *, half_width: float) -> np.ndarray:
    """``count`` seeded uniform random states of ``grid``'s box with |px| < half_width
    (starts already off the runway would agree with any BRT and flatter it)."""
    rng = np.random.default_rng(seed)
    lo, hi = grid.lo.copy(), grid.hi.copy()
    lo[0], hi[0] = max(lo[0], -half_width), min(hi[0], half_width)
    return lo + rng.uniform(size=(count, grid.ndim)) * (hi - lo)


def taxi_rollouts(scenario, duration: float, grid, states) -> dict:
    """Runs the real closed loop of ``scenario`` from each start for ``duration`` s
    (stopping at failure, |px| >= B). Returns per start ``failed``, ``failure_time``
    (s, NaN if none), ``left_box`` (the run left ``grid``'s box in py or theta),
    ``max_abs_theta`` (rad) and ``ticks`` (frames rendered). Use it through
    `real_outcomes`, which caches it; ``functools.partial(taxi_rollouts, scenario,
    duration, grid)`` is a picklable rollout function for `run_outcomes`."""
    key = fingerprint(scenario)
    if key not in _LOOPS:
        diagram = make_closed_loop_diagram(scenario)
        _LOOPS[key] = diagram, diagram.CreateDefaultContext()
    diagram, context = _LOOPS[key]
    B = scenario.environment.half_width
    out = {k: [] for k in ("failed", "failure_time", "left_box", "max_abs_theta", "ticks")}
    for x in np.asarray(states, float):
        if abs(x[0]) >= B:                      # already off the runway
            row = (True, 0.0, False, abs(x[2]), 0)
        else:
            run = simulate(diagram, initial_state=x, duration=duration,
                           period=scenario.controller.period, half_width=B, context=context)
            row = (run.failed, run.failure_time, left_box(run.state, grid, axes=OPEN_AXES),
                   float(np.max(np.abs(run.state[:, 2]))),
                   len(run.time))
        for k, v in zip(out, row):
            out[k].append(v)
    return {k: np.asarray(v) for k, v in out.items()}


def real_outcomes(scenario, starts, *, grid, duration: float, cache_dir, executor=None,
                  progress=True) -> Outcomes:
    """`taxi_rollouts` from every start, cached under ``cache_dir`` by content (the
    scenario, the horizon, ``grid``'s box and the starts): a killed batch resumes, a
    repeated one costs nothing."""
    scenario = resolved(scenario)
    rollout = functools.partial(taxi_rollouts, scenario, float(duration), grid)
    return run_outcomes(rollout, starts, cache_dir=cache_dir, executor=executor,
                        progress=progress, label=scenario.environment.name)


def real_loop_fidelity(scenario, value_function, starts, *, cache_dir, duration=None,
                       executor=None, progress=True) -> Fidelity:
    """The BRT's verdicts ``V(x0) <= 0`` against the real loop from ``starts`` over
    the BRT's horizon, with the runs that left the solved box in py or theta."""
    outcomes = real_outcomes(scenario, starts, grid=value_function.grid,
                             duration=duration or value_function.horizon,
                             cache_dir=cache_dir, executor=executor, progress=progress)
    return compare_verdicts(value_function.in_brt(starts), outcomes.failed,
                            outcomes["left_box"])
