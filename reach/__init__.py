"""Reachability: grids, sweeps of a closed-loop diagram, the HJB-VI solver, BRT queries
and rollout validation."""

import reachwatch.systems  # noqa: F401  (first: process-wide settings before torch)

from .closed_loop import (GUARDED_PROBE, drake_agreement, resolved, sweep_closed_loop,
                          sweep_guarded, sweep_key, taxi_dynamics)
from .dynamics import Dynamics, TaxiDynamics
from .grid import Grid, GridSpec
from .guarded import pipeline_failures
from .rollouts import min_target_along_rollouts, sign_agreement
from .solver import ACCURACIES, solve_brt
from .sweep import InlineExecutor, Probe, SweepTable, default_executor, sweep
from .value_function import ValueFunction

__all__ = ["GUARDED_PROBE", "sweep_guarded", "drake_agreement", "resolved", "sweep_closed_loop", "sweep_key", "taxi_dynamics",
           "Dynamics", "TaxiDynamics", "Grid", "GridSpec", "pipeline_failures", "min_target_along_rollouts",
           "sign_agreement", "ACCURACIES", "solve_brt", "InlineExecutor", "Probe",
           "SweepTable", "default_executor", "sweep", "ValueFunction"]
