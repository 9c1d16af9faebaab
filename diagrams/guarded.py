"""The guarded loop: the closed loop under test watched by the anomaly detector, with
the fallback switch between the controller and the plant."""

from typing import NamedTuple

from pydrake.systems.framework import Diagram, DiagramBuilder, LeafSystem, OutputPort
from pydrake.systems.primitives import Multiplexer, ZeroOrderHold

from reachwatch.systems import (AnomalyDetector, DeadReckoning, FallbackSwitch, FlagFilter,
                                HistoryMonitor, ProportionalController, TrueStateEstimator,
                                fallback_name)
from reachwatch.systems.checks import clip, warn_once

from .checkpoints import checkpoint_kind, load_detector, load_history_monitor
from .closed_loop import add_controller, export_loop_ports
from .controller import CONTROL_OUTPUT, ESTIMATE_OUTPUT, has_estimate
from .world import add_world, initial_state_vector

DETECTOR = "anomaly_detector"
SWITCH = "fallback_switch"
FLAG_FILTER = "flag_filter"
MONITOR_SIGNALS = "monitor_signals"


class Monitor(NamedTuple):
    """The systems `add_monitor` added, and the port of the flags the switch acts on
    (the detector's own, or the `FlagFilter`'s when a k-of-n rule confirms them).
    ``detector``: an `AnomalyDetector` or a `HistoryMonitor` (of one model or an
    ensemble)."""
    detector: LeafSystem
    switch: FallbackSwitch
    anomaly: OutputPort


def add_monitor_signals(builder, *, steering_port, estimate_port=None) -> OutputPort:
    """Adds the online signals a history monitor may read, as one vector (a
    `Multiplexer` named ``monitor_signals``): the controller's ``estimate_port`` (when
    it has one) and its steering ``steering_port``. Recording and monitoring build it
    the same way, so a monitor trained on recorded runs reads the same numbers online."""
    ports = ([estimate_port] if estimate_port is not None else []) + [steering_port]
    mux = builder.AddNamedSystem(MONITOR_SIGNALS, Multiplexer([p.size() for p in ports]))
    for i, port in enumerate(ports):
        builder.Connect(port, mux.get_input_port(i))
    return mux.get_output_port(0)


def check_per_state_monitor(monitor) -> None:
    """Raise ValueError, in one line, when ``monitor`` (a `MonitorConfig`) names a
    history monitor over more than one frame: a table of one score per state (the
    guard's table rollouts) reads it on a history of that state's frame alone, which is
    not what it outputs along a run. Judge such a monitor in the guarded real loop (a
    run file's ``monitor: {kind: history}``)."""
    if not monitor.detector or checkpoint_kind(monitor.detector) != "history_monitor":
        return
    _, config, _ = load_history_monitor(monitor.detector)
    if config.frames > 1:
        raise ValueError(f"monitor.detector: {monitor.detector} is a history monitor over "
                         f"{config.frames} frames; the guard's tables hold one score per "
                         f"state, from one frame, not what it outputs along a run: judge it "
                         f"in the guarded real loop (a run file's monitor: {{kind: history}})")


