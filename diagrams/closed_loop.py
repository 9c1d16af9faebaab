"""The closed loop under test: world + a vision controller (TaxiNet + P-controller by
default, or any system `reachwatch.diagrams.controller` accepts), the steering held
for one control period (the camera renders and the controller acts once per tick),
speed constant. Simulated with Drake's `Simulator`.

What `simulate` needs from a loop is declared by the diagram's exported output ports,
never by subsystem names: ``state`` (the plant state; the loop's continuous state is
the plant's), and optionally ``estimate``, ``speed`` and ``anomaly``."""

import dataclasses as dc

import numpy as np
from pydrake.geometry import SceneGraph
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import Diagram, DiagramBuilder, EventStatus, PortDataType
from pydrake.systems.primitives import ConstantVectorSource, ZeroOrderHold

from reachwatch.systems import ProportionalController, TaxiPlant, TrueStateEstimator

from .controller import CONTROL_OUTPUT, ESTIMATE_OUTPUT, IMAGE_INPUT, has_estimate, make_controller
from .finite_derivatives import check_finite_derivatives, leaf_systems, non_finite_message
from .world import add_world, initial_state_vector

#: Names the taxi sweeps use to find things in the closed-loop diagrams built here.
PLANT = "taxi_plant"
CONTROLLER = "controller"
CONTROL_PORT = f"{CONTROLLER}.{CONTROL_OUTPUT}"
ESTIMATE_PORT = f"{CONTROLLER}.{ESTIMATE_OUTPUT}"
#: The output ports a loop exports for `simulate` (``state`` required).
LOOP_OUTPUTS = ("state", "estimate", "speed", "anomaly", "score")


@dc.dataclass
class Trajectory:
    """A logged run: times (s), plant states and the controller's estimates (``(n, 0)``
    when it declares none) at every control tick; ``failed`` iff the run's failure rule
    (`simulate`'s ``failed``) held at a logged state or ended the run between ticks."""
    time: np.ndarray
    state: np.ndarray
    estimate: np.ndarray
    failed: bool
    failure_time: float = float("nan")
    speed: np.ndarray = None          # m/s per tick (loops exporting ``speed``)
    anomaly: np.ndarray = None        # detector flag per tick (loops exporting ``anomaly``)
    score: np.ndarray = None          # detector score per tick (loops exporting ``score``)
    records: dict = None              # `simulate`'s ``record``: name -> array, a row per tick


def add_controller(builder, world, controller):
    """Adds the controller ``controller`` (a `ControllerConfig`) names as the subsystem
    ``controller``, fed by the world's camera; returns it."""
    system = builder.AddNamedSystem(CONTROLLER, make_controller(controller))
    builder.Connect(world.camera.color_image_output_port(), system.GetInputPort(IMAGE_INPUT))
    return system


def export_loop_ports(builder, *, state, estimate=None, speed=None, anomaly=None, score=None):
    """Exports the output ports `simulate` reads (those given)."""
    for name, port in zip(LOOP_OUTPUTS, (state, estimate, speed, anomaly, score)):
        if port is not None:
            builder.ExportOutput(port, name)


def close_loop(builder, *, plant, steering, estimate, controller, name, before_build=None):
    """Holds ``steering`` for one control period, feeds the plant a constant speed,
    exports ``state`` (and ``estimate`` when given), calls ``before_build(builder)``
    when given, and builds the diagram."""
    hold = builder.AddNamedSystem("steering_hold", ZeroOrderHold(controller.period, 1))
    speed = builder.AddNamedSystem("speed", ConstantVectorSource([controller.speed]))
    builder.Connect(steering, hold.get_input_port())
    builder.Connect(hold.get_output_port(), plant.get_steering_angle_input_port())
    builder.Connect(speed.get_output_port(), plant.get_speed_input_port())
    export_loop_ports(builder, state=plant.get_state_output_port(), estimate=estimate)
    if before_build is not None:
        before_build(builder)
    diagram = builder.Build()
    diagram.set_name(name)
    return diagram


