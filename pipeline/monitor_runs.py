"""The monitor study's recorded runs (`reachwatch.pipeline.monitor_study`): each
environment's seeded starts, its runs of the loop alone recorded at every control tick,
and their failure times over a longer watch of the loop alone, which the study's
labels and its needless flags and stops are read from."""

import dataclasses as dc
import functools

import numpy as np

from reachwatch.diagrams import MonitorConfig
from reachwatch.reach.chunk_jobs import run_together

from .monitor_judge import watch_s
from .together import every_environment_bar


#: The starts' own random stream: environment ``i`` of the family is drawn from ``[seed,
#: i]`` (`reachwatch.systems.RandomEnvironments`), and starts seeded the same would
#: repeat its numbers (the first start's lateral offset was the hour's draw). Nonzero:
#: numpy seeds ``[seed, i, 0]`` as it seeds ``[seed, i]``.
STARTS_STREAM = 1


def starts_seed(spec, index: int) -> list:
    """The seed of the recorded starts of the study's ``index``-th environment (the
    family's, then ``also_held_out``'s): its own stream, `STARTS_STREAM`."""
    return [spec.family.seed, int(index), STARTS_STREAM]


def record_split(spec, application, scenario, environments, first, *, runs, cache_dir,
                executor, progress, detector=None):
    """``runs`` recorded runs of each environment: the application's `starts` in its
    `grid`'s box, those of the ``i``-th environment (counted from ``first``: its place in
    the family, or after it) seeded by `starts_seed`, and their watched failure times.
    ``detector`` (a checkpoint): the runs are recorded with its ``score`` at every tick
    too (`recorded_runs`' ``scored``: the same runs; one that engaged a fallback is a
    RuntimeError). `record_splits` of one split."""
    return record_splits(spec, application, scenario,
                         {"": (environments, first, runs, detector)}, cache_dir=cache_dir,
                         executor=executor, progress=progress)[""]


def record_splits(spec, application, scenario, splits: dict, *, cache_dir, executor,
                  progress, frames_read_back=()) -> dict:
    """`record_split` of each split, ``{name: (environments, first, runs, detector)}`` ->
    ``{name: [group per environment]}``. On a pool every split's environments' chunks
    are in flight together (`reachwatch.reach.chunk_jobs.run_together`); the groups come in
    the environments' order either way.

    The groups of the splits named in ``frames_read_back`` hold no ``frames``: each
    environment's are let go as its runs come in, and `recorded_frames` reads them back
    from the cached recordings when they are needed, so that a study's judged runs
    (gigabytes of frames at its protocol's size) are never all in memory at once."""
    splits = {k: (list(environments), *rest) for k, (environments, *rest) in splits.items()}
    unknown = sorted(set(frames_read_back) - set(splits))
    if unknown:
        raise ValueError(f"frames_read_back names splits {unknown} that are not recorded; "
                         f"the splits are {sorted(splits)}")
    named = [(environment.name, (environment, first + i, runs, detector, k in frames_read_back))
             for k, (environments, first, runs, detector) in splits.items()
             for i, environment in enumerate(environments)]
    if not named:
        return {k: [] for k in splits}
    continues = continues_from_recordings(
        application, dc.replace(scenario, environment=named[0][1][0]))

    def one(_, item):
        environment, index, runs, detector, read_back = item
        here = dc.replace(scenario, environment=environment)
        box = application.grid(here, (3,) * len(application.axes))
        starts = application.starts(here, (box.lo, box.hi), runs, starts_seed(spec, index))
        scored = dc.replace(here, monitor=MonitorConfig(detector=str(detector))) if detector \
            else here
        recorded = application.recorded_runs(scored, starts, duration=spec.duration,
                                              height=spec.height, width=spec.width,
                                              cache_dir=cache_dir, executor=executor,
                                              progress=progress, scored=detector is not None)
        if detector is not None and np.any(recorded["engaged"]):
            raise RuntimeError(f"recorded runs {environment.name}: the detector, watching "
                               f"only, engaged the fallback in runs "
                               f"{np.flatnonzero(recorded['engaged']).tolist()}: they are "
                               f"not the loop alone's")
        if read_back:       # let go before the watch, which renders for minutes while
            recorded.pop("frames")      # every other environment's runs come in
            recorded["read_frames"] = functools.partial(
                _read_frames, application, scored, starts, duration=spec.duration,
                height=spec.height, width=spec.width, cache_dir=cache_dir,
                scored=detector is not None)
        watched = watched_failure_times(spec, application, here, starts,
                                        recorded["failure_time"], cache_dir=cache_dir,
                                        executor=executor, progress=progress,
                                        recorded=recorded if continues else None)
        return {**recorded, "watched_failure_time": watched, "starts": starts,
                "name": environment.name, "environment": environment}

    groups = iter(each_named(named, one, executor=executor, what="recorded runs",
                             progress=progress))
    return {k: [next(groups) for _ in environments] for k, (environments, *_) in splits.items()}


