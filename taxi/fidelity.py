"""The taxi's real Drake closed loop (rendering at every tick) run from given starts:
the rollout functions behind rollout and trajectory labels and every fidelity check, the missions
(failure and liveness) of the loop alone and guarded by each fallback, and the
detector's score along real runs (what the guard's tables miss between nodes)."""

import copy
import dataclasses as dc
import functools

import numpy as np

from reachwatch.diagrams import (CONTROLLER, MonitorConfig, add_detector, make_closed_loop_diagram,
                                 make_guarded_diagram)
from reachwatch.diagrams.controller import CONTROL_OUTPUT, ESTIMATE_OUTPUT, has_estimate
from reachwatch.diagrams.lockstep import loop_copies, simulate_lockstep
from reachwatch.diagrams.render_stack import BUILD_LOCK
from reachwatch.reach.fidelity import Fidelity, compare_verdicts, left_box
from reachwatch.reach.fingerprint import fingerprint
from reachwatch.reach.liveness import (FAILED_AT_START, MISSION_FIELDS, SAME_DISTANCE_FIELDS,
                                       MissionOutcomes, check_mission_limit, mission_done,
                                       mission_row)
from reachwatch.reach.outcomes import (Outcomes, check_memoryless, map_states, path_fields,
                                       path_points, put_path, run_outcomes)
from reachwatch.reach.score_noise import fit_score_noise_on_runs
from reachwatch.reach.thread_kept import KEPT_DIAGRAMS, ThreadKept
from reachwatch.systems import fallback_parts
from reachwatch.systems.torch_threads import torch_threads

from .dynamics import OffRunway
from .sweeps import resolved

#: The taxi grid axes where leaving the box is not a failure (py, theta): past |px| = B
#: the run has failed, and it stops there.
OPEN_AXES = (1, 2)

#: Per worker *thread*: (make, scenario fingerprint) -> copies of the loop, each
#: ``(diagram, context)``, for the `KEPT_DIAGRAMS` most recently used loops, built by the
#: thread that runs them. Two threads never share a Context (a Simulator on it would see
#: the other's time) nor a VTK/EGL render context (it renders only on the thread that
#: created it).
_LOOPS = ThreadKept(KEPT_DIAGRAMS)

#: Real-loop runs a worker thread advances together, tick by tick
#: (`reachwatch.diagrams.lockstep`): their frames render one after another and the
#: controller sees them as one batch. The runs are identical to one at a time
#: (tests/test_lockstep.py); each needs its own copy of the loop (about 70 MB at
#: 200x360), built on the thread's first batch. 1: one run at a time.
LOCKSTEP = 4

#: torch's threads while real-loop runs go on (restored after; 0: torch's own setting).
#: TaxiNet's tensors are small: a second thread saves little, and on a loaded two-core
#: machine each of its ops waits for that thread to be scheduled (measured there at
#: 200x360, one run at a time: TaxiNet 33-74 ms per tick on two threads, 3.1-4.7 ms on
#: one; benchmarks/lockstep.py). The estimates are the same bits either way (measured).
LOOP_TORCH_THREADS = 1


def on_runway_starts(box, count: int, seed, *, half_width: float) -> np.ndarray:
    """``count`` seeded uniform random states of ``box`` (a `Grid`'s box, or ``(lo,
    hi)``) with |px| < half_width (starts already off the runway would agree with any
    BRT and flatter it). ``seed`` is anything `numpy.random.default_rng` takes."""
    lo, hi = (box.lo, box.hi) if hasattr(box, "lo") else box
    lo, hi = np.array(lo, float), np.array(hi, float)
    lo[0], hi[0] = max(lo[0], -half_width), min(hi[0], half_width)
    rng = np.random.default_rng(seed)
    return lo + rng.uniform(size=(count, len(lo))) * (hi - lo)


