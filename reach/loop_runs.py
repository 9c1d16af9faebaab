"""The generic real loop of an application, run from given starts: the runners behind
`Application.real_outcomes`, `real_paths`, `recorded_runs`, `missions` and
`real_score_noise` for any
loop the application builds, the taxi's included (an application may bring its own).
Each
takes ``ref`` (an `ApplicationRef`: picklable, a
worker loads the application again), the scenario and the run's settings, then the
``states`` of one chunk, and returns that chunk's fields (`reach.outcomes.map_states`).
Every control tick renders; a run stops at the integrator step where
`Application.failed` holds (between ticks or on one)."""

import copy
import dataclasses as dc
import functools

import numpy as np

from reachwatch.diagrams.lockstep import loop_copies, simulate_lockstep
from reachwatch.diagrams.render_stack import BUILD_LOCK
from reachwatch.systems.torch_threads import torch_threads

from .application import build_loop
from .fingerprint import fingerprint
from .outcomes import (check_memoryless, path_fields, path_points, put_path, put_recording,
                       recording_fields)
from .thread_kept import KEPT_DIAGRAMS, ThreadKept

#: Per worker *thread*: (spec, scenario, guarded) -> copies of the loop, each
#: ``(diagram, context)``, for the `KEPT_DIAGRAMS` most recently used loops, built by
#: the thread that runs them. Two threads never share a Context (a Simulator on it would
#: see the other's time) nor a VTK/EGL render context (it renders only on the thread
#: that created it).
_LOOPS = ThreadKept(KEPT_DIAGRAMS)

#: Real-loop runs a worker thread advances together, tick by tick
#: (`reachwatch.diagrams.lockstep`): their frames render one after another and the
#: systems with a batch entry point (TaxiNet) see them as one batch. The runs are
#: identical to one at a time (tests/test_lockstep.py); each needs its own copy of the
#: loop (about 70 MB at the taxi's 200x360), built on the thread's first batch. 1: one
#: run at a time.
LOCKSTEP = 4

#: torch's threads while real-loop runs go on (restored after; 0: torch's own setting).
#: TaxiNet's tensors are small: a second thread saves little, and on a loaded two-core
#: machine each of its ops waits for that thread to be scheduled (measured there at
#: 200x360, one run at a time: TaxiNet 33-74 ms per tick on two threads, 3.1-4.7 ms on
#: one; benchmarks/lockstep.py). The estimates are the same bits either way (measured).
LOOP_TORCH_THREADS = 1


def thread_copies(key, build, count: int = 1) -> list:
    """``count`` copies ``(diagram, context)`` of the loop ``build()`` makes, known by
    ``key``: built once per worker thread and kept while among its most recently used
    loops. A thread keeps the extra copies of one loop only: asking for several of one
    drops those of the others (their first copies stay)."""
    copies = _LOOPS.get(key, list)
    with BUILD_LOCK:                        # one build at a time per process, as get's
        if count > 1:
            for other, kept in _LOOPS.kept().items():
                if other != key:
                    del kept[1:]
        if len(copies) < count:
            copies.extend(loop_copies(build, count - len(copies)))
    return copies[:max(1, count)]


def thread_loops(ref, scenario, guarded: bool = False, count: int = 1) -> list:
    """`thread_copies` of ``ref``'s loop of ``scenario`` (guarded or not)."""
    return thread_copies(fingerprint(ref, scenario, "guarded" if guarded else "alone"),
                         lambda: build_loop(ref, scenario, guarded), count)


def _thread_loop(ref, scenario, guarded: bool = False):
    """``(application, diagram, context)``: ``ref``'s application and the first of
    `thread_loops`."""
    return (ref.load(), *thread_loops(ref, scenario, guarded)[0])


def lockstep_count(lockstep) -> int:
    """``lockstep`` (None: `LOCKSTEP`), checked: runs advanced together."""
    count = LOCKSTEP if lockstep is None else lockstep
    if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or count < 1:
        raise ValueError(f"lockstep must be a whole number >= 1 (runs advanced together), "
                         f"got {count!r}")
    return int(count)


def lockstep_runs(loops, states, *, lockstep=None, **settings) -> list:
    """`reachwatch.diagrams.simulate` of a loop from each of ``states``, `LOCKSTEP` runs
    (or ``lockstep``) at a time on this thread's copies of it (``loops(count)``: e.g.
    `thread_loops` with its loop given), on `LOOP_TORCH_THREADS` torch threads;
    ``settings``: `simulate_lockstep`'s."""
    if len(states) == 0:
        return []
    copies = loops(min(lockstep_count(lockstep), len(states)))
    with torch_threads(LOOP_TORCH_THREADS):
        return simulate_lockstep(copies, initial_states=states, **settings)


