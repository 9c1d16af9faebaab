"""The taxi's real Drake closed loop (rendering at every tick) run from given starts:
the generic runners of `reachwatch.reach.loop_runs` on the taxi's loop, by the names
the taxi's callers know (`real_outcomes`, `real_paths`, `mission_rollouts`,
`real_missions`, `score_runs`, `real_score_noise`), the start distribution of its
checks (`on_runway_starts`), the BRT's fidelity to the real loop
(`real_loop_fidelity`), and the loop with the detector watching
(`make_watched_loop`)."""

import numpy as np

from reachwatch.diagrams import CONTROLLER, add_detector, make_closed_loop_diagram
from reachwatch.diagrams.controller import CONTROL_OUTPUT, ESTIMATE_OUTPUT, has_estimate
from reachwatch.reach.fidelity import Fidelity, compare_verdicts
from reachwatch.reach.liveness import MissionOutcomes
from reachwatch.reach.application import ApplicationRef
from reachwatch.reach.loop_runs import loop_missions
from reachwatch.reach.outcomes import Outcomes


#: The taxi grid axes where leaving the box is not a failure (py, theta): past |px| = B
#: the run has failed, and it stops there.
OPEN_AXES = (1, 2)


def on_runway_starts(box, count: int, seed, *, half_width: float) -> np.ndarray:
    """``count`` seeded uniform random states of ``box`` (a `Grid`'s box, or ``(lo,
    hi)``) with |px| < half_width (starts already off the runway would agree with any
    BRT and flatter it). ``seed`` is anything `numpy.random.default_rng` takes."""
    lo, hi = (box.lo, box.hi) if hasattr(box, "lo") else box
    lo, hi = np.array(lo, float), np.array(hi, float)
    lo[0], hi[0] = max(lo[0], -half_width), min(hi[0], half_width)
    rng = np.random.default_rng(seed)
    return lo + rng.uniform(size=(count, len(lo))) * (hi - lo)


def real_outcomes(scenario, starts, *, grid, duration: float, cache_dir, executor=None,
                  progress=True) -> Outcomes:
    """The taxi's real loop from every start (`TaxiApplication.real_outcomes`: the generic
    `reach.loop_runs.loop_rollouts`, stopping where it leaves the runway), cached under
    ``cache_dir`` by content (the scenario without its monitor, the horizon, ``grid``'s
    box and the starts): a killed batch resumes, a repeated one costs nothing."""
    from .application import TaxiApplication
    return TaxiApplication().real_outcomes(scenario, starts, grid=grid, duration=duration,
                                           cache_dir=cache_dir, executor=executor,
                                           progress=progress)


def real_paths(scenario, starts, *, grid, horizon: float, extend: float, stride: int,
               cache_dir, executor=None, progress=True) -> Outcomes:
    """The taxi's runs from every start with the states they pass through and their
    labels (`TaxiApplication.real_paths`: the generic `reach.loop_runs.loop_paths`),
    cached by content under ``cache_dir`` like `real_outcomes`."""
    from .application import TaxiApplication
    return TaxiApplication().real_paths(scenario, starts, grid=grid, horizon=horizon,
                                        extend=extend, stride=stride, cache_dir=cache_dir,
                                        executor=executor, progress=progress)


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
    """The taxi's missions from each start, run here and not cached: the generic
    `reach.loop_runs.loop_missions` on the taxi's loop (``scenario`` as given), alone
    (``fallback=None``) or guarded by the fallback named ``fallback``."""
    from .application import TAXI_APPLICATION
    return loop_missions(ApplicationRef(TAXI_APPLICATION), scenario, fallback, duration,
                         states, mission_limit, lockstep=lockstep)


def real_missions(scenario, starts, *, fallback=None, duration: float, cache_dir,
                  mission_limit=None, executor=None, progress=True) -> MissionOutcomes:
    """The taxi's missions from every start (`TaxiApplication.missions`: the generic
    `reach.loop_runs.loop_missions`), cached by content under ``cache_dir``; the
    controller alone's runs are keyed without the monitor."""
    from .application import TaxiApplication
    return TaxiApplication().missions(scenario, starts, fallback=fallback, duration=duration,
                                      cache_dir=cache_dir, mission_limit=mission_limit,
                                      executor=executor, progress=progress)


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


def score_runs(scenario, starts, *, duration: float, cache_dir, executor=None,
               progress=True) -> dict:
    """The detector's score along the taxi's loop alone from every start
    (`TaxiApplication.score_runs`: the generic `reach.loop_runs.loop_scores`), cached by
    content under ``cache_dir``, keyed by the detector but not by the monitor's threshold
    and fallback settings."""
    from .application import TaxiApplication
    return TaxiApplication().score_runs(scenario, starts, duration=duration,
                                        cache_dir=cache_dir, executor=executor,
                                        progress=progress)


def real_score_noise(scenario, grid, score_table, starts, *, duration: float, cache_dir,
                     executor=None, progress=True):
    """`TaxiApplication.real_score_noise`: the detector's variation between the guarded
    sweep's nodes, fitted on the taxi's runs from ``starts`` along the distance on the
    ground. Returns ``(noise, fit)``."""
    from .application import TaxiApplication
    return TaxiApplication().real_score_noise(scenario, grid, score_table, starts,
                                              duration=duration, cache_dir=cache_dir,
                                              executor=executor, progress=progress)