def _loops(scenario, make, count: int = 1) -> list:
    """``count`` copies ``(diagram, context)`` of the loop ``make(scenario)``, built once
    per thread (a Dask worker runs tasks on several threads of one process) and kept
    while among its most recently used loops. A thread keeps the extra copies of one
    loop only: asking for several of one drops those of the others (their first copies
    stay, as before lockstep)."""
    key = (make.__name__, fingerprint(scenario))
    copies = _LOOPS.get(key, list)
    with BUILD_LOCK:                        # one build at a time per process, as get's
        if count > 1:
            for other, kept in _LOOPS.kept().items():
                if other != key:
                    del kept[1:]
        if len(copies) < count:
            copies.extend(loop_copies(lambda: make(scenario), count - len(copies)))
    return copies[:max(1, count)]


def _loop(scenario, make):
    """The diagram ``make(scenario)`` and a context for it, built once per thread."""
    return _loops(scenario, make)[0]


def _lockstep(lockstep) -> int:
    count = LOCKSTEP if lockstep is None else lockstep
    if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or count < 1:
        raise ValueError(f"lockstep must be a whole number >= 1 (runs advanced together), "
                         f"got {count!r}")
    return int(count)


def _real_runs(scenario, make, states, *, lockstep=None, **settings) -> list:
    """`simulate` of the loop ``make(scenario)`` from each of ``states``, `LOCKSTEP` runs
    (or ``lockstep``) at a time on this thread's copies of the loop (`_loops`), on
    `LOOP_TORCH_THREADS` torch threads."""
    if len(states) == 0:
        return []
    copies = _loops(scenario, make, min(_lockstep(lockstep), len(states)))
    with torch_threads(LOOP_TORCH_THREADS):
        return simulate_lockstep(copies, initial_states=states, **settings)


def taxi_rollouts(scenario, duration: float, grid, states, *, lockstep=None) -> dict:
    """Runs the real closed loop of ``scenario`` from each start for ``duration`` s
    (stopping at failure, |px| >= B). Returns per start ``failed``, ``failure_time``
    (s, NaN if none), ``left_box`` (the run left ``grid``'s box in py or theta),
    ``max_abs_theta`` (rad) and ``ticks`` (frames rendered). Use it through
    `real_outcomes`, which caches it; ``functools.partial(taxi_rollouts, scenario,
    duration, grid)`` is a picklable rollout function for `run_outcomes`. ``lockstep``:
    runs advanced together (default `LOCKSTEP`; the results do not depend on it)."""
    off = OffRunway(scenario.environment.half_width)
    states = np.asarray(states, float)
    on = ~off(states)
    runs = iter(_real_runs(scenario, make_closed_loop_diagram, states[on], lockstep=lockstep,
                           duration=duration, period=scenario.controller.period,
                           failed=off))
    out = {k: [] for k in ("failed", "failure_time", "left_box", "max_abs_theta", "ticks")}
    for x, on_runway in zip(states, on):
        if not on_runway:                       # already off the runway
            row = (True, 0.0, False, abs(x[2]), 0)
        else:
            run = next(runs)
            row = (run.failed, run.failure_time, left_box(run.state, grid, axes=OPEN_AXES),
                   float(np.max(np.abs(run.state[:, 2]))),
                   len(run.time))
        for k, v in zip(out, row):
            out[k].append(v)
    return {k: np.asarray(v) for k, v in out.items()}


