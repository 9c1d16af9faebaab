"""The guard stage of ``reachwatch run``: the guarded loop's failure sets and
liveness per fallback, their trade-off as the threshold sweeps, the same figures from
the real Drake loops, a real nominal-vs-guarded run and the online rate. It reaches the
plant through the run's application (`reachwatch.reach.application`); ``reachwatch
guard`` is a front end of its `guard_figures` and `guard_plots`. (The incremental
stage is `pipeline.incremental_stage`.)"""

import copy
import dataclasses as dc

import numpy as np
from scipy.ndimage import uniform_filter

from reachwatch.diagrams import check_per_state_monitor, paired_rates
from reachwatch.reach.application import application_key, load_application
from reachwatch.reach.fingerprint import modules_source_digest
from reachwatch.reach.guard import perfect_detector_scores, plot_tradeoff, tradeoff_row
from reachwatch.reach.liveness import UNGUARDED, liveness_figures
from reachwatch.reach.score_noise import ScoreNoise
from reachwatch.systems import fallback_parts
from reachwatch.systems.checks import warn_once

from .keys import digest
from .slot_defaults import DEFAULT_APPLICATION
from .stages import Run


def robust_starts(mask, grid, limit):
    """Up to ``limit`` node indices where ``mask`` holds, those whose 3x3x3
    neighbourhood agrees most first (ties: nearest the centreline)."""
    mask = mask.reshape(grid.shape)
    support = uniform_filter(mask.astype(float), size=3, mode="nearest").ravel()
    index = np.flatnonzero(mask.ravel())
    px = np.abs(grid.states(index)[:, 0])
    return index[np.lexsort((px, -support[index]))][:limit]


def showcase_candidates(on_grid, fallbacks, grid, limit):
    """Up to ``limit`` ``(fallback, node)`` pairs where the tables say the controller
    alone fails and an honest fallback saves the start: saves that keep moving first
    (fallbacks with the smaller failure set first), then saves that end stopped. When
    the outcomes are judged by distance too, a start that the fallback only makes fail
    later (past the horizon, on the same path) is no save."""
    honest = sorted((f for f in fallbacks if fallback_parts(f)[1] != "oracle"),
                    key=lambda f: on_grid[f].failed.mean())
    alone = on_grid[UNGUARDED].failed
    picks = []
    for moving in (True, False):
        for name in honest:
            outcome = on_grid[name]
            kept = ~outcome.stopped if moving else outcome.stopped
            if outcome.has_same_distance:
                kept = kept & ~outcome.failed_same_distance
            picks += [(name, node) for node in
                      robust_starts(alone & ~outcome.failed & kept, grid, limit)]
    return picks[:limit]


def showcase_run(run: Run, scenario, on_grid, grid, env) -> dict:
    """A start the tables say an honest fallback saves, checked in the real Drake loops:
    the first real save that keeps moving (and covers the distance the controller alone
    covers without failing), else the first real save by stopping, else the first start
    the fallback only makes fail later, else the first start tried; its plot,
    trajectories and replay."""
    spec, application = run.spec, run.application
    tried, moving_save, stop_save, delayed = [], None, None, None
    for name, node in showcase_candidates(on_grid, spec.guard.strategies, grid,
                                          spec.guard.candidates):
        x0 = grid.states([node])[0]
        alone, guarded = (application.mission_rollouts(scenario, f, spec.horizon, x0[None],
                                                       mission_limit=spec.guard.mission_limit)
                          for f in (None, name))
        entry = {"fallback": name, "start": [float(v) for v in x0],
                 "nominal_fails": bool(alone["failed"][0]),
                 "guarded_fails": bool(guarded["failed"][0]),
                 "guarded_stopped": bool(guarded["stopped"][0]),
                 "guarded_fails_later": bool(guarded["failed_same_distance"][0]
                                             and not guarded["failed"][0])}
        tried.append(entry)
        if entry["nominal_fails"] and not entry["guarded_fails"]:
            if entry["guarded_fails_later"]:
                delayed = delayed or entry
            elif not entry["guarded_stopped"]:
                moving_save = entry
                break
            else:
                stop_save = stop_save or entry
    record = {"tried": tried, "confirmed": bool(moving_save or stop_save),
              "save": "moving" if moving_save else "stop" if stop_save else None}
    if not tried:
        return record
    shown = moving_save or stop_save or delayed or tried[0]
    shown_scenario = copy.deepcopy(scenario)
    shown_scenario.monitor = shown_scenario.monitor.with_fallback(shown["fallback"])
    nominal, guarded, paths = application.simulate_guarded(
        shown_scenario, shown["start"], run.path("figures"), meshcat_html=spec.guard.meshcat_html)
    record.update(strategy=shown["fallback"], start=shown["start"],
                  nominal_fails=nominal.failed, guarded_fails=guarded.failed,
                  lowest_speed=float(np.min(guarded.speed)),
                  final_speed=float(np.asarray(guarded.speed).ravel()[-1]),
                  flagged_ticks=int(np.sum(np.asarray(guarded.anomaly) >= 0.5)),
                  ticks=len(guarded.time), files=[run.rel(p) for p in paths])
    return record


