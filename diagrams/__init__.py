"""Diagrams built from a `Scenario`, simulation helpers and graph export."""

from .graph import GraphvizMissing, export_graph
from .render import StateRenderer, check_state
from .scenario import InitialState, Scenario, ScenarioError, dump_scenario, load_scenario
from .world import World, add_world, initial_state_vector, make_world_diagram

__all__ = ["GraphvizMissing", "export_graph", "StateRenderer", "check_state",
           "InitialState", "Scenario", "ScenarioError", "dump_scenario", "load_scenario",
           "World", "add_world", "initial_state_vector", "make_world_diagram"]