def taxi_paths(scenario, horizon: float, extend: float, stride: int, grid, states, *,
               lockstep=None) -> dict:
    """Like `taxi_rollouts`, but each run lasts ``horizon + extend`` s (stopping at
    failure), and the states it passes through at the ticks `path_points` keeps are
    labelled by the same run (`reach.outcomes.path_labels`). Per start: ``failed``
    (within ``horizon``, as `taxi_rollouts`), ``failure_time`` (s, NaN if none within
    the whole run), ``left_box`` and ``max_abs_theta`` (within ``horizon``), ``ticks``
    (frames rendered), ``path_state`` ``(m, 3)`` (NaN where the run had ended) and
    ``path_label`` ``(m,)`` (1 anomalous, 0 safe, -1 unknown); row 0 of both is the
    start itself. Exact for the taxi's loop: TaxiNet and the P-controller keep no state,
    and the steering hold is reset at every control tick. ``lockstep`` as in
    `taxi_rollouts`."""
    diagram, _ = _loop(scenario, make_closed_loop_diagram)
    check_memoryless(diagram.GetSubsystemByName(CONTROLLER))
    off, period = OffRunway(scenario.environment.half_width), scenario.controller.period
    points = path_points(horizon, extend, stride, period)
    states = np.asarray(states, float)
    gone = off(states)                           # already off the runway
    runs = iter(_real_runs(scenario, make_closed_loop_diagram,
                           states[~gone], lockstep=lockstep,
                           duration=horizon + extend, period=period, failed=off))
    out = path_fields(len(states), points, states.shape[1])
    for i, x in enumerate(states):
        if gone[i]:
            put_path(out, i, x)
            out["max_abs_theta"][i] = abs(x[2])
            continue
        run = next(runs)
        within = put_path(out, i, x, time=run.time, state=run.state,
                          failure_time=run.failure_time if run.failed else None,
                          duration=horizon + extend, horizon=horizon, points=points)
        out["left_box"][i] = left_box(run.state[within], grid, axes=OPEN_AXES)
        out["max_abs_theta"][i] = float(np.max(np.abs(run.state[within, 2])))
    return out


def real_paths(scenario, starts, *, grid, horizon: float, extend: float, stride: int,
               cache_dir, executor=None, progress=True) -> Outcomes:
    """`taxi_paths` from every start, cached by content under ``cache_dir`` like
    `real_outcomes`."""
    scenario = without_monitor(scenario)
    rollout = functools.partial(taxi_paths, scenario, float(horizon), float(extend),
                                int(stride), grid)
    return run_outcomes(rollout, starts, cache_dir=cache_dir, executor=executor,
                        progress=progress, label=f"{scenario.environment.name} paths")


def without_monitor(scenario):
    """``scenario`` with the default monitor. The controller alone's loop never reads
    the monitor (detector, threshold, fallback), so its cached runs are keyed without
    it: a run with another detector or fallback setting reuses them."""
    return dc.replace(resolved(scenario), monitor=MonitorConfig())


def watching(scenario):
    """``scenario`` with a monitor of its detector alone (`MonitorConfig.watching`): runs
    that read the detector's score along the controller alone are keyed by it, not by
    the threshold or fallback. A copy: `resolved` may return the caller's scenario."""
    return dc.replace(resolved(scenario),
                      monitor=MonitorConfig.watching(scenario.monitor.detector))


def real_outcomes(scenario, starts, *, grid, duration: float, cache_dir, executor=None,
                  progress=True) -> Outcomes:
    """`taxi_rollouts` from every start, cached under ``cache_dir`` by content (the
    scenario, the horizon, ``grid``'s box and the starts): a killed batch resumes, a
    repeated one costs nothing. The monitor is not part of the key (`without_monitor`)."""
    scenario = without_monitor(scenario)
    rollout = functools.partial(taxi_rollouts, scenario, float(duration), grid)
    return run_outcomes(rollout, starts, cache_dir=cache_dir, executor=executor,
                        progress=progress, label=scenario.environment.name)


def real_loop_fidelity(scenario, value_function, starts, *, cache_dir, duration=None,
                       executor=None, progress=True) -> Fidelity:
    """The BRT's verdicts ``V(x0) <= 0`` against the real loop from ``starts`` over
    the BRT's horizon, with the runs that left the solved box in py or theta."""
    outcomes = real_outcomes(scenario, starts, grid=value_function.grid,
                             duration=duration or value_function.horizon,
                             cache_dir=cache_dir, executor=executor, progress=progress)
    return compare_verdicts(value_function.in_brt(starts), outcomes.failed,
                            outcomes["left_box"])


