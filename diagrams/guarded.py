"""The safety pipeline: the TaxiNet loop guarded by the anomaly detector and the
fallback switch."""

from pydrake.systems.framework import Diagram, DiagramBuilder
from pydrake.systems.primitives import LogVectorOutput, ZeroOrderHold

from reachwatch.systems import (AnomalyDetector, FallbackSwitch, ProportionalController,
                                TrueStateEstimator)

from .checkpoints import load_detector
from .closed_loop import add_taxinet_controller
from .world import add_world, initial_state_vector

DETECTOR = "anomaly_detector"
SWITCH = "fallback_switch"


def make_guarded_diagram(scenario, *, meshcat=None) -> Diagram:
    """Plant + camera + TaxiNet + P-controller + AnomalyDetector + FallbackSwitch.

    Subsystems: ``taxi_plant``, ``taxinet``, ``p_controller``, ``anomaly_detector``,
    ``fallback_switch``, ``steering_hold``, logs ``state_log``, ``estimate_log``,
    ``speed_log``, ``anomaly_log``; with ``pipeline.steering: oracle`` also
    ``state_estimator`` and ``oracle_p_controller`` (privileged). With ``meshcat``
    (a `Meshcat`), a `MeshcatVisualizer` of the perception scene is added."""
    pipeline, controller = scenario.pipeline, scenario.controller
    if not pipeline.detector:
        raise ValueError("pipeline.detector: the guarded pipeline needs a detector "
                         "checkpoint (train one with 'reachwatch evaluate')")
    builder = DiagramBuilder()
    world = add_world(builder, environment=scenario.environment, camera=scenario.camera,
                      shadows=scenario.shadows,
                      initial_state=initial_state_vector(scenario.initial_state))
    taxinet, p_controller = add_taxinet_controller(builder, world, controller)
    model, config, metadata = load_detector(pipeline.detector)
    detector = builder.AddNamedSystem(DETECTOR, AnomalyDetector(
        model=model, config=config, threshold=pipeline.threshold,
        image_size=metadata.get("image_size")))
    switch = builder.AddNamedSystem(SWITCH, FallbackSwitch(
        strategy=pipeline.strategy, steering=pipeline.steering, period=controller.period,
        nominal_speed=controller.speed, brake_deceleration=pipeline.brake_deceleration))
    hold = builder.AddNamedSystem("steering_hold", ZeroOrderHold(controller.period, 1))
    builder.Connect(world.camera.color_image_output_port(), detector.get_color_image_input_port())
    builder.Connect(p_controller.get_steering_angle_output_port(),
                    switch.get_steering_angle_input_port())
    builder.Connect(detector.get_anomaly_output_port(), switch.get_anomaly_input_port())
    if pipeline.steering == "oracle":
        estimator = builder.AddNamedSystem("state_estimator", TrueStateEstimator())
        oracle = builder.AddNamedSystem("oracle_p_controller", ProportionalController(
            px_gain=controller.px_gain, theta_gain=controller.theta_gain))
        builder.Connect(world.plant.get_state_output_port(), estimator.get_state_input_port())
        builder.Connect(estimator.get_estimate_output_port(), oracle.get_estimate_input_port())
        builder.Connect(oracle.get_steering_angle_output_port(),
                        switch.get_fallback_steering_angle_input_port())
    builder.Connect(switch.get_steering_angle_output_port(), hold.get_input_port())
    builder.Connect(hold.get_output_port(), world.plant.get_steering_angle_input_port())
    builder.Connect(switch.get_speed_output_port(), world.plant.get_speed_input_port())
    for port, name in [(world.plant.get_state_output_port(), "state_log"),
                       (taxinet.get_estimate_output_port(), "estimate_log"),
                       (switch.get_speed_output_port(), "speed_log"),
                       (detector.get_anomaly_output_port(), "anomaly_log")]:
        LogVectorOutput(port, builder, controller.period).set_name(name)
    if meshcat is not None:
        from pydrake.geometry import MeshcatVisualizer, MeshcatVisualizerParams, Role
        MeshcatVisualizer.AddToBuilder(builder, world.scene_graph, meshcat,
                                       MeshcatVisualizerParams(role=Role.kPerception))
    diagram = builder.Build()
    diagram.set_name(f"guarded_{pipeline.strategy}")
    return diagram
