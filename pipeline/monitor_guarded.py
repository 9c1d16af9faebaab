"""The monitor study's guarded real loop (`reachwatch.pipeline.monitor_study`): each
saved monitor, braking, against the loop alone from the first recorded starts of each
environment, and the oracle monitor's row beside them, pooled and per environment.

**What a stop is judged against.** A guarded run lasts the study's ``duration``; a
failure it prevented is one the loop alone has within it. Whether a stop was *needless*
is judged on the study's longer watch of the loop alone, ``duration + within``
(`monitor_runs.watched_failure_times`): the monitor's risk is of failing within
``within`` s, so a stop near the window's end claims a failure up to ``within`` s past
it, and a run the loop alone survives for the window but leaves the safe set soon
after is censored, not safe (its stop is counted apart, ``stopped_failing_after``,
neither prevented nor needless).

**What is rendered.** Until a monitor first flags, the guarded loop is the loop alone:
the same frames, controller and plant, tick for tick. So a run whose monitor's risk
along its recording (the study's, at every tick) stays below the threshold never
flags, and its guarded run is the loop alone's; only the others are rendered
(`guarded_missions`). The first such run of each environment is rendered too, and must
come out as the loop alone's. The loop alone's runs themselves are the recorded ones
(`monitor_runs.alone_from_recordings`, checked on two runs of each environment) where
the loop alone's speed is the controller's constant one."""

import dataclasses as dc

import numpy as np

from reachwatch.diagrams import MonitorConfig
from reachwatch.reach.liveness import MissionOutcomes
from reachwatch.training.monitor_eval import oracle_risks, rate

from .monitor_judge import fails_after
from .monitor_runs import alone_from_recordings, continues_from_recordings, each_named
from .monitor_sections import rate_text
from .monitor_spec import ORACLE


def guarded_rows(spec, application, scenario, held_out, models, checkpoints, *, risks,
                 cache_dir, executor, progress, log, lead, read_alone: bool = False):
    """The guarded real loop (braking) with each saved monitor against the loop alone,
    from the first ``guarded_runs`` recorded starts of each environment of ``held_out``
    (the held-out family's, or those outside it; the application's `missions`); and the
    oracle monitor's row (`_oracle_guarded`). Stops are judged on the loop alone watched
    ``within`` s past the window (see the module; `judged_runs`). ``risks[name]``: each
    monitor's risk (on its threshold's scale) at every tick of each environment's
    recorded runs, ``[env][run]``: what `guarded_missions` reads to render only the runs
    it may flag. ``read_alone`` (for a loop that
    `monitor_runs.alone_reads_recordings`): the loop alone's runs are read off the
    recordings (`monitor_runs.alone_from_recordings`), not rendered again."""
    def each(fn, what):              # every environment's runs together on a pool
        return each_named([(g["name"], g) for g in held_out], fn, executor=executor,
                          what=what, progress=progress)

    # the loop alone once per environment: every monitor is judged against the same runs,
    # read off the recordings where they are the same runs
    alone = alone_from_recordings if read_alone else (
        lambda application, scenario, g, runs, **kw: application.missions(
            scenario, g["starts"][:runs], **kw))
    alone_runs = each(lambda i, g: alone(
        application, dc.replace(scenario, environment=g["environment"]), g, spec.guarded_runs,
        duration=spec.duration, cache_dir=cache_dir, executor=executor, progress=progress),
        "the loop alone in")
    # the runs that survive the window but fail within the study's longer watch
    after = [fails_after(g)[:len(alone.failed)] for g, alone in zip(held_out, alone_runs)]
    rows = {}
    for name, path in checkpoints.items():
        threshold, (flags_needed, flag_window) = models[name][2:]

        def guarded_in(i, g, name=name, path=path, threshold=threshold,
                       rule=(flags_needed, flag_window)):
            sc = dc.replace(scenario, environment=g["environment"], monitor=MonitorConfig(
                detector=path, threshold=threshold, strategy="brake", flags_needed=rule[0],
                flag_window=rule[1], brake_deceleration=spec.brake_deceleration))
            starts = g["starts"][:spec.guarded_runs]
            peaks = np.array([np.max(r) if len(r) else -np.inf
                              for r in risks[name][i][:len(starts)]])
            return guarded_missions(application, sc, starts, alone_runs[i], peaks, threshold,
                                    duration=spec.duration, cache_dir=cache_dir,
                                    executor=executor, progress=progress,
                                    what=f"{name} in {g['name']}")

        envs, distances, rendered = [], [], 0
        for g, alone, late, (guarded, count) in zip(held_out, alone_runs, after,
                                                    each(guarded_in, f"{name} guarding")):
            rendered += count
            envs.append(judged_runs(g["name"], alone.failed, late, guarded.failed,
                                    guarded.ever_stopped))
            distances.append((float(alone.distance.sum()), float(guarded.distance.sum())))
        rows[name] = counts = _pooled(envs, distances)
        counts["rendered"] = rendered
        log(f"monitor: guarded real loop, {name}: failures {counts['failed_alone']} alone -> "
            f"{counts['failed_guarded']} guarded of {counts['runs']} runs; prevented "
            f"{rate_text(counts['prevented_rate'])}; needless stops "
            f"{rate_text(counts['needless_rate'])}; stopped {counts['stopped_failing_after']} of "
            f"the {counts['failing_after']} runs failing within {spec.within:g} s after the "
            f"window; {rendered} runs rendered, the others never reaching the threshold along "
            f"their recording")
    # the oracle goes on from recorded states: only a controller that keeps no state of
    # its own is the same loop there (else its row would fail after the others, or be wrong)
    if checkpoints and held_out and not continues_from_recordings(
            application, dc.replace(scenario, environment=held_out[0]["environment"])):
        log(f"monitor: guarded real loop, {ORACLE}: left out: it goes on from recorded "
            f"states, and this controller keeps state of its own across ticks")
    elif checkpoints:
        rows[ORACLE] = _oracle_guarded(spec, application, scenario, held_out, alone_runs,
                                       after, next(iter(checkpoints.values())), lead=lead,
                                       cache_dir=cache_dir, executor=executor,
                                       progress=progress)
        counts = rows[ORACLE]
        log(f"monitor: guarded real loop, {ORACLE}: failures {counts['failed_alone']} alone -> "
            f"{counts['failed_guarded']} guarded of {counts['runs']} runs; prevented "
            f"{rate_text(counts['prevented_rate'])}")
    return rows