def mission_rollouts(scenario, fallback, duration: float, states, mission_limit=None, *,
                     lockstep=None) -> dict:
    """Runs the real loop of ``scenario`` from each start for ``duration`` s, stopping
    at failure: the controller alone (``fallback=None``) or guarded by the detector of
    ``scenario.monitor`` with the fallback named ``fallback`` (e.g. ``"brake"``,
    ``"slow_down+dead_reckoning"``). Returns the `MissionOutcomes` fields per start:
    the speed logged at a tick is the speed applied since the previous one, and ticks
    are the control ticks before the horizon.

    With ``mission_limit`` (a number >= 1) a run goes on past the horizon until it has
    covered the distance the controller alone covers within it (its speed x
    ``duration``), fails, stands still for `reach.liveness.PARKED_SECONDS` or reaches
    ``mission_limit * duration`` s, and the same-distance fields are returned too; the
    others are read from its first ``duration`` s, as without it. ``lockstep`` as in
    `taxi_rollouts`."""
    if mission_limit is not None:
        mission_limit = check_mission_limit(mission_limit)
    loop, make = scenario, make_closed_loop_diagram
    if fallback is not None:
        loop, make = copy.deepcopy(scenario), make_guarded_diagram
        loop.monitor.strategy, loop.monitor.steering = fallback_parts(fallback)
    off, period = OffRunway(scenario.environment.half_width), scenario.controller.period
    nominal = scenario.controller.speed
    goal = nominal * duration
    names = MISSION_FIELDS + (SAME_DISTANCE_FIELDS if mission_limit is not None else ())
    out = {name: [] for name in names}
    states = np.asarray(states, float)
    gone = off(states)                           # already off the runway
    runs = iter(_real_runs(loop, make, states[~gone], lockstep=lockstep,
                           period=period, failed=off,
                           duration=duration * (mission_limit or 1.0),
                           stop_when=(None if mission_limit is None else
                                      lambda i: mission_done(goal, nominal, period, duration))))
    for at_start in gone:
        if at_start:
            row = FAILED_AT_START
        else:
            run = next(runs)
            row = mission_row(run.time, run.speed, run.anomaly, failed=run.failed,
                              failure_time=run.failure_time, nominal=nominal,
                              duration=duration, goal=goal)
        for name, value in zip(names, row):
            out[name].append(value)
    return {name: np.asarray(value) for name, value in out.items()}


def real_missions(scenario, starts, *, fallback=None, duration: float, cache_dir,
                  mission_limit=None, executor=None, progress=True) -> MissionOutcomes:
    """`mission_rollouts` from every start, cached by content under ``cache_dir`` like
    `real_outcomes` (a killed batch resumes, a repeated one costs nothing). The
    controller alone's runs (``fallback=None``) are keyed without the monitor
    (`without_monitor`), so they are shared by every detector and fallback setting."""
    scenario = resolved(scenario) if fallback else without_monitor(scenario)
    rollout = functools.partial(mission_rollouts, scenario, fallback, float(duration),
                                **({} if mission_limit is None
                                   else {"mission_limit": float(mission_limit)}))
    fields, _, _ = map_states(rollout, starts, cache_dir=cache_dir, executor=executor,
                              progress=progress, unit="run",
                              required=MISSION_FIELDS + (SAME_DISTANCE_FIELDS
                                                         if mission_limit is not None else ()),
                              label=f"real loop {scenario.environment.name} "
                                    f"{fallback or 'alone'}")
    return MissionOutcomes.from_fields(fields)


def make_watched_loop(scenario):
    """The controller alone's closed loop with the detector of ``scenario.monitor``
    watching its camera and acting on nothing: exports ``score`` beside ``state``, from
    the same rendered image the controller sees at each tick."""
    return make_closed_loop_diagram(
        scenario, prebuild_callback=lambda builder, world: export_watching_detector(
            builder, world, scenario))