def warn_other_fallback(monitor, metadata, speed=None) -> None:
    """A warning, once per checkpoint and fallback in a process, when a history monitor
    whose threshold a study fixed for braking at ``brake_deceleration`` from
    ``speed_mps`` (its metadata's) guards a loop whose fallback is not braking as hard,
    or that runs faster (``speed``, m/s: the controller's): its warnings come the
    study's lead ahead, which such a loop may not stop within, so the study's miss-rate
    bound does not speak of it."""
    trained = metadata.get("speed_mps")
    if speed is not None and trained is not None and speed > float(trained) * (1 + 1e-9):
        warn_once(f"monitor.detector: its threshold was fixed for a loop at "
                  f"{float(trained):g} m/s, warning {float(metadata.get('lead_s', 0)):g} s "
                  f"ahead; this loop runs at {speed:g} m/s, and braking from it takes "
                  f"longer: the study's miss-rate bound does not speak of it",
                  key=("faster loop", str(monitor.detector), float(speed)))
    braking = metadata.get("brake_deceleration")
    if braking is None or (monitor.strategy == "brake"
                           and monitor.brake_deceleration >= float(braking)):
        return
    this = (f"braking at {monitor.brake_deceleration:g} m/s^2" if monitor.strategy == "brake"
            else f"'{monitor.strategy}'")
    warn_once(f"monitor.detector: its threshold was fixed for a fallback braking at "
              f"{float(braking):g} m/s^2, warning {float(metadata.get('lead_s', 0)):g} s "
              f"ahead; this loop's fallback is {this}, which may need longer: the study's "
              f"miss-rate bound does not speak of it",
              key=("other fallback", str(monitor.detector), monitor.strategy,
                   monitor.brake_deceleration))


def add_detector(builder, *, image_port, monitor, period=None, steering_port=None,
                 estimate_port=None, speed=None):
    """Adds the monitor of ``monitor`` (a `MonitorConfig`: its checkpoint and threshold),
    named ``anomaly_detector``, on ``image_port``; returns it. The checkpoint is an
    image `AnomalyDetector`'s or a `HistoryMonitor`'s (of one model or an ensemble's
    members), which ticks every ``period`` s and, when trained with signals, reads the
    controller's ``estimate_port`` and ``steering_port`` through `add_monitor_signals`. Alone (no switch) it watches a
    loop without acting on it. A null threshold is the checkpoint's own
    (`MonitorConfig.with_checkpoint_defaults`). ``speed`` (m/s), the loop's, is compared
    with the one a study fixed the threshold at (`warn_other_fallback`)."""
    monitor = monitor.with_checkpoint_defaults()
    if checkpoint_kind(monitor.detector) == "history_monitor":
        model, config, metadata = load_history_monitor(monitor.detector)
        if period is None:
            raise ValueError("monitor.detector: a history monitor needs the control period")
        missing = [key for key in ("period_s", "image_size") if key not in metadata]
        if "lead_s" in metadata and missing:     # a study's, saved before they were recorded
            warn_once(f"monitor.detector: {clip(monitor.detector, 120)} is a study's monitor "
                      f"saved before its {' and '.join(missing)} were recorded, so this loop's "
                      f"are not checked against the ones it was trained at; run the study "
                      f"again to have them checked", key=("unrecorded", str(monitor.detector)))
        trained = metadata.get("period_s")
        if trained is not None and abs(float(trained) - period) > 1e-9:
            raise ValueError(f"monitor.detector: the history monitor was trained on frames "
                             f"every {float(trained):g} s and this loop ticks every "
                             f"{period:g} s: its history, flag rule and threshold count "
                             f"ticks, so they would span other times; train it at this "
                             f"period")
        if monitor.threshold < 1.0:     # it may act (threshold 1: it only watches)
            warn_other_fallback(monitor, metadata, speed)
        system = builder.AddNamedSystem(DETECTOR, HistoryMonitor(
            model=model, threshold=monitor.threshold, period=period,
            calibration=metadata.get("calibration", (1.0, 0.0)),
            image_size=metadata.get("image_size"), encoder_process=monitor.encoder_process))
        if config.signals:
            signals_port = (None if steering_port is None else add_monitor_signals(
                builder, steering_port=steering_port, estimate_port=estimate_port))
            if signals_port is None or signals_port.size() != config.signals:
                got = "none" if signals_port is None else f"{signals_port.size()}"
                raise ValueError(f"monitor.detector: the history monitor reads {config.signals} "
                                 f"online signals, this loop offers {got}")
            builder.Connect(signals_port, system.get_signals_input_port())
        builder.Connect(image_port, system.get_color_image_input_port())
        return system
    model, config, metadata = load_detector(monitor.detector)
    detector = builder.AddNamedSystem(DETECTOR, AnomalyDetector(
        model=model, config=config, threshold=monitor.threshold,
        image_size=metadata.get("image_size"), encoder_process=monitor.encoder_process,
        period=period))
    builder.Connect(image_port, detector.get_color_image_input_port())
    return detector


