"""The monitor study's recorded runs (`reachwatch.pipeline.monitor_study`): each
environment's seeded starts, its runs of the loop alone recorded at every control tick,
and their failure times over a longer watch of the loop alone, which the study's
labels and its needless flags and stops are read from."""

import dataclasses as dc

import numpy as np

from .monitor_judge import watch_s


#: The starts' own random stream: environment ``i`` of the family is drawn from ``[seed,
#: i]`` (`reachwatch.systems.RandomEnvironments`), and starts seeded the same would
#: repeat its numbers (the first start's lateral offset was the hour's draw). Nonzero:
#: numpy seeds ``[seed, i, 0]`` as it seeds ``[seed, i]``.
STARTS_STREAM = 1


def starts_seed(spec, index: int) -> list:
    """The seed of the recorded starts of the study's ``index``-th environment (the
    family's, then ``also_held_out``'s): its own stream, `STARTS_STREAM`."""
    return [spec.family.seed, int(index), STARTS_STREAM]


def record_runs(spec, application, scenario, environments, first, *, runs, cache_dir,
                executor, progress):
    """``runs`` recorded runs of each environment: the application's `starts` in its
    `grid`'s box, those of the ``i``-th environment (counted from ``first``: its place in
    the family, or after it) seeded by `starts_seed`."""
    out = []
    for i, environment in enumerate(environments):
        here = dc.replace(scenario, environment=environment)
        box = application.grid(here, (3,) * len(application.axes))
        seed = starts_seed(spec, first + i)
        starts = application.starts(here, (box.lo, box.hi), runs, seed)
        recorded = application.recorded_runs(here, starts, duration=spec.duration,
                                              height=spec.height, width=spec.width,
                                              cache_dir=cache_dir, executor=executor,
                                              progress=progress)
        watched = watched_failure_times(spec, application, here, starts,
                                        recorded["failure_time"], cache_dir=cache_dir,
                                        executor=executor, progress=progress)
        out.append({**recorded, "watched_failure_time": watched, "starts": starts,
                    "name": environment.name, "environment": environment})
    return out


def watched_failure_times(spec, application, scenario, starts, failure_time, *, cache_dir,
                          executor, progress) -> np.ndarray:
    """Each run's failure time over a longer watch of the loop alone, `watch_s` (the
    recording's ``duration`` and the risk's horizon ``within`` after it): its recorded
    ``failure_time`` where it failed within the recording; for a run that survived
    it, the failure time of the loop alone from the same start within the watch (the
    application's `missions`, run again from those starts only), NaN if none. Every
    tick of a recording then has a known label ("fails within ``within`` s"), and a
    run that leaves the safe set just after the recording is not taken for safe."""
    failure = np.asarray(failure_time, float).copy()
    survived = np.flatnonzero(~np.isfinite(failure))
    if not len(survived) or spec.within <= 0:
        return failure
    period, watch = scenario.controller.period, watch_s(spec)
    # one tick longer: a failure at the watch's last tick is still an acting tick
    longer = application.missions(scenario, np.asarray(starts)[survived], duration=watch + period,
                                  cache_dir=cache_dir, executor=executor, progress=progress)
    at = (np.asarray(longer.ticks) - 1) * period
    later = np.where(np.asarray(longer.failed, bool) & (at <= watch + 1e-9), at, np.nan)
    if np.any(later <= spec.duration + 1e-9):
        raise RuntimeError(f"the loop alone in {scenario.environment.name} fails within "
                           f"{spec.duration:g} s from a start whose recorded run did not: "
                           f"the loop is not deterministic, and its labels would be wrong")
    failure[survived] = later
    return failure


def merged_runs(groups):
    """The runs of ``groups`` as one group (what training reads)."""
    keys = ("frames", "signals", "ticks", "failure_time", "watched_failure_time", "state")
    return {k: np.concatenate([g[k] for g in groups]) for k in keys}
