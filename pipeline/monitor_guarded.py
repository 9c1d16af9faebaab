"""The monitor study's guarded real loop (`reachwatch.pipeline.monitor_study`): each
saved monitor, braking, against the loop alone from the first recorded starts of each
environment, and the oracle monitor's row beside them, pooled and per environment."""

import dataclasses as dc

import numpy as np

from reachwatch.diagrams import MonitorConfig
from reachwatch.training.monitor_eval import oracle_risks, rate

from .monitor_sections import rate_text


def guarded_rows(spec, application, scenario, held_out, models, checkpoints, *, cache_dir,
                 executor, progress, log, lead):
    """The guarded real loop (braking) with each saved monitor against the loop alone,
    from the first ``guarded_runs`` recorded starts of each environment of ``held_out``
    (the held-out family's, or those outside it; the application's `missions`); and the
    oracle monitor's row (`_oracle_guarded`)."""
    # the loop alone once per environment: every monitor is judged against the same runs
    alone_runs = [application.missions(dc.replace(scenario, environment=g["environment"]),
                                       g["starts"][:spec.guarded_runs], duration=spec.duration,
                                       cache_dir=cache_dir, executor=executor,
                                       progress=progress)
                  for g in held_out]
    rows = {}
    for name, path in checkpoints.items():
        threshold, (flags_needed, flag_window) = models[name][2:]
        envs, distances = [], []
        for g, alone in zip(held_out, alone_runs):
            sc = dc.replace(scenario, environment=g["environment"], monitor=MonitorConfig(
                detector=path, threshold=threshold, strategy="brake",
                flags_needed=flags_needed, flag_window=flag_window,
                brake_deceleration=spec.brake_deceleration))
            starts = g["starts"][:spec.guarded_runs]
            guarded = application.missions(sc, starts, fallback="brake",
                                           duration=spec.duration, cache_dir=cache_dir,
                                           executor=executor, progress=progress)
            env = {"environment": g["name"], "runs": len(starts),
                   "failed_alone": int(alone.failed.sum()),
                   "failed_guarded": int(guarded.failed.sum()),
                   "prevented": int(np.sum(alone.failed & ~guarded.failed)),
                   "safe_alone": int(np.sum(~alone.failed)),
                   "needless_stops": int(np.sum(~alone.failed & guarded.ever_stopped))}
            envs.append(env)
            distances.append((float(alone.distance.sum()), float(guarded.distance.sum())))
        rows[name] = counts = _pooled(envs, distances)
        log(f"monitor: guarded real loop, {name}: failures {counts['failed_alone']} alone -> "
            f"{counts['failed_guarded']} guarded of {counts['runs']} runs; prevented "
            f"{rate_text(counts['prevented_rate'])}; needless stops {rate_text(counts['needless_rate'])}")
    if checkpoints:
        rows[ORACLE] = _oracle_guarded(spec, application, scenario, held_out, alone_runs,
                                       next(iter(checkpoints.values())), lead=lead,
                                       cache_dir=cache_dir, executor=executor,
                                       progress=progress)
        counts = rows[ORACLE]
        log(f"monitor: guarded real loop, {ORACLE}: failures {counts['failed_alone']} alone -> "
            f"{counts['failed_guarded']} guarded of {counts['runs']} runs; prevented "
            f"{rate_text(counts['prevented_rate'])}")
    return rows


#: The guarded-loop row of the oracle monitor.
ORACLE = "oracle (privileged)"


def oracle_flag_ticks(ticks, failure_times, *, period: float, lead: float) -> np.ndarray:
    """The control tick at which the oracle monitor (`oracle_risks`) first flags each
    recorded run: -1 for a run that does not fail."""
    risks = oracle_risks(ticks, failure_times, period=period, lead=lead)
    return np.array([int(np.argmax(r >= 0.5)) if np.any(r >= 0.5) else -1 for r in risks])