def _read_frames(application, scenario, starts, *, duration, height, width, cache_dir,
                 scored) -> np.ndarray:
    # the recordings of `record_splits`' ``one``, read back from their cache (the same
    # key: the same call); inline, as the cache holds every chunk
    return application.recorded_runs(scenario, starts, duration=duration, height=height,
                                     width=width, cache_dir=cache_dir, executor=None,
                                     progress=False, scored=scored)["frames"]


def recorded_frames(group) -> np.ndarray:
    """The recorded frames of ``group`` (one environment's, from `record_splits`): those it
    holds, or those read back from the cached recordings for a split it recorded with
    ``frames_read_back``."""
    return group["frames"] if "frames" in group else group["read_frames"]()


def each_named(named, fn, *, executor, what: str, progress: bool = False) -> list:
    """``[fn(i, item)]`` for ``named``, ``[(environment name, item)]``: on a pool every
    environment's chunks in flight together (`reachwatch.reach.chunk_jobs.run_together`,
    an error raised with ``"{what} {name}: "`` before it), inline one after another;
    results in ``named``'s order either way. ``progress``: on a pool, a bar of the runs
    of every environment below theirs (its rate and time left the machine's)."""
    rows_bar = every_environment_bar("run", f"{what}, every environment", shown=progress)
    return run_together([(name, lambda i=i, item=item: fn(i, item))
                         for i, (name, item) in enumerate(named)], executor, what=what,
                        rows_bar=rows_bar)


def continues_from_recordings(application, scenario) -> bool:
    """Whether a run of the loop alone from a recorded state is the rest of the recorded
    run: its controller (the system of `Application.probe`'s control port) keeps no
    state of its own (`reachwatch.reach.outcomes.check_memoryless`, which trajectory
    labels need too). Builds the loop once."""
    from reachwatch.reach.outcomes import check_memoryless
    scenario = application.without_monitor(scenario)
    diagram = application.loop_diagram(scenario)
    system = str(application.probe(scenario).control_port).partition(".")[0]
    if not diagram.HasSubsystemNamed(system):
        return False
    try:
        check_memoryless(diagram.GetSubsystemByName(system))
    except ValueError:
        return False
    return True


def alone_reads_recordings(application, scenario) -> bool:
    """Whether the loop alone's `missions` outcomes can be read off its recordings
    (`alone_from_recordings`): its loop alone exports no ``speed``, so that
    `reach.loop_runs.loop_missions` takes the controller's constant speed and nothing
    but a run's ticks and failure decides its outcome. Builds the loop once."""
    diagram = application.loop_diagram(application.without_monitor(scenario))
    return not diagram.HasOutputPort("speed")


def alone_from_recordings(application, scenario, group, runs: int, *, duration: float,
                          cache_dir, executor, progress):
    """`reach.liveness.MissionOutcomes` of the loop alone from the first ``runs`` recorded
    starts of ``group`` (`record_split`'s) for ``duration`` s (the recordings'), read off
    the recordings for a loop that `alone_reads_recordings`: the same runs, so the same
    ticks and failures, at the controller's constant speed up to the failure time. Its first surviving and
    first failing runs are also run (`missions`: an application's own runners too) and
    must come out the same in every field, else a RuntimeError."""
    from reachwatch.reach.liveness import MissionOutcomes, travelled
    period, speed = scenario.controller.period, scenario.controller.speed
    ticks, failed = np.asarray(group["ticks"])[:runs], np.asarray(group["failed"])[:runs]
    rows = []
    for n, fails, at in zip(ticks, failed, np.asarray(group["failure_time"])[:runs]):
        if n == 0:                                      # a start already off the safe set
            rows.append((True, False, False, 0.0, 0, 0))
            continue
        time = np.arange(int(n)) * period               # the ticks the run logged
        within = time <= duration + 1e-9
        # a loop that stops at the crossing itself (the taxi's) fails after its last
        # logged tick, and covers the stretch to it too
        rows.append((bool(fails), False, False,
                     travelled(time[within], np.full(int(within.sum()), speed),
                               float(at) if fails else None), 0,
                     int(np.sum(time[within] < duration - 1e-9))))
    read = MissionOutcomes(*(np.array(column) for column in zip(*rows)))
    check = np.concatenate([np.flatnonzero(~failed)[:1], np.flatnonzero(failed & (ticks > 0))[:1]])
    ran = application.missions(scenario, np.asarray(group["starts"])[check], duration=duration,
                               cache_dir=cache_dir, executor=executor, progress=progress)
    differ = [name for name, value in ran.as_fields().items()
              if not np.array_equal(value, read.as_fields()[name][check])]
    if differ:
        raise RuntimeError(f"the loop alone in {scenario.environment.name}: its runs from "
                           f"recorded starts {check.tolist()} differ from their recordings in "
                           f"{differ}: the loop alone does not repeat its recordings")
    return read