def export_watching_detector(builder, world, scenario):
    """A ``prebuild_callback`` step: the detector of ``scenario.monitor`` reading the
    camera of ``world`` and the controller's outputs, its ``score`` exported, wired to
    nothing that acts."""
    controller = builder.GetSubsystemByName(CONTROLLER)
    detector = add_detector(
        builder, image_port=world.camera.color_image_output_port(),
        monitor=scenario.monitor, period=scenario.controller.period,
        steering_port=controller.GetOutputPort(CONTROL_OUTPUT),
        estimate_port=(controller.GetOutputPort(ESTIMATE_OUTPUT)
                       if has_estimate(controller) else None))
    builder.ExportOutput(detector.get_score_output_port(), "score")


def score_paths(scenario, duration: float, states, *, lockstep=None) -> dict:
    """From each start, the real closed loop of the controller alone for ``duration``
    s (stopping at failure), and the detector's score of the image at every logged
    tick (``scenario.monitor.detector``, `make_watched_loop`): ``state`` ``(n, T, 3)``
    and ``score`` ``(n, T)``, NaN after a run ends; ``ticks`` ``(n,)``.
    ``functools.partial(score_paths, scenario, duration)`` is a picklable rollout
    function for `map_states`. ``lockstep`` as in `taxi_rollouts`."""
    scenario = resolved(scenario)
    period, off = scenario.controller.period, OffRunway(scenario.environment.half_width)
    length = int(np.floor(duration / period + 1e-9)) + 2
    states = np.asarray(states, float)
    gone = off(states)                           # already off the runway: no path
    runs = iter(_real_runs(scenario, make_watched_loop, states[~gone],
                           lockstep=lockstep, duration=duration, period=period,
                           failed=off))
    out = {"state": np.full((len(states), length, 3), np.nan),
           "score": np.full((len(states), length), np.nan), "ticks": np.zeros(len(states), int)}
    for i in range(len(states)):
        if gone[i]:
            continue
        run = next(runs)
        n = min(len(run.time), length)
        out["state"][i, :n] = np.asarray(run.state, float)[:n]
        out["score"][i, :n] = np.asarray(run.score, float)[:n]
        out["ticks"][i] = n
    return out


def score_runs(scenario, starts, *, duration: float, cache_dir, executor=None,
               progress=True) -> dict:
    """`score_paths` from every start, cached by content under ``cache_dir`` like
    `real_outcomes`, keyed by the detector but not by the monitor's threshold and
    fallback settings: the controller alone and the detector's score do not depend on
    them. Every run is the controller alone's (``engaged`` all False)."""
    scenario = watching(scenario)
    rollout = functools.partial(score_paths, scenario, float(duration))
    fields, _, _ = map_states(rollout, starts, cache_dir=cache_dir, executor=executor,
                              progress=progress, unit="run", required=("score", "state"),
                              label=f"detector score along real runs {scenario.environment.name}")
    return {**fields, "engaged": np.zeros(len(fields["ticks"]), bool)}


def real_score_noise(scenario, grid, score_table, starts, *, duration: float, cache_dir,
                     executor=None, progress=True):
    """`reach.score_noise.ScoreNoise` fitted (`fit_score_noise`) to how the detector's real score along
    runs of the controller alone from ``starts`` departs from ``score_table``
    (the guarded sweep's score on ``grid``) interpolated at the same states. Runs are
    cached like `real_outcomes`, under a key without the monitor's threshold and fallback
    settings: the controller alone and the detector's score do not depend on them.
    Returns ``(noise, {"runs", "ticks"})``."""
    fields = score_runs(scenario, starts, duration=duration, cache_dir=cache_dir,
                        executor=executor, progress=progress)
    return fit_score_noise_on_runs(       # distance along the path on the ground (px, py)
        grid, score_table, fields["state"], fields["score"], fields["ticks"],
        lambda path: np.concatenate([[0.0], np.cumsum(np.linalg.norm(
            np.diff(path[:, :2], axis=0), axis=1))]))
