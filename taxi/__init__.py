"""The TaxiNet application of reachwatch: the taxi dynamics and grid, the sweeps of the
TaxiNet and guarded closed loops, failure sets with a fallback, BRT slice plots and
the check against the real Drake loop. Built on the generic `reachwatch.reach`."""

from .dynamics import TaxiDynamics, dynamics_for
from .fidelity import drake_agreement
from .grid import TaxiGridSpec, paper_grid
from .guarded import failure_sets, guarded_failures
from .guarded_run import simulate_guarded
from .sweeps import (GUARDED_PROBE, TAXI_PROBE, resolved, sweep_closed_loop, sweep_guarded,
                     taxi_sweep_key)

__all__ = ["TaxiDynamics", "dynamics_for", "drake_agreement", "TaxiGridSpec", "paper_grid",
           "failure_sets", "guarded_failures", "simulate_guarded", "GUARDED_PROBE", "TAXI_PROBE", "resolved", "sweep_closed_loop",
           "sweep_guarded", "taxi_sweep_key"]