def add_monitor(builder, *, image_port, steering_port, monitor, controller,
                estimate_port=None) -> Monitor:
    """Adds the runtime monitor of ``monitor`` (a `MonitorConfig`) to any loop: the
    `AnomalyDetector` on ``image_port``, a `FlagFilter` (named ``flag_filter``) when
    ``monitor.flag_window`` > 1, and the `FallbackSwitch` fed by the controller's
    ``steering_port``, ticking at ``controller.period`` from ``controller.speed``.
    Returns a `Monitor`; connect the switch's ``steering_angle`` and ``speed`` outputs
    to your plant (and its ``fallback_steering_angle`` input for ``oracle``). A history
    monitor reads the controller's ``estimate_port`` (when given) and steering. A null
    threshold or k-of-n rule is the checkpoint's own (`MonitorConfig.with_checkpoint_defaults`)."""
    monitor = monitor.with_checkpoint_defaults()
    # the switch before the monitor: its tick's update, which asks the controller's
    # steering before the flag, then comes first (`HistoryMonitor` ``encoder_process``)
    switch = builder.AddNamedSystem(SWITCH, FallbackSwitch(
        fallback=monitor.fallback, nominal_speed=controller.speed, period=controller.period))
    detector = add_detector(builder, image_port=image_port, monitor=monitor,
                            period=controller.period, steering_port=steering_port,
                            estimate_port=estimate_port, speed=controller.speed)
    builder.Connect(steering_port, switch.get_steering_angle_input_port())
    anomaly = detector.get_anomaly_output_port()
    if monitor.flag_window > 1:
        confirm = builder.AddNamedSystem(FLAG_FILTER, FlagFilter(
            flags_needed=monitor.flags_needed, window=monitor.flag_window,
            period=controller.period))
        builder.Connect(anomaly, confirm.get_anomaly_input_port())
        anomaly = confirm.get_anomaly_output_port()
    builder.Connect(anomaly, switch.get_anomaly_input_port())
    return Monitor(detector, switch, anomaly)


def add_dead_reckoning(builder, *, estimate_port, anomaly_port, switch, controller,
                       wheelbase):
    """Adds the honest fallback steering to a loop with a `FallbackSwitch` whose
    steering is ``dead_reckoning``: `DeadReckoning` (named ``dead_reckoning``) on the
    controller's ``estimate_port`` ``[px m, theta deg]`` and the detector's
    ``anomaly_port``, fed back the switch's steering and speed, and the P-controller
    (``fallback_p_controller``, ``controller``'s gains) on its estimate, into the
    switch's ``fallback_steering_angle``. Returns the `DeadReckoning` system."""
    reckoning = builder.AddNamedSystem("dead_reckoning", DeadReckoning(
        period=controller.period, wheelbase=wheelbase))
    fallback = builder.AddNamedSystem("fallback_p_controller", ProportionalController(
        px_gain=controller.px_gain, theta_gain=controller.theta_gain))
    builder.Connect(estimate_port, reckoning.get_estimate_input_port())
    builder.Connect(anomaly_port, reckoning.get_anomaly_input_port())
    builder.Connect(switch.get_steering_angle_output_port(), reckoning.get_steering_angle_input_port())
    builder.Connect(switch.get_speed_output_port(), reckoning.get_speed_input_port())
    builder.Connect(reckoning.get_estimate_output_port(), fallback.get_estimate_input_port())
    builder.Connect(fallback.get_steering_angle_output_port(),
                    switch.get_fallback_steering_angle_input_port())
    return reckoning


