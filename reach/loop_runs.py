"""The generic real loop of an application, run from given starts: the runners behind
`Application.real_outcomes`, `real_paths`, `recorded_runs`, `missions` and
`real_score_noise` for any
loop the application builds (an application may bring faster ones of its own). Each
takes ``ref`` (an `ApplicationRef`: picklable, a
worker loads the application again), the scenario and the run's settings, then the
``states`` of one chunk, and returns that chunk's fields (`reach.outcomes.map_states`).
Every control tick renders; a run stops at the integrator step where
`Application.failed` holds (between ticks or on one), as the taxi's runs do."""

import copy
import dataclasses as dc
import functools

import numpy as np

from .application import build_loop
from .fingerprint import fingerprint
from .outcomes import (check_memoryless, path_fields, path_points, put_path, put_recording,
                       recording_fields)
from .thread_kept import KEPT_DIAGRAMS, ThreadKept

#: Per worker thread: (spec, scenario) -> (application, diagram, context), the
#: `KEPT_DIAGRAMS` most recently used (a Context, and a render context, never crosses
#: threads).
_LOOPS = ThreadKept(KEPT_DIAGRAMS)


def _thread_loop(ref, scenario, guarded: bool = False):
    """``(application, diagram, context)`` of ``ref``'s loop of ``scenario``, built once
    per worker thread and kept while it is among the thread's most recently used."""
    key = fingerprint(ref, scenario) if not guarded else fingerprint(ref, scenario, "guarded")

    def build():
        diagram = build_loop(ref, scenario, guarded)
        return ref.load(), diagram, diagram.CreateDefaultContext()
    return _LOOPS.get(key, build)


def failure_rule(application, scenario):
    """``failed(states) -> bools``: `Application.failed` of ``scenario``, the failure
    rule `reachwatch.diagrams.simulate` checks at every integrator step."""
    return functools.partial(application.failed, scenario)


def already_failed(failed, states) -> np.ndarray:
    """Which of the starts ``states`` the rule ``failed`` (`failure_rule`) says have
    failed already: they are not run."""
    from reachwatch.diagrams.closed_loop import failed_at
    return failed_at(failed, np.asarray(states, float))


def run_until_failed(diagram, scenario, failed, start, duration: float, *, context=None,
                     done=None):
    """``(trajectory, failed)``: the loop ``diagram`` of ``scenario`` from the state
    ``start`` for ``duration`` s, stopped at the integrator step where ``failed``
    (`failure_rule`) holds (as the taxi's runs stop), or at the first control tick where
    ``done(rows)`` says so; ``context``: a reused one. The trajectory's ``failed`` and
    ``failure_time`` (the step's time, between ticks or on one) say when."""
    from reachwatch.diagrams import simulate
    run = simulate(diagram, initial_state=start, duration=duration,
                   period=scenario.controller.period, context=context, failed=failed,
                   stop_when=done)
    return run, run.failed


def run_reading(diagram, scenario, failed, start, duration: float, read, *, context=None):
    """``(trajectory, readings)``: the run `run_until_failed` makes, with
    ``read(root_context)`` called at every control tick the run logs (inside the loop,
    before the tick's row is read), its results listed in order."""
    from reachwatch.diagrams.closed_loop import LoopRun
    run = LoopRun(diagram, initial_state=start, duration=duration,
                  period=scenario.controller.period, context=context, failed=failed)
    readings = []
    while run.advance():
        readings.append(read(run.context))
        run.sample()
    return run.trajectory(), readings


def _subsystem_port(application, diagram, name: str, what: str):
    """The output port ``name`` (``"system.port"``) of a subsystem of ``diagram``; a
    ValueError naming the application's attribute ``what`` when there is none."""
    system, _, port = str(name).partition(".")
    if not (diagram.HasSubsystemNamed(system) and
            diagram.GetSubsystemByName(system).HasOutputPort(port)):
        raise ValueError(f"the application '{application.name}': its loop has no output port "
                         f"'{name}' (its {what}); set {what} to the loop's 'system.port'")
    system = diagram.GetSubsystemByName(system)
    return system, system.GetOutputPort(port)