#: How far below the threshold (relative to it, at least this much absolute) a run's
#: largest recorded risk must stay for `guarded_missions` to take its guarded run from
#: the loop alone: a history monitor's online risk is its offline one up to float
#: rounding.
QUIET_MARGIN = 1e-3


def guarded_missions(application, scenario, starts, alone, peaks, threshold, *, duration,
                     cache_dir, executor, progress, what: str):
    """``(MissionOutcomes, rendered)``: the guarded loop of ``scenario`` (its monitor,
    braking) from ``starts``, as `missions` gives it, rendering only what may differ
    from the loop alone's runs ``alone`` from the same starts. A run whose monitor's
    largest risk along its recording (``peaks``) stays below ``threshold`` by
    `QUIET_MARGIN` never flags, under any k-of-n rule, so its guarded run is the loop
    alone's. The others are rendered, and so is the first quiet one, which must come
    out exactly as the loop alone's: else a RuntimeError naming ``what`` (the loop
    alone does not repeat itself, or the online monitor is not the one recorded)."""
    peaks = np.asarray(peaks, float)
    if len(peaks) != len(starts) or len(alone) != len(starts):
        raise ValueError(f"guarded runs of {what}: {len(starts)} starts, {len(alone)} runs "
                         f"alone and {len(peaks)} recorded risks")
    quiet = peaks < threshold - QUIET_MARGIN * max(1.0, abs(threshold))
    check = np.flatnonzero(quiet)[:1]
    render = ~quiet
    render[check] = True
    fields = {name: np.array(value) for name, value in alone.as_fields().items()}
    which = np.flatnonzero(render)
    if len(which):
        ran = application.missions(scenario, np.asarray(starts)[which], fallback="brake",
                                   duration=duration, cache_dir=cache_dir,
                                   executor=executor, progress=progress)
        for name, value in ran.as_fields().items():
            if name not in fields:
                raise ValueError(f"guarded runs of {what}: the guarded loop gives {name}, "
                                 f"the loop alone does not")
            fields[name][which] = value
        for i in check:
            differ = [name for name, value in alone.as_fields().items()
                      if not np.array_equal(value[i], fields[name][i])]
            if differ:
                raise RuntimeError(
                    f"guarded runs of {what}: run {i} never reaches the threshold along its "
                    f"recording, yet guarded it differs from the loop alone in {differ}: "
                    f"the loop alone does not repeat itself, or the online monitor is not "
                    f"the one recorded")
    return MissionOutcomes.from_fields(fields), len(which)