def largest_heading(application, states) -> float:
    """The largest ``|heading|`` of ``states`` (the application's `heading_axis`), NaN
    for a plant without one."""
    axis = application.heading_axis
    if axis is None or len(states) == 0:
        return float("nan")
    return float(np.max(np.abs(np.asarray(states, float)[:, axis])))


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
    (`failure_rule`) holds, or at the first control tick where
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


def subsystem_port(application, diagram, name: str, what: str):
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
    from reachwatch.diagrams.render import check_frame_size, warn_blank_frames
    from reachwatch.systems import DetectorConfig, resize_for_detector
    if scored:
        scenario = _never_engaging(scenario)
    application, diagram, context = _thread_loop(ref, scenario, scored)
    camera = subsystem_port(application, diagram, application.camera_port, "camera_port")
    controller, steering = subsystem_port(application, diagram,
                                           application.probe(scenario).control_port,
                                           "probe's control_port")
    signals = ([(controller, controller.GetOutputPort(ESTIMATE_OUTPUT))]
               if controller.HasOutputPort(ESTIMATE_OUTPUT) else []) + [(controller, steering)]
    score = (subsystem_port(application, diagram, application.score_port, "score_port")
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

    def frame(root):
        image = read(*camera, root).data
        check_frame_size(image.shape, scenario)     # a monitor's checkpoint records it
        return image
    for i, x in enumerate(states):
        if gone[i]:                                     # already failed: no run
            put_recording(out, i, failed=True, failure_time=0.0)
            continue
        trajectory, rows = run_reading(
            diagram, scenario, failed, x, duration, context=context, read=lambda root: (
                resize_for_detector(frame(root)[None], size)[0],
                np.concatenate([np.asarray(read(s, p, root), float).ravel()
                                for s, p in signals]),
                float(np.ravel(read(*score, root))[0]) if scored else None))
        n = min(len(trajectory.time), length)
        if scored:
            out["engaged"][i] = _engaged(trajectory, scenario.controller.speed)
        frames = np.stack([row[0] for row in rows])[:n, ..., :3]
        warn_blank_frames(frames, f"the recorded runs of {scenario.environment.name}")
        put_recording(out, i, frames=frames,
                      signals=np.stack([row[1] for row in rows])[:n],
                      state=trajectory.state[:n],
                      score=[row[2] for row in rows[:n]] if scored else None,
                      failed=trajectory.failed, failure_time=trajectory.failure_time)
    return out


def loop_missions(ref, scenario, fallback, duration: float, states,
                  mission_limit=None, *, lockstep=None) -> dict:
    """The `reach.liveness.MissionOutcomes` fields of `Application.missions`: the loop of
    ``ref``'s application (guarded by ``scenario.monitor`` with the fallback named
    ``fallback``, or the controller alone for None) from each start for ``duration`` s,
    stopping where `Application.failed` holds. The speed logged at a tick (the guarded
    loop's exported ``speed``, else the controller's) is the speed applied since the
    previous one; ticks are the control ticks before the horizon.

    With ``mission_limit`` (a number >= 1) a run goes on past the horizon until it has
    covered the distance the controller alone covers within it (its speed x
    ``duration``), fails, stands still for `reach.liveness.PARKED_SECONDS` or reaches
    ``mission_limit * duration`` s, and the same-distance fields are returned too; the
    others are read from its first ``duration`` s, as without it. ``lockstep`` as in
    `loop_rollouts`."""
    from reachwatch.systems import fallback_parts
    from .liveness import (FAILED_AT_START, MISSION_FIELDS, SAME_DISTANCE_FIELDS,
                           check_mission_limit, mission_done, mission_row)
    if mission_limit is not None:
        mission_limit = check_mission_limit(mission_limit)
    guarded = fallback is not None
    if guarded:
        scenario = copy.deepcopy(scenario)
        scenario.monitor.strategy, scenario.monitor.steering = fallback_parts(fallback)
    application = ref.load()
    failed = failure_rule(application, scenario)
    period, nominal = scenario.controller.period, scenario.controller.speed
    goal = nominal * duration
    names = MISSION_FIELDS + (SAME_DISTANCE_FIELDS if mission_limit is not None else ())
    states = np.asarray(states, float)
    gone = already_failed(failed, states)
    if guarded and not gone.all():          # the first copy the runs take: built once
        diagram = thread_loops(ref, scenario, True)[0][0]
        if not all(diagram.HasOutputPort(port) for port in ("speed", "anomaly")):
            raise ValueError(f"the application '{application.name}': its guarded loop "
                             f"exports no 'speed' and 'anomaly' "
                             f"(reachwatch.diagrams.export_loop_ports), which its real "
                             f"runs are judged by")
    runs = iter(lockstep_runs(
        functools.partial(thread_loops, ref, scenario, guarded), states[~gone],
        lockstep=lockstep, period=period, failed=failed,
        duration=duration * (mission_limit or 1.0),
        stop_when=(None if mission_limit is None else
                   lambda i: mission_done(goal, nominal, period, duration))))
    out = {name: [] for name in names}
    for failed_already in gone:
        if failed_already:
            row = FAILED_AT_START
        else:
            run = next(runs)
            row = mission_row(run.time, run.speed, run.anomaly, failed=run.failed,
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
    detector, score = subsystem_port(application, diagram, application.score_port,
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


def loop_rollouts(ref, scenario, duration: float, grid, states, *, lockstep=None) -> dict:
    """The real loop of ``ref``'s application from each start for ``duration`` s,
    stopping where its `Application.failed` holds: the fields of
    `Application.real_outcomes`. Per start ``failed``, ``failure_time`` (s, NaN if
    none), ``left_box`` (the run left ``grid``'s box along `Application.open_axes`),
    ``max_abs_theta`` (`largest_heading`) and ``ticks`` (frames rendered). Runs
    `lockstep_runs` (``lockstep``: runs advanced together; the results do not depend
    on it)."""
    from .fidelity import left_box
    application = ref.load()
    failed = failure_rule(application, scenario)
    states = np.asarray(states, float)
    gone = already_failed(failed, states)
    runs = iter(lockstep_runs(functools.partial(thread_loops, ref, scenario, False),
                              states[~gone], lockstep=lockstep, duration=duration,
                              period=scenario.controller.period, failed=failed))
    out = {k: [] for k in ("failed", "failure_time", "left_box", "max_abs_theta", "ticks")}
    for x, failed_already in zip(states, gone):
        if failed_already:                              # no run
            row = (True, 0.0, False, largest_heading(application, x[None]), 0)
        else:
            run = next(runs)
            row = (run.failed, run.failure_time,
                   left_box(run.state, grid, axes=application.open_axes),
                   largest_heading(application, run.state), len(run.time))
        for k, v in zip(out, row):
            out[k].append(v)
    return {k: np.asarray(v) for k, v in out.items()}


def loop_paths(ref, scenario, horizon: float, extend: float, stride: int, grid,
               states, *, lockstep=None) -> dict:
    """The fields of `Application.real_paths`: like `loop_rollouts`, but each run lasts
    ``horizon + extend`` s (stopping at failure), and the states it passes through at
    the ticks `path_points` keeps are labelled by the same run
    (`reach.outcomes.path_labels`). Per start: ``failed`` (within ``horizon``),
    ``failure_time`` (s, NaN if none within the whole run), ``left_box`` and
    ``max_abs_theta`` (within ``horizon``), ``ticks``, ``path_state`` ``(m, n)`` (NaN
    where the run had ended) and ``path_label`` ``(m,)`` (1 anomalous, 0 safe, -1
    unknown); row 0 of both is the start itself. Exact when the plant's state is all the
    loop remembers between control ticks: the controller (the system of
    `Application.probe`'s control port) must keep no state of its own
    (`check_memoryless`). ``lockstep`` as in `loop_rollouts`."""
    from .fidelity import left_box
    application, diagram, _ = _thread_loop(ref, scenario)
    controller, _ = subsystem_port(application, diagram,
                                    application.probe(scenario).control_port,
                                    "probe's control_port")
    check_memoryless(controller)
    failed = failure_rule(application, scenario)
    period, duration = scenario.controller.period, horizon + extend
    points = path_points(horizon, extend, stride, period)
    states = np.asarray(states, float)
    gone = already_failed(failed, states)
    runs = iter(lockstep_runs(functools.partial(thread_loops, ref, scenario, False),
                              states[~gone], lockstep=lockstep, duration=duration,
                              period=period, failed=failed))
    out = path_fields(len(states), points, states.shape[1])
    for i, x in enumerate(states):
        if gone[i]:                                     # already failed: no run
            put_path(out, i, x)
            out["max_abs_theta"][i] = largest_heading(application, x[None])
            continue
        run = next(runs)
        within = put_path(out, i, x, time=run.time, state=run.state,
                          failure_time=run.failure_time if run.failed else None,
                          duration=duration, horizon=horizon, points=points)
        out["left_box"][i] = left_box(run.state[within], grid, axes=application.open_axes)
        out["max_abs_theta"][i] = largest_heading(application, run.state[within])
    return out
