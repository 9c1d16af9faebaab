"""Diagrams built from a `Scenario`, simulation helpers and graph export."""

import reachwatch.systems  # noqa: F401  (first: sets process-wide settings before torch loads)

from .checkpoints import (REFERENCE_TAXINET, CheckpointError, file_hash, load_checkpoint,
                          load_detector, load_taxinet, save_checkpoint)
from .closed_loop import (CONTROL_PORT, CONTROLLER, ESTIMATE_PORT, PLANT, Trajectory,
                          add_controller, export_loop_ports, make_closed_loop_diagram,
                          loop_context, make_state_feedback_diagram, simulate, start_simulator,
                          tick_times)
from .controller import (ControllerProbe, TaxiNetController, check_controller, make_controller,
                         make_taxinet_controller, resolve_factory)
from .guarded import (DETECTOR, FLAG_FILTER, SWITCH, Monitor, add_dead_reckoning, add_detector,
                      add_monitor, check_per_state_monitor, make_guarded_diagram)
from .graph import GraphvizMissing, export_graph
from .render import StateRenderer, check_state, render_at_states, write_png
from .scenario import ControllerConfig, InitialState, MonitorConfig, Scenario, ScenarioError, dump_scenario, load_scenario
from .timing import paired_rates
from .world import World, add_world, initial_state_vector, make_world_diagram

__all__ = ["REFERENCE_TAXINET", "CheckpointError", "file_hash", "load_checkpoint",
           "load_detector", "load_taxinet", "save_checkpoint", "CONTROL_PORT", "CONTROLLER", "ESTIMATE_PORT", "PLANT",
           "Trajectory", "add_controller", "export_loop_ports", "make_closed_loop_diagram",
           "loop_context", "make_state_feedback_diagram", "simulate", "start_simulator",
           "tick_times",
           "ControllerProbe", "TaxiNetController", "check_controller", "make_controller",
           "make_taxinet_controller", "resolve_factory",
           "ControllerConfig", "MonitorConfig", "DETECTOR", "FLAG_FILTER", "Monitor", "SWITCH", "add_dead_reckoning", "add_detector", "check_per_state_monitor", "add_monitor", "make_guarded_diagram", "GraphvizMissing", "export_graph", "StateRenderer", "check_state", "render_at_states", "write_png",
           "InitialState", "Scenario", "ScenarioError", "dump_scenario", "load_scenario",
           "paired_rates", "World", "add_world", "initial_state_vector", "make_world_diagram"]