def make_guarded_diagram(scenario, *, meshcat=None) -> Diagram:
    """Plant + camera + the scenario's controller + AnomalyDetector + FallbackSwitch.

    .. pydrake_system::

        name: guarded_loop
        output_ports:
        - state
        - estimate (when the controller has one)
        - speed
        - anomaly
        - score

    Subsystems: ``taxi_plant``, ``controller``, ``anomaly_detector``,
    ``fallback_switch``, ``steering_hold``; ``flag_filter`` with a k-of-n rule (the
    ``anomaly`` output is then the confirmed flag); with ``monitor.steering: dead_reckoning``
    also ``dead_reckoning`` (fed by the controller's ``estimate``, which must be
    ``[px m, theta deg]``) and ``fallback_p_controller``; with ``oracle`` also
    ``state_estimator`` and ``oracle_p_controller`` (privileged). With ``meshcat``
    (a `Meshcat`), a `MeshcatVisualizer` of the perception scene is added."""
    monitor, controller = scenario.monitor, scenario.controller
    if not monitor.detector:
        raise ValueError("monitor.detector: the guarded loop needs a detector "
                         "checkpoint (train one with 'reachwatch evaluate')")
    builder = DiagramBuilder()
    world = add_world(builder, environment=scenario.environment, camera=scenario.camera,
                      shadows=scenario.shadows,
                      initial_state=initial_state_vector(scenario.initial_state))
    vision = add_controller(builder, world, controller)
    detector, switch, anomaly = add_monitor(
        builder, image_port=world.camera.color_image_output_port(),
        steering_port=vision.GetOutputPort(CONTROL_OUTPUT), monitor=monitor,
        controller=controller,
        estimate_port=vision.GetOutputPort(ESTIMATE_OUTPUT) if has_estimate(vision) else None)
    hold = builder.AddNamedSystem("steering_hold", ZeroOrderHold(controller.period, 1))
    if monitor.steering == "oracle":
        estimator = builder.AddNamedSystem("state_estimator", TrueStateEstimator())
        oracle = builder.AddNamedSystem("oracle_p_controller", ProportionalController(
            px_gain=controller.px_gain, theta_gain=controller.theta_gain))
        builder.Connect(world.plant.get_state_output_port(), estimator.get_state_input_port())
        builder.Connect(estimator.get_estimate_output_port(), oracle.get_estimate_input_port())
        builder.Connect(oracle.get_steering_angle_output_port(),
                        switch.get_fallback_steering_angle_input_port())
    elif monitor.steering == "dead_reckoning":
        if not has_estimate(vision):
            raise ValueError("monitor.steering: dead_reckoning carries the controller's "
                             "'estimate' output forward, and this controller has none")
        add_dead_reckoning(builder, estimate_port=vision.GetOutputPort(ESTIMATE_OUTPUT),
                           anomaly_port=anomaly, switch=switch,
                           controller=controller, wheelbase=world.plant.wheelbase)
    builder.Connect(switch.get_steering_angle_output_port(), hold.get_input_port())
    builder.Connect(hold.get_output_port(), world.plant.get_steering_angle_input_port())
    builder.Connect(switch.get_speed_output_port(), world.plant.get_speed_input_port())
    export_loop_ports(builder, state=world.plant.get_state_output_port(),
                      estimate=(vision.GetOutputPort(ESTIMATE_OUTPUT)
                                if has_estimate(vision) else None),
                      speed=switch.get_speed_output_port(),
                      anomaly=anomaly, score=detector.get_score_output_port())
    if meshcat is not None:
        from pydrake.geometry import MeshcatVisualizer, MeshcatVisualizerParams, Role
        MeshcatVisualizer.AddToBuilder(builder, world.scene_graph, meshcat,
                                       MeshcatVisualizerParams(role=Role.kPerception))
    diagram = builder.Build()
    diagram.set_name(f"guarded_{fallback_name(monitor.strategy, monitor.steering)}")
    return diagram