def watched_failure_times(spec, application, scenario, starts, failure_time, *, cache_dir,
                          executor, progress, recorded=None) -> np.ndarray:
    """Each run's failure time over a longer watch of the loop alone, `watch_s` (the
    recording's ``duration`` and the risk's horizon ``within`` after it): its recorded
    ``failure_time`` where it failed within the recording; for a run that survived
    it, the failure time of the loop alone within the watch (the application's
    `missions`), NaN if none. Every tick of a recording then has a known label ("fails
    within ``within`` s"), and a run that leaves the safe set just after the recording
    is not taken for safe.

    The loop alone runs again from the starts of the runs that survived, for the whole
    watch; or, with ``recorded`` (the runs' `recorded_runs` fields, for a loop that
    `continues_from_recordings`), from each one's last recorded state for the rest of
    the watch, a third of the renders for the default 8 s and 4 s. Then the first such
    run is also watched from its start, and the two must agree on its failure (to the
    tick), else a RuntimeError.

    A failure time is that of the first tick whose state has failed, as a recording's
    is: a loop that stops at the crossing logs the tick before it, which is taken for
    the failure's unless that tick's state is one the recording found safe (its
    last); so a run fails at the recording's end + one tick at the earliest."""
    failure = np.asarray(failure_time, float).copy()
    survived = np.flatnonzero(~np.isfinite(failure))
    if not len(survived) or spec.within <= 0:
        return failure
    period, watch = scenario.controller.period, watch_s(spec)
    starts = np.asarray(starts)

    # the recordings' last tick (a run that survived has them all); times are tick
    # indices x period, as the recordings' and `missions`' own are
    end = int(np.floor(spec.duration / period + 1e-9))

    def failing_at(from_states, first):
        # one tick longer: a failure at the watch's last tick is still an acting tick
        longer = application.missions(scenario, from_states,
                                      duration=watch - first * period + period,
                                      cache_dir=cache_dir, executor=executor,
                                      progress=progress)
        failed = np.asarray(longer.failed, bool)
        # the run's last logged tick: the failing one, or the one before a failure
        # between ticks (a loop that stops at the crossing); before the recording's
        # end, the recording would have failed too
        tick = first + np.asarray(longer.ticks) - 1
        if np.any(failed & (tick < end)):
            raise RuntimeError(f"the loop alone in {scenario.environment.name} fails within "
                               f"{spec.duration:g} s from a start whose recorded run did not: "
                               f"the loop is not deterministic, and its labels would be wrong")
        # the recording's last state is not failed, so the first failed tick is a later one
        at = np.maximum(tick, end + 1) * period
        return np.where(failed & (at <= watch + 1e-9), at, np.nan)

    if recorded is None:
        later = failing_at(starts[survived], 0)
    else:
        last = np.asarray(recorded["ticks"])[survived] - 1
        if np.any(last != end):
            raise ValueError(f"recorded runs in {scenario.environment.name}: the runs that "
                             f"survived have {sorted(set(last + 1))} ticks, not {end + 1}")
        later = failing_at(np.asarray(recorded["state"])[survived, last], end)
        whole = failing_at(starts[survived[:1]], 0)
        # a failure between ticks may be logged at either tick beside it
        if not np.allclose(whole, later[:1], atol=period * 1.001, equal_nan=True):
            raise RuntimeError(
                f"the loop alone in {scenario.environment.name}: from its last recorded "
                f"state, run {survived[0]} fails at {later[0]:g} s, from its start at "
                f"{whole[0]:g} s: its recorded state is not all the loop carries")
    failure[survived] = later
    return failure


def merged_runs(groups):
    """The runs of ``groups`` as one group (what training reads)."""
    keys = ("frames", "signals", "ticks", "failure_time", "watched_failure_time", "state")
    return {k: np.concatenate([g[k] for g in groups]) for k in keys}