def judged_runs(name: str, failed_alone, failed_after, failed_guarded, stopped) -> dict:
    """One environment's guarded-loop counts from per-run bools: the loop alone failed
    within the window (``failed_alone``) or survived it and failed within ``within`` s
    after it (``failed_after``); the guarded loop failed (``failed_guarded``) or came to
    a standstill at some tick (``stopped``). *Safe* runs are those the loop alone
    survives for the window and the ``within`` s after it; a needless stop is a stop of
    a safe run. A stop of a run failing after the window (``stopped_failing_after``)
    is neither needless nor a prevented failure."""
    failed_alone, failed_after, failed_guarded, stopped = (
        np.asarray(a, bool) for a in (failed_alone, failed_after, failed_guarded, stopped))
    if np.any(failed_alone & failed_after):
        raise ValueError(f"{name}: a run fails within the window alone but survived it in "
                         f"its recording: the loop alone does not repeat its recordings")
    safe = ~failed_alone & ~failed_after
    return {"environment": name, "runs": len(failed_alone),
            "failed_alone": int(failed_alone.sum()), "failed_guarded": int(failed_guarded.sum()),
            "prevented": int(np.sum(failed_alone & ~failed_guarded)),
            "failing_after": int(failed_after.sum()),
            "stopped_failing_after": int(np.sum(failed_after & stopped)),
            "safe_alone": int(safe.sum()), "needless_stops": int(np.sum(safe & stopped))}


def oracle_flag_ticks(ticks, failure_times, *, period: float, lead: float) -> np.ndarray:
    """The control tick at which the oracle monitor (`oracle_risks`) first flags each
    recorded run: -1 for a run that does not fail."""
    risks = oracle_risks(ticks, failure_times, period=period, lead=lead)
    return np.array([int(np.argmax(r >= 0.5)) if np.any(r >= 0.5) else -1 for r in risks])


def _oracle_guarded(spec, application, scenario, held_out, alone_runs, after, detector, *,
                    lead, cache_dir, executor, progress) -> dict:
    """The oracle monitor in the guarded real loop: it flags a run from the tick its true
    time to failure leaves the fallback just its need (`oracle_flag_ticks`) and never a
    run that does not fail. Until that tick the guarded loop is the loop alone, so each
    failing run goes on from its recorded state at that tick in the guarded loop flagged
    at every tick (a monitor with threshold 0, braking), for what is left of the run;
    it fails if it leaves the safe set before the run's end. This takes the loop's state
    to be the state a recording holds (true of a loop whose controller keeps no state of
    its own across ticks; `tests/test_monitor_study.py` checks the taxi's). A run that
    does not fail within the window is the loop alone's (no stop, its distance);
    ``after``: per environment, which of those fail soon after it (`judged_runs`)."""
    period = scenario.controller.period
    def one(i, g):
        alone, late = alone_runs[i], after[i]
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
            # from the flag's state the loop alone must fail when the recording did (a
            # loop that stops at the crossing logs the tick before it: one tick apart)
            failing_in = (rest.ticks - 1) * period
            if not (rest.failed.all() and np.allclose(failing_in, failure[failing] - flag[failing]
                                                      * period, atol=period * 1.001)):
                raise RuntimeError(f"the oracle in the guarded loop: in {g['name']}, the loop "
                                   f"alone from a recorded state does not fail as recorded: its "
                                   f"state is more than the recorded one")
            # a run stops at its failure: its last tick is the failure's; one failing by
            # the run's end (as missions count it) counts
            fails[failing] = braked.failed & ((braked.ticks - 1) * period <= left + 1e-9)
            # before the flag it covered what the loop alone covers less what the loop
            # alone covers from the flag's state on
            distance[failing] = alone.distance[failing] - rest.distance + braked.distance
        # the oracle flags no run that does not fail within the window (checked above)
        return (judged_runs(g["name"], alone.failed, late, fails, np.zeros(n, bool)),
                (float(alone.distance.sum()), float(distance.sum())))

    # every environment's runs together on a pool, in their order
    rows = each_named([(g["name"], g) for g in held_out], one, executor=executor,
                      what="the oracle in", progress=progress)
    return _pooled([env for env, _ in rows], [d for _, d in rows])


def _pooled(envs: list, distances: list) -> dict:
    """A guarded-loop row: the per-environment rows ``envs`` summed, with the distances
    (m) the loop alone and guarded covered in each (``[(alone, guarded)]``), and the
    prevented and needless-stop rates with their Wilson intervals."""
    counts = {key: sum(env[key] for env in envs) for key in
              ("runs", "failed_alone", "failed_guarded", "prevented", "failing_after",
               "stopped_failing_after", "safe_alone", "needless_stops")}
    counts["distance_alone_m"] = sum((a for a, _ in distances), 0.0)
    counts["distance_guarded_m"] = sum((g for _, g in distances), 0.0)
    counts["environments"] = envs
    counts["prevented_rate"] = rate(counts["prevented"], counts["failed_alone"])
    counts["needless_rate"] = rate(counts["needless_stops"], counts["safe_alone"])
    return counts