def _or_default(application):
    """``application``, or the default one (`DEFAULT_APPLICATION`) for callers that name
    none."""
    return application if application is not None else load_application(DEFAULT_APPLICATION)


def fit_guard_noise(scenario, grid, tables, *, noise_starts: int, noise_seed: int,
                    horizon: float, cache_dir, executor=None, progress=True, application=None):
    """The detector's variation between the nodes of the guarded sweep ``tables``
    (`Application.real_score_noise`), fitted on ``noise_starts`` real runs of the
    controller alone from the application's starts (`Application.starts`) seeded
    ``noise_seed``: ``(noise, record)``, the record holding the fit (mean, sigma,
    length, runs, ticks, seed); ``(None, record)`` with the reason when it cannot be
    fitted. ``application``: default the taxi."""
    application = _or_default(application)
    calibration = application.starts(scenario, grid, noise_starts, noise_seed)
    try:
        noise, fit = application.real_score_noise(
            scenario, grid, tables[application.score_port], calibration, duration=horizon,
            cache_dir=cache_dir, executor=executor, progress=progress)
    except ValueError as e:
        return None, {"error": str(e), "runs": noise_starts, "seed": noise_seed}
    return noise, {**dc.asdict(noise), **fit, "seed": noise_seed}


def guard_check(scenario, grid, tables, fallbacks, *, starts: int, seed: int, horizon: float,
                mission_limit, cache_dir, executor=None, progress=True, noise_starts: int = 0,
                noise_seed: int = 4000, noise_seeds: int = 1, application=None) -> dict:
    """Every fallback and the controller alone in the real loops (`Application.missions`)
    from ``starts`` seeded starts (`Application.starts`), beside the tables' figures
    from the same starts; with ``noise_starts``, also beside the tables with the
    detector's variation between nodes (`reach.score_noise`) fitted on that many other
    real runs of the controller alone (starts and noise seeded ``noise_seed``; with
    ``noise_seeds`` > 1 the tables are also rolled out with the noise seeded
    ``noise_seed + 1, ...``, kept per fallback as ``table_with_noise_by_seed``). A fit
    that fails is recorded with its reason and the check goes on. ``application``:
    default the taxi."""
    if noise_seeds < 1:
        raise ValueError(f"noise_seeds must be >= 1, got {noise_seeds}")
    application = _or_default(application)
    points = application.starts(scenario, grid, starts, seed)
    table = application.fallback_rollouts(scenario, grid, tables, horizon, fallbacks,
                                          starts=points, mission_limit=mission_limit)
    real = {f: application.missions(scenario, points, fallback=None if f == UNGUARDED else f,
                                    duration=horizon, mission_limit=mission_limit,
                                    cache_dir=cache_dir, executor=executor, progress=progress)
            for f in [UNGUARDED, *fallbacks]}
    check = {"starts": len(points), "seed": seed,
             "fallbacks": {f: {"table": liveness_figures(table[UNGUARDED], table[f]),
                               "real": liveness_figures(real[UNGUARDED], real[f])}
                           for f in fallbacks}}
    if not noise_starts:
        return check
    noise, check["score_noise"] = fit_guard_noise(
        scenario, grid, tables, noise_starts=noise_starts, noise_seed=noise_seed,
        horizon=horizon, cache_dir=cache_dir, executor=executor, progress=progress,
        application=application)
    if noise is None:
        return check
    noisy = [application.fallback_rollouts(scenario, grid, tables, horizon, fallbacks,
                                           starts=points, mission_limit=mission_limit,
                                           score_noise=noise, seed=noise_seed + k,
                                           alone=table[UNGUARDED])
             for k in range(noise_seeds)]
    for f in fallbacks:
        figures = [liveness_figures(table[UNGUARDED], n[f]) for n in noisy]
        check["fallbacks"][f]["table_with_noise"] = figures[0]
        if noise_seeds > 1:
            check["fallbacks"][f]["table_with_noise_by_seed"] = figures
    return check