def _oracle_guarded(spec, application, scenario, held_out, alone_runs, detector, *, lead,
                    cache_dir, executor, progress) -> dict:
    """The oracle monitor in the guarded real loop: it flags a run from the tick its true
    time to failure leaves the fallback just its need (`oracle_flag_ticks`) and never a
    run that does not fail. Until that tick the guarded loop is the loop alone, so each
    failing run goes on from its recorded state at that tick in the guarded loop flagged
    at every tick (a monitor with threshold 0, braking), for what is left of the run;
    it fails if it leaves the safe set before the run's end. This takes the loop's state
    to be the state a recording holds (true of a loop whose controller keeps no state of
    its own across ticks; `tests/test_monitor_study.py` checks the taxi's). A safe run is
    the loop alone's (no stop, its distance)."""
    period = scenario.controller.period
    envs, distances = [], []
    for g, alone in zip(held_out, alone_runs):
        n = len(alone.failed)
        ticks, failure = g["ticks"][:n], g["failure_time"][:n]
        flag = oracle_flag_ticks(ticks, failure, period=period, lead=lead)
        failing = np.flatnonzero(flag >= 0)
        # the recordings and the loop alone must agree on which runs fail (a start
        # already off the safe set fails alone with no recorded tick): else the loop is
        # not deterministic, and the oracle's row would be wrong
        disagree = int(np.sum((flag >= 0) != (np.asarray(alone.failed, bool) & (ticks > 0))))
        if disagree:
            raise RuntimeError(f"the oracle in the guarded loop: in {g['name']}, {disagree} "
                               f"recorded runs and the loop alone's disagree on failing")
        # a run the oracle does not flag runs as the loop alone does
        fails = np.asarray(alone.failed, bool).copy()
        distance = np.asarray(alone.distance, float).copy()
        if len(failing):
            sc = dc.replace(scenario, environment=g["environment"], monitor=MonitorConfig(
                detector=detector, threshold=0.0, strategy="brake", flags_needed=1,
                flag_window=1, brake_deceleration=spec.brake_deceleration))
            states = np.stack([g["state"][i, flag[i]] for i in failing])
            here = dc.replace(scenario, environment=g["environment"])
            rest = application.missions(here, states, duration=spec.duration,
                                        cache_dir=cache_dir, executor=executor,
                                        progress=progress)
            braked = application.missions(sc, states, fallback="brake", duration=spec.duration,
                                          cache_dir=cache_dir, executor=executor,
                                          progress=progress)
            left = spec.duration - flag[failing] * period
            # from the flag's state the loop alone must fail when the recording did
            after = (rest.ticks - 1) * period
            if not (rest.failed.all() and np.allclose(after, failure[failing] - flag[failing]
                                                      * period, atol=period / 2)):
                raise RuntimeError(f"the oracle in the guarded loop: in {g['name']}, the loop "
                                   f"alone from a recorded state does not fail as recorded: its "
                                   f"state is more than the recorded one")
            # a run stops at its failure: its last tick is the failure's; one failing by
            # the run's end (as missions count it) counts
            fails[failing] = braked.failed & ((braked.ticks - 1) * period <= left + 1e-9)
            # before the flag it covered what the loop alone covers less what the loop
            # alone covers from the flag's state on
            distance[failing] = alone.distance[failing] - rest.distance + braked.distance
        env = {"environment": g["name"], "runs": n, "failed_alone": int(alone.failed.sum()),
               "failed_guarded": int(fails.sum()),
               "prevented": int(np.sum(alone.failed & ~fails)),
               # the oracle flags no run that does not fail (checked above)
               "safe_alone": int(np.sum(~alone.failed)), "needless_stops": 0}
        envs.append(env)
        distances.append((float(alone.distance.sum()), float(distance.sum())))
    return _pooled(envs, distances)


def _pooled(envs: list, distances: list) -> dict:
    """A guarded-loop row: the per-environment rows ``envs`` summed, with the distances
    (m) the loop alone and guarded covered in each (``[(alone, guarded)]``), and the
    prevented and needless-stop rates with their Wilson intervals."""
    counts = {key: sum(env[key] for env in envs) for key in
              ("runs", "failed_alone", "failed_guarded", "prevented", "safe_alone",
               "needless_stops")}
    counts["distance_alone_m"] = sum((a for a, _ in distances), 0.0)
    counts["distance_guarded_m"] = sum((g for _, g in distances), 0.0)
    counts["environments"] = envs
    counts["prevented_rate"] = rate(counts["prevented"], counts["failed_alone"])
    counts["needless_rate"] = rate(counts["needless_stops"], counts["safe_alone"])
    return counts