def _never_engaging(scenario):
    """A copy of ``scenario`` whose monitor never engages its fallback (threshold 1, the
    longest k-of-n window): its guarded loop is the controller alone's, with the
    detector's score read along it."""
    from reachwatch.diagrams.scenario import MAX_FLAG_WINDOW
    scenario = copy.deepcopy(scenario)
    scenario.monitor = dc.replace(scenario.monitor, threshold=1.0,
                                  flags_needed=MAX_FLAG_WINDOW, flag_window=MAX_FLAG_WINDOW)
    return scenario


def _engaged(trajectory, nominal) -> bool:
    """Whether a run's logged speed left the controller's ``nominal`` one."""
    return (trajectory.speed is not None
            and bool(np.any(np.asarray(trajectory.speed, float) != nominal)))


def loop_recordings(ref, scenario, duration: float, height: int, width: int,
                    states, *, scored: bool = False) -> dict:
    """The fields of `Application.recorded_runs`: the controller alone's loop of
    ``ref``'s application from each start, the camera's image (`Application.camera_port`)
    resized to ``height`` x ``width`` and the online signals (the controller's
    ``estimate`` when it has one, then its steering: `Application.probe`'s control port)
    read inside the loop at every control tick, stopping where `Application.failed`
    holds. ``scored``: the guarded loop whose monitor never
    engages (as `loop_scores`), the detector's ``score`` (`Application.score_port`)
    read at every tick too, with ``engaged`` per run."""
    from reachwatch.diagrams.controller import ESTIMATE_OUTPUT
    from reachwatch.systems import DetectorConfig, resize_for_detector
    if scored:
        scenario = _never_engaging(scenario)
    application, diagram, context = _thread_loop(ref, scenario, scored)
    camera = _subsystem_port(application, diagram, application.camera_port, "camera_port")
    controller, steering = _subsystem_port(application, diagram,
                                           application.probe(scenario).control_port,
                                           "probe's control_port")
    signals = ([(controller, controller.GetOutputPort(ESTIMATE_OUTPUT))]
               if controller.HasOutputPort(ESTIMATE_OUTPUT) else []) + [(controller, steering)]
    score = (_subsystem_port(application, diagram, application.score_port, "score_port")
             if scored else None)
    size = DetectorConfig(height=height, width=width)
    period = scenario.controller.period
    length = int(np.floor(duration / period + 1e-9)) + 1
    states = np.asarray(states, float)
    m = sum(port.size() for _, port in signals)
    out = recording_fields(len(states), length, height, width, m, states.shape[1],
                           scored=scored)
    if scored:
        out["engaged"] = np.zeros(len(states), bool)
    failed = failure_rule(application, scenario)
    gone = already_failed(failed, states)
    read = lambda system, port, root: port.Eval(system.GetMyContextFromRoot(root))  # noqa: E731
    for i, x in enumerate(states):
        if gone[i]:                                     # already failed: no run
            put_recording(out, i, failed=True, failure_time=0.0)
            continue
        trajectory, rows = run_reading(
            diagram, scenario, failed, x, duration, context=context, read=lambda root: (
                resize_for_detector(read(*camera, root).data[None], size)[0],
                np.concatenate([np.asarray(read(s, p, root), float).ravel()
                                for s, p in signals]),
                float(np.ravel(read(*score, root))[0]) if scored else None))
        n = min(len(trajectory.time), length)
        if scored:
            out["engaged"][i] = _engaged(trajectory, scenario.controller.speed)
        put_recording(out, i, frames=np.stack([row[0] for row in rows])[:n, ..., :3],
                      signals=np.stack([row[1] for row in rows])[:n],
                      state=trajectory.state[:n],
                      score=[row[2] for row in rows[:n]] if scored else None,
                      failed=trajectory.failed, failure_time=trajectory.failure_time)
    return out