def noisy_guard_figures(check, scenario, grid, tables, horizon, fallbacks, points: int, *,
                        mission_limit, alone=None, application=None):
    """The guard's figures on the grid again with the score noise that ``check`` (a
    `guard_check` record) fitted, seeded as its check: ``(liveness, curves)``, the
    `liveness_figures` of each fallback at the scenario's threshold and the trade-off
    curves (`Application.tradeoff_curves`, when ``points``); ``({}, {})`` when the check
    fitted no noise (no check, no noise runs, or a failed fit). ``application``: default
    the taxi."""
    fit = (check or {}).get("score_noise")
    if not fit or "error" in fit:
        return {}, {}
    application = _or_default(application)
    noise = ScoreNoise(sigma=fit["sigma"], length=fit["length"], mean=fit["mean"])
    kw = dict(mission_limit=mission_limit, score_noise=noise, seed=fit["seed"])
    runs = application.fallback_rollouts(scenario, grid, tables, horizon, fallbacks,
                                         alone=alone, **kw)
    liveness = {f: liveness_figures(runs[UNGUARDED], runs[f]) for f in fallbacks}
    curves = (application.tradeoff_curves(scenario, grid, tables, horizon, fallbacks, points,
                                          alone=runs[UNGUARDED], **kw) if points else {})
    return liveness, curves


def budget_threshold(scenario, grid, tables, fallback: str, budget: float, *, starts: int,
                     seed: int, horizon: float, mission_limit, noise_starts: int,
                     noise_seed: int, cache_dir, executor=None, progress=True,
                     application=None) -> dict:
    """A flag budget turned into this environment's detector threshold, without labels:
    `Application.flag_budget_threshold` for ``fallback`` from ``starts`` starts seeded
    ``seed``, in the tables with the score noise fitted on ``noise_starts`` real runs of
    the controller alone (`fit_guard_noise`; without it when 0 or when the fit fails).
    Its record, with the scenario's own threshold beside it and how the noise fit went.
    ``application``: default the taxi."""
    application = _or_default(application)
    noise, fit = None, None
    if noise_starts:
        noise, fit = fit_guard_noise(scenario, grid, tables, noise_starts=noise_starts,
                                     noise_seed=noise_seed, horizon=horizon, cache_dir=cache_dir,
                                     executor=executor, progress=progress,
                                     application=application)
    points = application.starts(scenario, grid, starts, seed)
    chosen = application.flag_budget_threshold(scenario, grid, tables, horizon, fallback, budget,
                                               starts=points, mission_limit=mission_limit,
                                               score_noise=noise, seed=noise_seed)
    return {**chosen, "seed": seed, "score_noise": noise is not None, "score_noise_fit": fit,
            "scenario_threshold": scenario.monitor.threshold}


