"""Reachability for any closed loop: N-dimensional grids, sweeps of a closed-loop
diagram, the HJB-VI solver, BRT queries and rollout validation. Nothing here knows
about runways: applications are built on it, outside it."""

import reachwatch.systems  # noqa: F401  (first: process-wide settings before torch)

from .dynamics import Dynamics
from .fidelity import Fidelity, compare_verdicts, left_box, select_map, wilson_interval
from .fingerprint import Unfingerprintable, fingerprint
from .grid import Grid
from .robust import local_range
from .rollouts import min_target_along_rollouts, sign_agreement
from .solver import ACCURACIES, solve_brt
from .sweep import (RESPAWNS, InlineExecutor, Probe, RespawningPool, SweepTable,
                    default_executor, stop_executor, sweep, sweep_key)
from .value_function import ValueFunction

__all__ = ["Dynamics", "Fidelity", "compare_verdicts", "left_box", "select_map", "wilson_interval", "Unfingerprintable", "fingerprint", "Grid", "local_range", "min_target_along_rollouts",
           "sign_agreement", "ACCURACIES", "solve_brt", "InlineExecutor", "Probe", "RESPAWNS",
           "RespawningPool", "SweepTable",
           "default_executor", "stop_executor", "sweep", "sweep_key", "ValueFunction"]