def make_closed_loop_diagram(scenario, *, prebuild_callback=None) -> Diagram:
    """Plant + camera + the scenario's controller at ``scenario.controller.period``.

    .. pydrake_system::

        name: closed_loop
        output_ports:
        - state
        - estimate (when the controller has one)

    Subsystems: ``taxi_plant``, ``controller``, ``steering_hold`` (zero-order hold),
    ``speed``, and the world's scene graph, geometry and camera.

    ``prebuild_callback(builder, world)``, when given, is called just before the
    diagram is built, with the `World` handles: add your own systems there (e.g. an
    observer on ``world.camera``) and export their ports (``score`` is read by
    `simulate`)."""
    builder = DiagramBuilder()
    world = add_world(builder, environment=scenario.environment, camera=scenario.camera,
                      shadows=scenario.shadows,
                      initial_state=initial_state_vector(scenario.initial_state))
    controller = add_controller(builder, world, scenario.controller)
    return close_loop(builder, plant=world.plant,
                      steering=controller.GetOutputPort(CONTROL_OUTPUT),
                      estimate=(controller.GetOutputPort(ESTIMATE_OUTPUT)
                                if has_estimate(controller) else None),
                      controller=scenario.controller, name="closed_loop",
                      before_build=(None if prebuild_callback is None else
                                    lambda builder: prebuild_callback(builder, world)))


def make_state_feedback_diagram(scenario) -> Diagram:
    """The P-controller on the *true* state (no camera): privileged, for comparison
    and as the smallest example of a user closed loop the sweep accepts.

    Subsystems: ``taxi_plant``, ``state_estimator``, ``p_controller``,
    ``steering_hold``, ``speed``; outputs ``state``, ``estimate``."""
    controller = scenario.controller
    builder = DiagramBuilder()
    plant = builder.AddNamedSystem(PLANT, TaxiPlant(
        initial_state=initial_state_vector(scenario.initial_state)))
    estimator = builder.AddNamedSystem("state_estimator", TrueStateEstimator())
    p_controller = builder.AddNamedSystem("p_controller", ProportionalController(
        px_gain=controller.px_gain, theta_gain=controller.theta_gain))
    builder.Connect(plant.get_state_output_port(), estimator.get_state_input_port())
    builder.Connect(estimator.get_estimate_output_port(), p_controller.get_estimate_input_port())
    return close_loop(builder, plant=plant, steering=p_controller.get_steering_angle_output_port(),
                      estimate=estimator.get_estimate_output_port(), controller=controller,
                      name="state_feedback_closed_loop")


def _output(diagram, name, required=False):
    if diagram.HasOutputPort(name):
        return diagram.GetOutputPort(name)
    if required:
        outputs = [diagram.get_output_port(i).get_name() for i in range(diagram.num_output_ports())]
        raise ValueError(f"the loop '{diagram.get_name()}' must export an output port '{name}' "
                         f"(the plant state); it exports {outputs}")
    return None


def reset_context(diagram: Diagram, context):
    """``diagram.SetDefaultContext(context)``, but for the `SceneGraph`s: their state (the
    geometry and its render engines) is kept. No system of a loop changes it while the
    loop runs, and resetting it clones every render engine: at 200x360 that cost about
    as much as four renders per run, and the fresh clone's first frame rendered slower
    again."""
    for system in diagram.GetSystems():
        if isinstance(system, SceneGraph):
            continue
        if isinstance(system, Diagram):
            reset_context(system, context)
        else:
            system.SetDefaultContext(system.GetMyMutableContextFromRoot(context))


#: The attribute on a diagram that keeps the Context `loop_context` made for it.
_LOOP_CONTEXT = "_reachwatch_loop_context"


def loop_context(diagram: Diagram):
    """The Context a run of ``diagram`` given no Context of its own runs in: made on
    first use and kept on the diagram, so that runs of one diagram reuse it. Each
    Context of a diagram holds its own clone of the render engine, and clones of one
    engine spoil each other's frames. Measured on KSFO at 21 h, overcast: the second
    `simulate` of one loop, in a new Context, left the run of a fresh diagram from the
    same start 4.2 s in (TaxiNet's estimate off by up to 4.2, the path by 1.6 cm); in
    the reused Context it was the same run, to the bit."""
    context = getattr(diagram, _LOOP_CONTEXT, None)
    if context is None:
        context = diagram.CreateDefaultContext()
        setattr(diagram, _LOOP_CONTEXT, context)
    return context