def guard_figures(application, scenario, grid, spec, *, sweep_cache, outcomes_cache,
                  executor=None, progress=True) -> dict:
    """The guard's figures of one environment, what ``reachwatch run``'s guard stage and
    ``reachwatch guard`` share, with the settings of ``spec`` (a `RunSpec`: its
    ``horizon`` and ``guard``): the guarded sweep of ``scenario`` over ``grid``
    (``tables``, cached under ``sweep_cache``); with ``guard.flag_budget``, the
    threshold it sets without labels (``budget``, `budget_threshold`; the scenario's
    monitor is set to it); the controller alone's and each fallback's outcomes on the
    grid (``on_grid``), their failure sets (``volumes``) and ``liveness``; the
    trade-off ``curves`` (none for 0 ``guard.tradeoff_points``); the real-loop ``check``
    (`guard_check`, real runs cached under ``outcomes_cache``; None for 0
    ``guard.check_starts``) and the grid's figures with the score noise it fitted
    (``noisy_liveness``, ``noisy``: `noisy_guard_figures`)."""
    check_per_state_monitor(scenario.monitor)
    guard, horizon = spec.guard, spec.horizon
    fallbacks = guard.strategies
    tables = application.sweep(scenario, grid, guarded=True, cache_dir=sweep_cache,
                               executor=executor, progress=progress)
    budget = None
    if guard.flag_budget is not None:          # the threshold, set here without labels
        budget = budget_threshold(scenario, grid, tables, fallbacks[0], guard.flag_budget,
                                  starts=guard.flag_budget_starts, seed=guard.flag_budget_seed,
                                  horizon=horizon, mission_limit=guard.mission_limit,
                                  noise_starts=guard.noise_starts, noise_seed=guard.noise_seed,
                                  cache_dir=outcomes_cache, executor=executor,
                                  progress=progress, application=application)
        scenario.monitor.threshold = budget["threshold"]
    on_grid = application.fallback_rollouts(scenario, grid, tables, horizon, fallbacks,
                                            mission_limit=guard.mission_limit)
    alone = on_grid[UNGUARDED]
    curves = (application.tradeoff_curves(scenario, grid, tables, horizon, fallbacks,
                                           guard.tradeoff_points,
                                           mission_limit=guard.mission_limit, alone=alone)
              if guard.tradeoff_points else {})
    check = (guard_check(scenario, grid, tables, fallbacks, starts=guard.check_starts,
                         seed=guard.check_seed, horizon=horizon,
                         mission_limit=guard.mission_limit, cache_dir=outcomes_cache,
                         executor=executor, progress=progress,
                         noise_starts=guard.noise_starts, noise_seed=guard.noise_seed,
                         application=application)
             if guard.check_starts else None)
    noisy_liveness, noisy = noisy_guard_figures(
        check, scenario, grid, tables, horizon, fallbacks, guard.tradeoff_points,
        mission_limit=guard.mission_limit, alone=alone, application=application)
    return {"tables": tables, "budget": budget, "on_grid": on_grid,
            "volumes": {k: float(v.failed.mean()) for k, v in on_grid.items()},
            "liveness": {f: liveness_figures(alone, on_grid[f]) for f in fallbacks},
            "curves": curves, "check": check, "noisy_liveness": noisy_liveness, "noisy": noisy}


def guard_plots(application, scenario, grid, spec, figures, folder):
    """The figures of `guard_figures` (``figures``) of ``scenario``'s environment, in
    ``folder``: its failure sets (``guard_ENV.png``, `Application.plot_failure_sets` at
    ``spec.slice_py``) and, when it has trade-off curves, their plot
    (``tradeoff_ENV.png``). Returns their paths (None for no trade-off plot)."""
    name, threshold = scenario.environment.name, scenario.monitor.threshold
    slices = application.plot_failure_sets(
        {k: v.failed for k, v in figures["on_grid"].items()}, grid, spec.horizon,
        scenario=scenario, at=spec.slice_py, path=folder / f"guard_{name}.png",
        title=f"{name}: failing start states (grey), detector at threshold {threshold:.3g}")
    if not figures["curves"]:
        return slices, None
    tradeoff = plot_tradeoff(
        figures["curves"], alone=figures["volumes"][UNGUARDED], noisy_curves=figures["noisy"],
        operating={f: tradeoff_row(v, threshold) for f, v in figures["liveness"].items()},
        noisy_operating={f: tradeoff_row(v, threshold)
                         for f, v in figures["noisy_liveness"].items()},
        path=folder / f"tradeoff_{name}.png",
        title=f"{name}: failures against liveness as the detector threshold sweeps (star: "
              f"threshold {threshold:.3g})")
    return slices, tradeoff


