"""The BRT checked against the real Drake closed loop (rendering at every tick)."""

import numpy as np

from reachwatch.diagrams import make_closed_loop_diagram, simulate
from reachwatch.reach.fidelity import Fidelity, compare_verdicts, left_box

from .sweeps import resolved

#: The taxi grid axes where leaving the box is not a failure (py, theta): past |px| = B
#: the run has failed, and it stops there.
OPEN_AXES = (1, 2)


def on_runway_starts(grid, count: int, seed: int, *, half_width: float) -> np.ndarray:
    """``count`` seeded uniform random states of ``grid``'s box with |px| < half_width
    (starts already off the runway would agree with any BRT and flatter it)."""
    rng = np.random.default_rng(seed)
    lo, hi = grid.lo.copy(), grid.hi.copy()
    lo[0], hi[0] = max(lo[0], -half_width), min(hi[0], half_width)
    return lo + rng.uniform(size=(count, grid.ndim)) * (hi - lo)


def real_loop_fidelity(scenario, value_function, starts, *, duration=None,
                       progress=None) -> Fidelity:
    """Runs the real Drake closed loop from each start for the BRT's horizon and
    compares "left the runway" with the verdict ``V(x0) <= 0``; counts the runs that
    left the solved box in py or theta. Returns the `Fidelity`."""
    scenario = resolved(scenario)
    B = scenario.environment.half_width
    diagram = make_closed_loop_diagram(scenario)
    context = diagram.CreateDefaultContext()
    duration = duration or value_function.horizon
    predicted = value_function.in_brt(starts)
    failed, left = [], []
    for x in (progress(starts) if progress else starts):
        if abs(x[0]) >= B:
            failed.append(True)
            left.append(False)
            continue
        run = simulate(diagram, initial_state=x, duration=duration,
                       period=scenario.controller.period, half_width=B, context=context)
        failed.append(run.failed)
        left.append(left_box(run.state, value_function.grid, axes=OPEN_AXES))
    return compare_verdicts(predicted, failed, left)
