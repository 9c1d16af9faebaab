"""The taxi application of reachwatch: the taxi dynamics and grid, the sweeps of the
closed and guarded loops of any controller on the taxi plant, failure sets with a fallback, BRT slice plots and
the check against the real Drake loop. Built on the generic `reachwatch.reach`."""

from .dynamics import OffRunway, TaxiDynamics, dynamics_for
from .fidelity import mission_rollouts, on_runway_starts, real_loop_fidelity, real_missions
from .grid import TaxiGridSpec, paper_grid
from .guarded import UNGUARDED, taxi_fallback_rollouts, taxi_guarded_rollouts, p_controller_policy
from .guarded_run import simulate_guarded
from .application import TAXI_APPLICATION, TaxiApplication
from .sweeps import (refine_closed_loop, resolved, steering_bounds, taxi_probe, sweep_closed_loop,
                     sweep_guarded, taxi_sweep_key)

__all__ = ["OffRunway", "TAXI_APPLICATION", "TaxiApplication", "TaxiDynamics", "dynamics_for", "on_runway_starts", "real_loop_fidelity", "TaxiGridSpec", "paper_grid",
           "UNGUARDED", "taxi_fallback_rollouts", "taxi_guarded_rollouts",
           "p_controller_policy", "mission_rollouts", "real_missions", "simulate_guarded", "refine_closed_loop", "resolved", "steering_bounds", "taxi_probe", "sweep_closed_loop",
           "sweep_guarded", "taxi_sweep_key"]