def guard_environment(run: Run, env) -> dict:
    spec, trained, application = run.spec, run.outputs["train"], run.application
    scenario = run.scenario_for(env)
    if scenario.monitor.detector or scenario.monitor.threshold is not None:
        warn_once("scenario.monitor.detector and threshold: the guard stage guards with the "
                  "detector this run trains, at its threshold, not the run file's (which "
                  "'reachwatch guard', 'simulate --loop guarded' and 'graph --loop guarded' "
                  "read); its fallback and flag rule are the run file's",
                  key="guard stage's own detector")
    scenario.monitor.detector = str(run.path(trained["detector"]))
    scenario.monitor.threshold = float(trained["threshold"])
    scenario.duration = spec.horizon
    scenario = application.resolved(scenario)
    grid = run.grid_for(env)
    fallbacks = spec.guard.strategies
    figures = guard_figures(application, scenario, grid, spec, sweep_cache=run.sweep_cache,
                            outcomes_cache=run.path("outcomes"), executor=run.executor,
                            progress=run.progress)
    on_grid, tables = figures["on_grid"], figures["tables"]
    perfect = application.fallback_rollouts(
        scenario, grid, tables, spec.horizon, fallbacks, threshold=0.0,
        scores=perfect_detector_scores(run.value_function(env.name), grid),
        mission_limit=spec.guard.mission_limit, alone=on_grid[UNGUARDED])
    perfect_liveness = {f: liveness_figures(perfect[UNGUARDED], perfect[f]) for f in fallbacks}
    slices, tradeoff = guard_plots(application, scenario, grid, spec, figures,
                                   run.path("figures"))
    run_record = showcase_run(run, scenario, on_grid, grid, env)
    # Both loops side by side in alternating blocks; the median per-round ratio (the VM drifts).
    shown = copy.deepcopy(scenario)
    shown.monitor = shown.monitor.with_fallback(
        run_record.get("strategy") or (fallbacks[0] if fallbacks else "slow_down"))
    alone, guarded_rate = paired_rates(application.loop_diagram(shown),
                                       application.loop_diagram(shown, guarded=True),
                                       rounds=3, duration=spec.guard.online_seconds,
                                       period=scenario.controller.period,
                                       starts=application.timing_starts(scenario, grid))
    return {"threshold": scenario.monitor.threshold, "flag_budget": figures["budget"],
            "volumes": figures["volumes"], "liveness": figures["liveness"],
            "liveness_with_noise": figures["noisy_liveness"],
            "perfect_detector": perfect_liveness,
            "tradeoff": figures["curves"], "tradeoff_with_noise": figures["noisy"],
            "tradeoff_figure": run.rel(tradeoff) if tradeoff else None,
            "check": figures["check"], "figure": run.rel(slices), "run": run_record,
            "online": {"alone_ticks_per_s": float(np.median(alone)),
                       "guarded_ticks_per_s": float(np.median(guarded_rate)),
                       "ratio": float(np.median(np.asarray(guarded_rate) / np.asarray(alone))),
                       "image": [scenario.camera.height, scenario.camera.width]}}


#: In the guard stage's key: 2 since a real run judged by distance that parks within the
#: horizon goes on to it (`reach.liveness.mission_done`), 3 since the score noise is
#: fitted on each run up to its first tick outside the box, so records of before are
#: run again.
GUARD_FORMAT = 3


#: The source in a guard record's key: this module (the guard's rollouts and figures
#: in reach/ are loop code, in its BRT's key already).
GUARD_CODE = ("reachwatch.pipeline.online_stages",)


def stage_guard(run: Run) -> dict:
    out = {}
    if not run.application.rolls_out_fallbacks(run.application.resolved(run.spec.scenario)):
        run.log(f"[guard] skipped: the application '{run.application.name}' has no fallback "
                f"rollouts")
        return out
    # the application keys the stage by its code too: its dynamics drive the table
    # rollouts at the fallback's speed, which the BRT (solved at the nominal speed) does
    # not see
    own = application_key(run.application)
    for env in run.spec.guard_environments():
        # content keys: a detector or BRT rebuilt with other bytes guards again
        key = digest(run.content_key("train"), run.content_key(f"solve_{env.name}"),
                     run.spec.guard, run.spec.scenario.monitor, run.spec.horizon,
                     {"guard_format": GUARD_FORMAT, "code": modules_source_digest(*GUARD_CODE)},
                     own)
        out[env.name] = run.stage(f"guard_{env.name}", key,
                                  lambda env=env: guard_environment(run, env))
    return out
