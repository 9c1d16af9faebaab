"""The closed loop under test: world + `TaxiNet` + `ProportionalController`, the
steering held for one control period (the camera renders and TaxiNet acts once per
tick), speed constant. Simulated with Drake's `Simulator`."""

import dataclasses as dc

import numpy as np
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import Diagram, DiagramBuilder, EventStatus
from pydrake.systems.primitives import ConstantVectorSource, LogVectorOutput, ZeroOrderHold

from reachwatch.systems import ProportionalController, TaxiNet, TaxiPlant, TrueStateEstimator

from .checkpoints import REFERENCE_TAXINET, load_taxinet
from .world import add_world, initial_state_vector

#: Names the sweep and the switch use to find things in a closed-loop diagram.
PLANT = "taxi_plant"
CONTROL_PORT = "p_controller.steering_angle"
ESTIMATE_PORT = "taxinet.estimate"


@dc.dataclass
class Trajectory:
    """A logged run: times (s), states [px m, py m, theta rad] and estimates
    [px_hat m, theta_hat deg] at every control tick; ``failed`` iff ``|px| >= B``."""
    time: np.ndarray
    state: np.ndarray
    estimate: np.ndarray
    half_width: float
    failed: bool
    failure_time: float = float("nan")
    speed: np.ndarray = None          # m/s per tick (guarded pipeline only)
    anomaly: np.ndarray = None        # detector flag per tick (guarded pipeline only)


def add_taxinet_controller(builder, world, controller):
    """Adds TaxiNet (from ``controller.checkpoint``, or the reference one) and the
    P-controller fed by the world's camera; returns ``(taxinet, p_controller)``."""
    model, preprocess_config, metadata = load_taxinet(controller.checkpoint or REFERENCE_TAXINET)
    image_size = metadata.get("image_size")
    taxinet = builder.AddNamedSystem("taxinet", TaxiNet(
        model=model, preprocess_config=preprocess_config, image_size=image_size))
    p_controller = builder.AddNamedSystem("p_controller", ProportionalController(
        px_gain=controller.px_gain, theta_gain=controller.theta_gain))
    builder.Connect(world.camera.color_image_output_port(),
                    taxinet.get_color_image_input_port())
    builder.Connect(taxinet.get_estimate_output_port(), p_controller.get_estimate_input_port())
    return taxinet, p_controller


def close_loop(builder, *, plant, estimate_port, p_controller, controller, name):
    """Holds the P-controller's steering for one control period, feeds the plant a
    constant speed, logs state and estimate once per tick, and builds the diagram."""
    hold = builder.AddNamedSystem("steering_hold", ZeroOrderHold(controller.period, 1))
    speed = builder.AddNamedSystem("speed", ConstantVectorSource([controller.speed]))
    builder.Connect(p_controller.get_steering_angle_output_port(), hold.get_input_port())
    builder.Connect(hold.get_output_port(), plant.get_steering_angle_input_port())
    builder.Connect(speed.get_output_port(), plant.get_speed_input_port())
    LogVectorOutput(plant.get_state_output_port(), builder, controller.period).set_name("state_log")
    LogVectorOutput(estimate_port, builder, controller.period).set_name("estimate_log")
    diagram = builder.Build()
    diagram.set_name(name)
    return diagram


def make_closed_loop_diagram(scenario) -> Diagram:
    """Plant + camera + TaxiNet + P-controller at ``scenario.controller.period``.

    Subsystems: ``taxi_plant``, ``taxinet``, ``p_controller``, ``steering_hold``
    (zero-order hold), ``speed``, ``state_log``, ``estimate_log``."""
    builder = DiagramBuilder()
    world = add_world(builder, environment=scenario.environment, camera=scenario.camera,
                      shadows=scenario.shadows,
                      initial_state=initial_state_vector(scenario.initial_state))
    taxinet, p_controller = add_taxinet_controller(builder, world, scenario.controller)
    return close_loop(builder, plant=world.plant, estimate_port=taxinet.get_estimate_output_port(),
                      p_controller=p_controller, controller=scenario.controller,
                      name="taxinet_closed_loop")