def loop_missions(ref, scenario, fallback, duration: float, states,
                  mission_limit=None) -> dict:
    """The `reach.liveness.MissionOutcomes` fields of `Application.missions`: the loop of
    ``ref``'s application (guarded by ``scenario.monitor`` with the fallback named
    ``fallback``, or the controller alone for None) from each start for ``duration`` s,
    stopping where `Application.failed` holds. The speed
    logged at a tick (the guarded loop's exported ``speed``, else the controller's) is
    the speed applied since the previous one.

    With ``mission_limit`` (a number >= 1) a run goes on past the horizon until it has
    covered the distance the controller alone covers within it (its speed x
    ``duration``), fails, stands still for `reach.liveness.PARKED_SECONDS` or reaches
    ``mission_limit * duration`` s, and the same-distance fields are returned too; the
    others are read from its first ``duration`` s, as without it."""
    from reachwatch.systems import fallback_parts
    from .liveness import (FAILED_AT_START, MISSION_FIELDS, SAME_DISTANCE_FIELDS,
                           check_mission_limit, mission_done, mission_row)
    if mission_limit is not None:
        mission_limit = check_mission_limit(mission_limit)
    if fallback is not None:
        scenario = copy.deepcopy(scenario)
        scenario.monitor.strategy, scenario.monitor.steering = fallback_parts(fallback)
    application, diagram, context = _thread_loop(ref, scenario, fallback is not None)
    failed = failure_rule(application, scenario)
    period, nominal = scenario.controller.period, scenario.controller.speed
    goal = nominal * duration
    names = MISSION_FIELDS + (SAME_DISTANCE_FIELDS if mission_limit is not None else ())
    out = {name: [] for name in names}
    states = np.asarray(states, float)
    for x, gone in zip(states, already_failed(failed, states)):
        if gone:                                        # already failed
            row = FAILED_AT_START
        else:
            done = (None if mission_limit is None else
                    mission_done(goal, nominal, period, duration))
            run, end = run_until_failed(diagram, scenario, failed, x,
                                        duration * (mission_limit or 1.0), context=context,
                                        done=done)
            if fallback is not None and (run.speed is None or run.anomaly is None):
                raise ValueError(f"the application '{application.name}': its guarded loop "
                                 f"exports no 'speed' and 'anomaly' "
                                 f"(reachwatch.diagrams.export_loop_ports), which its real "
                                 f"runs are judged by")
            row = mission_row(run.time, run.speed, run.anomaly, failed=end,
                              failure_time=run.failure_time, nominal=nominal,
                              duration=duration, goal=goal)
        for name, value in zip(names, row):
            out[name].append(value)
    return {name: np.asarray(value) for name, value in out.items()}


def loop_scores(ref, scenario, duration: float, states) -> dict:
    """The detector's score along the controller alone's runs, for
    `Application.real_score_noise`: ``ref``'s guarded loop, whose monitor never engages
    its fallback (``scenario.monitor``'s threshold at 1 and the longest k-of-n window),
    from each start for ``duration`` s, stopping where `Application.failed` holds; at
    every tick the state and the detector's score
    (`Application.score_port`). Per start: ``state`` ``(T, d)`` and ``score`` ``(T,)``
    (NaN after the run ends), ``ticks``, and ``engaged``: whether the speed still left
    the nominal one at some tick (such a run is not the controller alone's)."""
    scenario = _never_engaging(scenario)
    application, diagram, context = _thread_loop(ref, scenario, True)
    detector, score = _subsystem_port(application, diagram, application.score_port,
                                      "score_port")
    failed = failure_rule(application, scenario)
    period, nominal = scenario.controller.period, scenario.controller.speed
    length = int(np.floor(duration / period + 1e-9)) + 1
    states = np.asarray(states, float)
    out = {"state": np.full((len(states), length, states.shape[1]), np.nan),
           "score": np.full((len(states), length), np.nan),
           "ticks": np.zeros(len(states), int), "engaged": np.zeros(len(states), bool)}
    gone = already_failed(failed, states)
    for i, x in enumerate(states):
        if gone[i]:                                     # already failed: no run
            continue
        trajectory, scores = run_reading(
            diagram, scenario, failed, x, duration, context=context,
            read=lambda root: float(np.ravel(score.Eval(detector.GetMyContextFromRoot(root)))[0]))
        n = min(len(trajectory.time), length)
        out["state"][i, :n] = trajectory.state[:n]
        out["score"][i, :n] = scores[:n]
        out["ticks"][i] = n
        out["engaged"][i] = _engaged(trajectory, nominal)
    return out