def _checked_rule(failed):
    """``failed`` checked: None (a run never fails) or a function of states ``(n, d)``
    returning ``(n,)`` bools, as `reachwatch.reach.Application.failed` of one scenario
    (the taxi's: `reachwatch.taxi.OffRunway`); a ValueError naming what was given
    otherwise."""
    if failed is not None and not callable(failed):
        raise ValueError(f"failed must be a function of the plant states (n, d) returning n "
                         f"bools, or None, got {type(failed).__name__}")
    return failed


def failed_at(failed, states) -> np.ndarray:
    """The failure rule ``failed`` (`_checked_rule`; None: never) of the states
    ``(n, d)``: ``(n,)`` bools, or a ValueError when the rule gives another shape."""
    states = np.asarray(states, float)
    if failed is None:
        return np.zeros(len(states), bool)
    out = np.asarray(failed(states), bool)
    if out.shape != (len(states),):
        raise ValueError(f"failed gave shape {out.shape} for {len(states)} states; a failure "
                         f"rule maps states (n, d) to n bools")
    return out


def state_failed(failed, x) -> bool:
    """The failure rule ``failed`` (`failed_at`) of one state ``x``."""
    return bool(failed_at(failed, np.asarray(x, float)[None])[0])


def start_simulator(diagram: Diagram, *, initial_state, failed=None,
                    stop_on_failure: bool = True, context=None):
    """A `Simulator` of a closed-loop diagram, initialised at time 0 from its default
    context with its continuous state (the plant's) set to ``initial_state`` and a
    monitor that ends the run at the first step where ``failed`` (`_checked_rule`: a
    function of plant states; None: never) holds of the state, if asked.
    ``context``: the Context to run in (reset first); None: the diagram's own
    (`loop_context`), so runs of one diagram without one run one after another, not
    interleaved. Its Python plants refuse, in one line, a state derivative that stays
    not finite however short the integrator's steps (`check_finite_derivatives`; the
    monitor tells them each step). Returns ``(simulator, failure)``;
    ``failure`` gets ``"t"`` (s) when the monitor fires."""
    x0 = np.asarray(initial_state, float)
    if x0.ndim != 1 or not np.all(np.isfinite(x0)):
        raise ValueError(f"initial state must be a vector of finite numbers (the plant's "
                         f"state), got {np.asarray(initial_state).tolist()}")
    failed = _checked_rule(failed)
    state = _output(diagram, "state", required=True)
    checks = check_finite_derivatives(diagram)      # a NaN one would hang the integrator
    simulator = Simulator(diagram, loop_context(diagram) if context is None else context)
    context = simulator.get_mutable_context()
    reset_context(diagram, context)           # a reused context starts afresh (holds, speed)
    context.SetTime(0.0)
    size = context.num_continuous_states()
    if size != len(x0):
        raise ValueError(f"the loop '{diagram.get_name()}' has {size} continuous states (its "
                         f"plant's), the initial state {len(x0)} numbers")
    context.SetContinuousState(x0)
    failure = {}

    watched = stop_on_failure and failed is not None

    def monitor(root_context):          # after each step the integrator accepted
        checks.stepped(root_context)
        if watched and state_failed(failed, state.Eval(root_context)):
            failure["t"] = root_context.get_time()
            return EventStatus.ReachedTermination(diagram, "failed")
        return EventStatus.DidNothing()

    checks.start()
    if watched or len(checks):
        simulator.set_monitor(monitor)
    simulator.Initialize()
    return simulator, failure


def tick_times(duration: float, period: float) -> np.ndarray:
    """The control ticks ``0, period, 2 period, ...`` up to ``duration`` s."""
    if not (np.isfinite(duration) and duration > 0):
        raise ValueError(f"duration must be a finite number > 0 s, got {duration}")
    if not (np.isfinite(period) and period > 0):
        raise ValueError(f"period must be a finite number > 0 s, got {period}")
    return np.arange(int(np.floor(duration / period + 1e-9)) + 1) * period