def make_state_feedback_diagram(scenario) -> Diagram:
    """The P-controller on the *true* state (no camera): privileged, for comparison
    and as the smallest example of a user closed loop the sweep accepts.

    Subsystems: ``taxi_plant``, ``state_estimator``, ``p_controller``,
    ``steering_hold``, ``speed``, ``state_log``, ``estimate_log``."""
    controller = scenario.controller
    builder = DiagramBuilder()
    plant = builder.AddNamedSystem(PLANT, TaxiPlant(
        initial_state=initial_state_vector(scenario.initial_state)))
    estimator = builder.AddNamedSystem("state_estimator", TrueStateEstimator())
    p_controller = builder.AddNamedSystem("p_controller", ProportionalController(
        px_gain=controller.px_gain, theta_gain=controller.theta_gain))
    builder.Connect(plant.get_state_output_port(), estimator.get_state_input_port())
    builder.Connect(estimator.get_estimate_output_port(), p_controller.get_estimate_input_port())
    return close_loop(builder, plant=plant, estimate_port=estimator.get_estimate_output_port(),
                      p_controller=p_controller, controller=controller,
                      name="state_feedback_closed_loop")


def start_simulator(diagram: Diagram, *, initial_state, half_width: float = 1e9,
                    stop_on_failure: bool = True, context=None):
    """A `Simulator` of a closed-loop diagram, initialised at time 0 in
    ``initial_state`` [px m, py m, theta rad] with its logs cleared and a monitor that
    ends the run at failure (``|px| >= half_width``) if asked. Returns
    ``(simulator, failure)``; ``failure`` gets ``"t"`` (s) when the monitor fires."""
    x0 = np.asarray(initial_state, float)
    if x0.shape != (3,) or not np.all(np.isfinite(x0)):
        raise ValueError(f"initial state must be 3 finite numbers [px m, py m, theta rad], "
                         f"got {np.asarray(initial_state).tolist()}")
    if not (np.isfinite(half_width) and half_width > 0):
        raise ValueError(f"half_width must be a finite number > 0 m, got {half_width}")
    plant = diagram.GetSubsystemByName(PLANT)
    simulator = Simulator(diagram, context) if context is not None else Simulator(diagram)
    context = simulator.get_mutable_context()
    diagram.SetDefaultContext(context)        # a reused context starts afresh (holds, speed)
    context.SetTime(0.0)
    plant.GetMyMutableContextFromRoot(context).SetContinuousState(x0)
    for name in ("state_log", "estimate_log", "speed_log", "anomaly_log"):
        if diagram.HasSubsystemNamed(name):
            diagram.GetSubsystemByName(name).FindMutableLog(context).Clear()
    state = plant.get_state_output_port()
    failure = {}

    def monitor(root_context):
        px = state.Eval(plant.GetMyContextFromRoot(root_context))[0]
        if stop_on_failure and abs(px) >= half_width:
            failure["t"] = root_context.get_time()
            return EventStatus.ReachedTermination(plant, "left the runway")
        return EventStatus.DidNothing()

    simulator.set_monitor(monitor)
    simulator.Initialize()
    return simulator, failure


def simulate(diagram: Diagram, *, initial_state, duration: float, half_width: float,
             stop_on_failure: bool = True, context=None) -> Trajectory:
    """Runs a closed-loop diagram from ``initial_state`` [px m, py m, theta rad] for
    ``duration`` s; stops early at failure (``|px| >= half_width``) if asked."""
    if not (np.isfinite(duration) and duration > 0):
        raise ValueError(f"duration must be a finite number > 0 s, got {duration}")
    simulator, failure = start_simulator(diagram, initial_state=initial_state,
                                         half_width=half_width,
                                         stop_on_failure=stop_on_failure, context=context)
    context = simulator.get_context()
    logs = [diagram.GetSubsystemByName(n) for n in ("state_log", "estimate_log")]
    simulator.AdvanceTo(duration)
    state_log, estimate_log = (log.FindLog(context) for log in logs)
    n = min(state_log.num_samples(), estimate_log.num_samples())
    x = state_log.data().T[:n]
    failed = bool(np.any(np.abs(x[:, 0]) >= half_width)) or "t" in failure
    t_fail = failure.get("t", float("nan"))
    if failed and np.isnan(t_fail):
        t_fail = float(state_log.sample_times()[np.argmax(np.abs(x[:, 0]) >= half_width)])
    extra = {}
    for name, field in [("speed_log", "speed"), ("anomaly_log", "anomaly")]:
        if diagram.HasSubsystemNamed(name):
            extra[field] = diagram.GetSubsystemByName(name).FindLog(context).data()[0, :n]
    return Trajectory(time=state_log.sample_times()[:n], state=x,
                      estimate=estimate_log.data().T[:n], half_width=half_width,
                      failed=failed, failure_time=t_fail, **extra)
