"""A Meshcat replay of a logged run as one standalone HTML file.

The recording is made in a spawned process holding the only Meshcat server: a
diagram of Python LeafSystems is not freed by Python's garbage collector while it
holds port handles, so a server added to it in this process would stay open. When
the process ends, so does the server."""

import concurrent.futures as cf
import multiprocessing

import numpy as np
from pydrake.systems.framework import DiagramBuilder

from .world import add_world


def _record(environment, camera, shadows, times, states) -> str:
    from pydrake.geometry import (Meshcat, MeshcatParams, MeshcatVisualizer,
                                  MeshcatVisualizerParams, Role)
    meshcat = Meshcat(MeshcatParams(host="127.0.0.1"))
    builder = DiagramBuilder()
    world = add_world(builder, environment=environment, camera=camera, shadows=shadows,
                      initial_state=states[0])
    visualizer = MeshcatVisualizer.AddToBuilder(builder, world.scene_graph, meshcat,
                                                MeshcatVisualizerParams(role=Role.kPerception))
    diagram = builder.Build()
    context = diagram.CreateDefaultContext()
    plant_context = world.plant.GetMyMutableContextFromRoot(context)
    visualizer.StartRecording(set_transforms_while_recording=False)
    for t, x in zip(times, states):
        context.SetTime(float(t))
        plant_context.SetContinuousState(np.asarray(x, float))
        diagram.ForcedPublish(context)
    visualizer.StopRecording()
    visualizer.PublishRecording()
    return meshcat.StaticHtml()


def meshcat_replay_html(scenario, times, states) -> str:
    """Standalone HTML replaying ``states`` [px m, py m, theta rad] at ``times`` (s) in
    ``scenario``'s environment, recorded by a Meshcat server that is closed on return."""
    times, states = np.asarray(times, float), np.asarray(states, float)
    if len(times) == 0 or len(times) != len(states):
        raise ValueError(f"a replay needs as many times as states (and at least one), got "
                         f"{len(times)} and {len(states)}")
    context = multiprocessing.get_context("spawn")
    with cf.ProcessPoolExecutor(max_workers=1, mp_context=context) as pool:
        return pool.submit(_record, scenario.environment, scenario.camera, scenario.shadows,
                           times, states).result()