def _holds(diagram: Diagram) -> list:
    """The `ZeroOrderHold` systems of ``diagram``, its sub-diagrams' included."""
    return [system for system in leaf_systems(diagram) if isinstance(system, ZeroOrderHold)]


class LoopRun:
    """One run of `simulate`, advanced a control tick at a time: `advance` steps the
    Simulator to the next tick, `sample` reads the exported ports there, `trajectory`
    returns the run. `simulate` is ``while run.advance(): run.sample()``; a caller may
    interleave several runs (`reachwatch.diagrams.lockstep`) and compute things at a
    tick between the two calls. Arguments are `simulate`'s."""

    def __init__(self, diagram: Diagram, *, initial_state, duration: float, period: float,
                 failed=None, stop_on_failure: bool = True, context=None,
                 stop_when=None, record=None):
        self.times = tick_times(duration, period)
        self.duration, self.stop_when = duration, stop_when
        self.rule = _checked_rule(failed)
        self.simulator, self.failure = start_simulator(
            diagram, initial_state=initial_state, failed=failed,
            stop_on_failure=stop_on_failure, context=context)
        self.context = self.simulator.get_context()
        self.ports = {name: _output(diagram, name) for name in LOOP_OUTPUTS}
        self.rows = {name: [] for name, port in self.ports.items() if port is not None}
        self.record = dict(record or {})
        for name in self.record:
            if not diagram.HasOutputPort(name):
                raise ValueError(f"record: the loop '{diagram.get_name()}' exports no output "
                                 f"port '{name}'")
        self.recorded = {name: [] for name in self.record}
        self.record_ports = {name: diagram.GetOutputPort(name) for name in self.record}
        # the holds that latch at the control ticks, checked before each step
        # (`_check_derivatives`); and whether a failure between ticks is watched for
        holds = _holds(diagram)
        self.holds = [h for h in holds if abs(h.period() - period) <= 1e-12
                      and abs(h.offset()) <= 1e-12]
        # a loop whose commands are all held at another period runs at that period,
        # where its tables, BRT and rollouts take `period` (holds of images, such as a
        # discrete camera's, are no commands)
        commands = [h for h in holds
                    if h.get_input_port().get_data_type() == PortDataType.kVectorValued]
        if commands and not [h for h in commands if h in self.holds]:
            latched = sorted({f"{h.period():g} s" + (f" from {h.offset():g} s" if h.offset()
                                                       else "") for h in commands})
            raise ValueError(f"the loop '{diagram.get_name()}' holds its commands every "
                             f"{', '.join(latched)}, and the control period "
                             f"(scenario.controller.period) is {period:g} s from 0 s, which "
                             f"its tables and BRT are computed at: build the loop's holds "
                             f"from it")
        self.watched = stop_on_failure and failed is not None
        self.tick = 0                    # the index in ``times`` of the next tick
        self.done = False

    def advance(self) -> bool:
        """Steps to the next tick; False (and `done`) when the run has ended: every tick
        logged, stopped after the last sample, or stopped between ticks (failure). After
        the last tick, a duration that is not a whole number of periods is simulated to
        its end when failures are watched between ticks (``stop_on_failure`` with a
        rule; no tick falls there, so nothing is sampled), so that a failure in that
        last part of a period counts, as it does in the BRT and the table rollouts."""
        if self.done or self.tick >= len(self.times):
            if (not self.done and self.watched
                    and self.times[-1] < self.duration - 1e-9 * max(1.0, self.duration)):
                self._check_derivatives()
                self.simulator.AdvanceTo(self.duration)
            self.done = True
            return False
        t = self.times[self.tick]
        if t > 0:
            self._check_derivatives()
            self.simulator.AdvanceTo(min(t, self.duration))
        if "t" in self.failure and self.context.get_time() < t - 1e-12:
            self.done = True             # stopped between ticks: no sample at t
            return False
        return True

    def _check_derivatives(self):
        """A ValueError in one line when the loop is about to integrate NaN or inf: the
        value a zero-order hold of the control period latches at this tick (the
        controller's new command, which the next step applies first; the step reads the
        same cached port), or the state derivative now (a controller that feeds the
        plant directly), naming the system whose derivative it is
        (`non_finite_message`). Drake's error-controlled integrator would step forever
        on a NaN derivative (RobotLocomotion/drake#12647) in a plant that does not check
        its inputs. A Python plant's derivative that turns NaN between ticks is refused
        where the integrator cannot get past it (`check_finite_derivatives`); a C++
        plant's is not seen there."""
        loop = self.simulator.get_system()
        name = f" '{loop.get_name()}'" if loop.get_name() else ""
        for hold in self.holds:
            value = hold.get_input_port().Eval(hold.GetMyContextFromRoot(self.context))
            if isinstance(value, np.ndarray) and not np.all(np.isfinite(value)):
                raise ValueError(
                    f"the loop{name}: its hold '{hold.get_name()}' would take "
                    f"{value.tolist()} at t = {self.context.get_time():.3f} s, not finite: "
                    f"does the controller output NaN or inf there?")
        derivative = loop.EvalTimeDerivatives(self.context).CopyToVector()
        if not np.all(np.isfinite(derivative)):
            raise ValueError(non_finite_message(loop, self.context) or (
                f"the loop{name}: its state derivative is "
                f"{derivative.tolist()} at t = {self.context.get_time():.3f} s, not finite: "
                f"does the controller output NaN or inf there?"))

    def sample(self):
        """Reads the exported ports (and ``record``) at the tick `advance` reached."""
        for name in self.rows:
            self.rows[name].append(self.ports[name].Eval(self.context).copy())
        for name, fn in self.record.items():
            self.recorded[name].append(np.asarray(fn(self.record_ports[name].Eval(self.context))))
        self.tick += 1
        if "t" in self.failure or (self.stop_when is not None and self.stop_when(self.rows)):
            self.done = True

    def trajectory(self) -> Trajectory:
        """The run logged so far."""
        rows, times = self.rows, self.times
        n = len(rows["state"])
        x = np.array(rows["state"]).reshape(n, -1)
        at = failed_at(self.rule, x) if n else np.zeros(0, bool)
        failed = bool(np.any(at)) or "t" in self.failure
        t_fail = self.failure.get("t", float("nan"))
        if failed and np.isnan(t_fail):
            t_fail = float(times[np.argmax(at)])
        estimate = (np.array(rows["estimate"]).reshape(n, -1) if "estimate" in rows
                    else np.zeros((n, 0)))
        extra = {name: np.array(rows[name]).reshape(n, -1)[:, 0]
                 for name in ("speed", "anomaly", "score") if name in rows}
        return Trajectory(time=times[:n], state=x, estimate=estimate, failed=failed,
                          failure_time=t_fail,
                          records=({k: np.stack(v) for k, v in self.recorded.items()}
                                   if self.record else None),
                          **extra)


def simulate(diagram: Diagram, *, initial_state, duration: float, period: float,
             failed=None, stop_on_failure: bool = True, context=None,
             stop_when=None, record=None) -> Trajectory:
    """Runs a closed-loop diagram from ``initial_state`` for ``duration`` s and reads its
    exported ports (``state``; ``estimate``, ``speed``, ``anomaly`` when exported) at
    every control tick (every ``period`` s); stops early at failure if asked (the first
    step where ``failed``, a function of plant states ``(n, d)`` -> ``(n,)`` bools,
    holds; None: the run never fails), and after the tick where ``stop_when(rows)`` is
    true, if given (``rows``: {port name: list of the values read so far, one per tick}).

    ``record`` ({exported output port name: function of its value}) reads more ports at
    every tick, e.g. ``{"color_image": lambda image: image.data.copy()}``; the results
    are stacked in ``Trajectory.records``. `LoopRun` is the same run a tick at a time."""
    run = LoopRun(diagram, initial_state=initial_state, duration=duration, period=period,
                  failed=failed, stop_on_failure=stop_on_failure, context=context,
                  stop_when=stop_when, record=record)
    while run.advance():
        run.sample()
    return run.trajectory()