def loop_rollouts(ref, scenario, duration: float, grid, states) -> dict:
    """The real loop of ``ref``'s application from each start for ``duration`` s,
    stopping where its `Application.failed` holds: the fields of
    `Application.real_outcomes`. One diagram and Context per worker thread
    (a Context, and a render context, never crosses threads)."""
    from .fidelity import left_box
    application, diagram, context = _thread_loop(ref, scenario)
    failed = failure_rule(application, scenario)
    out = {k: [] for k in ("failed", "failure_time", "left_box", "max_abs_theta", "ticks")}
    states = np.asarray(states, float)
    for x, gone in zip(states, already_failed(failed, states)):
        if gone:                                        # already failed
            row = (True, 0.0, False, np.nan, 0)
        else:
            run, end = run_until_failed(diagram, scenario, failed, x, duration,
                                        context=context)
            row = (end, run.failure_time,
                   left_box(run.state, grid, axes=application.open_axes), np.nan, len(run.time))
        for k, v in zip(out, row):
            out[k].append(v)
    return {k: np.asarray(v) for k, v in out.items()}


def loop_paths(ref, scenario, horizon: float, extend: float, stride: int, grid,
               states) -> dict:
    """The fields of `Application.real_paths`: like `loop_rollouts`, but each run lasts
    ``horizon + extend`` s (stopping at failure), and the states it passes through at
    the ticks `path_points` keeps are labelled by the same run
    (`reach.outcomes.path_labels`). Per start: ``failed`` (within ``horizon``),
    ``failure_time`` (s, NaN if none within the whole run), ``left_box`` (within
    ``horizon``), ``max_abs_theta`` (NaN: no heading is known here), ``ticks``,
    ``path_state`` ``(m, n)`` (NaN where the run had ended) and ``path_label`` ``(m,)``
    (1 anomalous, 0 safe, -1 unknown); row 0 of both is the start itself. Exact when the
    plant's state is all the loop remembers between control ticks: the controller (the
    system of `Application.probe`'s control port) must keep no state of its own
    (`check_memoryless`)."""
    from .fidelity import left_box
    application, diagram, context = _thread_loop(ref, scenario)
    controller, _ = _subsystem_port(application, diagram,
                                    application.probe(scenario).control_port,
                                    "probe's control_port")
    check_memoryless(controller)
    failed = failure_rule(application, scenario)
    period, duration = scenario.controller.period, horizon + extend
    points = path_points(horizon, extend, stride, period)
    states = np.asarray(states, float)
    out = path_fields(len(states), points, states.shape[1])
    gone = already_failed(failed, states)
    for i, x in enumerate(states):
        if gone[i]:                                     # already failed: no run
            put_path(out, i, x)
            continue
        run, end = run_until_failed(diagram, scenario, failed, x, duration, context=context)
        within = put_path(out, i, x, time=run.time, state=run.state,
                          failure_time=run.failure_time if end else None,
                          duration=duration, horizon=horizon, points=points)
        out["left_box"][i] = left_box(run.state[within], grid, axes=application.open_axes)
    return out
