"""The world diagram: `TaxiPlant` + `AircraftGeometry` + runway scene + wing camera."""

import dataclasses as dc

import numpy as np
from pydrake.geometry import MakeRenderEngineVtk, SceneGraph
from pydrake.systems.framework import Diagram, DiagramBuilder
from pydrake.systems.sensors import RgbdSensor

from reachwatch.systems import (AircraftGeometry, CameraConfig, Environment, TaxiPlant,
                                add_runway_scene, lighting_for, make_wing_camera,
                                render_engine_params)

RENDERER = "vtk"


@dc.dataclass
class World:
    """Handles to the systems `add_world` put into a builder (``plant`` is None when the
    caller brought its own plant)."""
    plant: TaxiPlant
    geometry: AircraftGeometry
    scene_graph: SceneGraph
    camera: RgbdSensor
    environment: Environment
    camera_config: CameraConfig


def initial_state_vector(initial_state) -> np.ndarray:
    """``[px m, py m, theta rad]`` from an `InitialState` (theta in degrees)."""
    return np.array([initial_state.px, initial_state.py, np.deg2rad(initial_state.theta_deg)])


def add_world(builder: DiagramBuilder, *, environment: Environment,
              camera: CameraConfig = None, shadows: bool = False,
              initial_state=(0.0, 110.0, 0.0), pose_port=None) -> World:
    """Adds plant, aircraft geometry, the environment's scene and renderer, and the
    wing camera to ``builder``; leaves the plant's inputs unconnected.

    ``pose_port``: the output port of your own plant giving the camera carrier's
    ``[px m, py m, theta rad]``; then no `TaxiPlant` is added and ``world.plant`` is None."""
    environment.validate()
    camera = (camera or CameraConfig()).validate()
    plant = None
    if pose_port is None:
        plant = builder.AddNamedSystem("taxi_plant", TaxiPlant(initial_state=initial_state))
        pose_port = plant.get_state_output_port()
    scene_graph = builder.AddNamedSystem("scene_graph", SceneGraph())
    lighting = lighting_for(environment)
    scene_graph.AddRenderer(RENDERER, MakeRenderEngineVtk(
        render_engine_params(lighting, shadows=shadows)))
    add_runway_scene(scene_graph, environment.spec(), lamps_lit=lighting.lamps_lit)
    geometry = builder.AddNamedSystem("aircraft_geometry",
                                      AircraftGeometry(scene_graph=scene_graph))
    sensor = builder.AddSystem(make_wing_camera(frame_id=geometry.frame_id, config=camera,
                                                renderer_name=RENDERER))
    builder.Connect(pose_port, geometry.get_state_input_port())
    builder.Connect(geometry.get_geometry_pose_output_port(),
                    scene_graph.get_source_pose_port(geometry.source_id))
    builder.Connect(scene_graph.get_query_output_port(), sensor.query_object_input_port())
    return World(plant, geometry, scene_graph, sensor, environment, camera)


def make_world_diagram(scenario) -> Diagram:
    """Plant + scene + camera from a `Scenario`.

    .. pydrake_system::

        name: world
        input_ports:
        - steering_angle
        - speed
        output_ports:
        - state
        - color_image
    """
    builder = DiagramBuilder()
    world = add_world(builder, environment=scenario.environment, camera=scenario.camera,
                      shadows=scenario.shadows,
                      initial_state=initial_state_vector(scenario.initial_state))
    builder.ExportInput(world.plant.get_steering_angle_input_port(), "steering_angle")
    builder.ExportInput(world.plant.get_speed_input_port(), "speed")
    builder.ExportOutput(world.plant.get_state_output_port(), "state")
    builder.ExportOutput(world.camera.color_image_output_port(), "color_image")
    diagram = builder.Build()
    diagram.set_name(f"world_{scenario.environment.name}")
    return diagram
