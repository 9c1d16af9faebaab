"""Recorded real-loop runs of the taxi for a monitor over the image history: at every
control tick the camera frame (resized to the monitor's input), the online signals a
monitor may read (`reachwatch.diagrams.guarded.add_monitor_signals`: the controller's
estimate and steering) and the state, with the run's failure time. Time-to-failure
labels come from these by `reachwatch.reach.outcomes.time_to_failure`."""

import functools

import numpy as np

from reachwatch.diagrams import CONTROLLER, make_closed_loop_diagram, simulate
from reachwatch.diagrams.controller import CONTROL_OUTPUT, ESTIMATE_OUTPUT, has_estimate
from reachwatch.diagrams.guarded import add_monitor_signals
from reachwatch.reach.outcomes import map_states, put_recording, recording_fields
from reachwatch.systems import DetectorConfig, resize_for_detector

from .dynamics import OffRunway
from .fidelity import _loop, export_watching_detector, watching, without_monitor

#: The exported ports of `make_recording_loop` beside ``state`` and ``estimate``.
FRAME_PORT, SIGNALS_PORT = "color_image", "monitor_signals"


def make_recording_loop(scenario, *, scored: bool = False):
    """The controller alone's closed loop, also exporting the camera's ``color_image``
    and the ``monitor_signals`` a history monitor reads online; ``scored``: and the
    ``score`` of the detector of ``scenario.monitor`` watching it, acting on nothing
    (`fidelity.export_watching_detector`)."""
    def export(builder, world):
        controller = builder.GetSubsystemByName(CONTROLLER)
        builder.ExportOutput(world.camera.color_image_output_port(), FRAME_PORT)
        builder.ExportOutput(add_monitor_signals(
            builder, steering_port=controller.GetOutputPort(CONTROL_OUTPUT),
            estimate_port=(controller.GetOutputPort(ESTIMATE_OUTPUT)
                           if has_estimate(controller) else None)), SIGNALS_PORT)
        if scored:
            export_watching_detector(builder, world, scenario)
    return make_closed_loop_diagram(scenario, prebuild_callback=export)


def make_scored_recording_loop(scenario):
    """`make_recording_loop` with the detector's ``score`` (a thread keeps it apart)."""
    return make_recording_loop(scenario, scored=True)


def record_runs(scenario, duration: float, height: int, width: int, states, *,
                scored: bool = False) -> dict:
    """Runs the real closed loop of ``scenario`` from each start for ``duration`` s
    (stopping at failure) and records every control tick. Per start: ``frames`` uint8
    ``(T, height, width, 3)``, ``signals`` ``(T, m)``, ``state`` ``(T, 3)`` (zeros /
    NaN after the run ended), ``ticks``, ``failed`` and ``failure_time`` (s, NaN for
    none); ``T`` is the horizon's tick count. ``scored``: also ``score`` ``(T,)`` (NaN
    after the run ended), the detector of ``scenario.monitor`` on the same frames
    (`make_recording_loop`). ``functools.partial(record_runs, scenario, duration,
    height, width)`` is a picklable rollout function."""
    diagram, context = _loop(scenario, make_scored_recording_loop if scored
                             else make_recording_loop)
    size = DetectorConfig(height=height, width=width)
    period, off = scenario.controller.period, OffRunway(scenario.environment.half_width)
    length = int(np.floor(duration / period + 1e-9)) + 1
    states = np.asarray(states, float)
    out = recording_fields(len(states), length, height, width,
                           diagram.GetOutputPort(SIGNALS_PORT).size(), states.shape[1],
                           scored=scored)
    frame = functools.partial(_resized, size)
    gone = off(states)
    for i, x in enumerate(states):
        if gone[i]:                              # already off the runway: no run
            put_recording(out, i, failed=True, failure_time=0.0)
            continue
        run = simulate(diagram, initial_state=x, duration=duration, period=period,
                       failed=off, context=context,
                       record={FRAME_PORT: frame, SIGNALS_PORT: np.copy})
        put_recording(out, i, frames=run.records[FRAME_PORT],
                      signals=run.records[SIGNALS_PORT], state=run.state,
                      score=run.score if scored else None, failed=run.failed,
                      failure_time=run.failure_time)
    return out


def _resized(config, image):
    return resize_for_detector(image.data[None], config)[0]


def recorded_runs(scenario, starts, *, duration: float, height: int, width: int, cache_dir,
                  executor=None, progress=True, scored: bool = False) -> dict:
    """`record_runs` from every start, cached by content under ``cache_dir`` (the
    scenario without its monitor, or with its detector alone when ``scored``, the
    horizon, the frame size and the starts) like every real-loop batch: a killed batch
    resumes, a repeated one costs nothing. The runs are the controller alone's
    (``engaged`` all False: the detector acts on nothing)."""
    scenario = watching(scenario) if scored else without_monitor(scenario)
    rollout = functools.partial(record_runs, scenario, float(duration), int(height), int(width),
                                scored=scored)
    fields, _, _ = map_states(rollout, starts, cache_dir=cache_dir, executor=executor,
                              progress=progress, unit="run",
                              required=("failed", "frames") + (("score",) if scored else ()),
                              label=f"recorded runs {scenario.environment.name}")
    return {**fields, **({"engaged": np.zeros(len(fields["ticks"]), bool)} if scored else {})}
