"""The BRT checked against the real Drake closed loop (rendering in the loop)."""

import numpy as np

from reachwatch.diagrams import make_closed_loop_diagram, simulate

from .sweeps import resolved


def drake_agreement(scenario, value_function, starts, *, duration=None, progress=None):
    """Runs the real Drake closed loop (rendering in the loop) from each start and
    compares "left the runway" with the BRT verdict ``V(x0) <= 0``. Returns
    ``(agreement, failed, predicted)``."""
    scenario = resolved(scenario)
    B = scenario.environment.half_width
    diagram = make_closed_loop_diagram(scenario)
    context = diagram.CreateDefaultContext()
    duration = duration or value_function.horizon
    predicted = value_function.in_brt(starts)
    failed = []
    for x in (progress(starts) if progress else starts):
        failed.append(abs(x[0]) >= B or simulate(diagram, initial_state=x, duration=duration,
                                                  period=scenario.controller.period,
                                                  half_width=B, context=context).failed)
    failed = np.array(failed)
    return float(np.mean(failed == predicted)), failed, predicted
