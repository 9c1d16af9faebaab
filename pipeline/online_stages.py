"""The online stages of ``reachwatch run``: guard (the guarded loop's failure
sets and liveness per fallback, their trade-off as the threshold sweeps, the same
figures from the real Drake loops, a real nominal-vs-guarded run, the online rate) and incremental (TaxiNet
fine-tuned on mined anomalies, the held-out BRT recomputed)."""

import copy
import dataclasses as dc

import numpy as np
from scipy.ndimage import uniform_filter

from reachwatch.diagrams import (file_hash, load_taxinet,
                                 make_closed_loop_diagram, make_guarded_diagram, paired_rates,
                                 simulate)
from reachwatch.diagrams.plots import plot_runway_top_view
from reachwatch.diagrams.scenario import InitialState
from reachwatch.reach import ValueFunction
from reachwatch.reach.liveness import liveness_figures
from reachwatch.reach.score_noise import ScoreNoise
from reachwatch.systems import fallback_parts
from reachwatch.taxi import (UNGUARDED, fallback_rollouts, mission_rollouts, on_runway_starts,
                             perfect_detector_scores, real_missions, resolved, simulate_guarded,
                             sweep_guarded)
from reachwatch.taxi.fidelity import real_score_noise
from reachwatch.taxi.guarded import (SCORE_PORT, flag_budget_threshold, tradeoff_curves,
                                     tradeoff_row)
from reachwatch.taxi.plots import plot_brt_slices, plot_failure_sets, plot_tradeoff
from reachwatch.taxi.incremental import fine_tune_taxinet, mine_anomalies

from .spec import digest
from .brt_stages import solve_env, sweep_env
from .stages import Run


def robust_starts(mask, grid, limit):
    """Up to ``limit`` node indices where ``mask`` holds, those whose 3x3x3
    neighbourhood agrees most first (ties: nearest the centreline)."""
    mask = mask.reshape(grid.shape)
    support = uniform_filter(mask.astype(float), size=3, mode="nearest").ravel()
    index = np.flatnonzero(mask.ravel())
    px = np.abs(grid.states(index)[:, 0])
    return index[np.lexsort((px, -support[index]))][:limit]


def _state(x):
    return InitialState(px=float(x[0]), py=float(x[1]), theta_deg=float(np.rad2deg(x[2])))


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
    spec = run.spec
    tried, moving_save, stop_save, delayed = [], None, None, None
    for name, node in showcase_candidates(on_grid, spec.guard.strategies, grid,
                                          spec.guard.candidates):
        x0 = grid.states([node])[0]
        alone, guarded = (mission_rollouts(scenario, f, spec.horizon, x0[None],
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
    shown_scenario.initial_state = _state(shown["start"])
    nominal, guarded, paths = simulate_guarded(shown_scenario, run.path("figures"),
                                               meshcat_html=spec.guard.meshcat_html)
    record.update(strategy=shown["fallback"], start=shown["start"],
                  nominal_fails=nominal.failed, guarded_fails=guarded.failed,
                  lowest_speed=float(np.min(guarded.speed)),
                  final_speed=float(np.asarray(guarded.speed).ravel()[-1]),
                  flagged_ticks=int(np.sum(np.asarray(guarded.anomaly) >= 0.5)),
                  ticks=len(guarded.time), files=[run.rel(p) for p in paths])
    return record


def fit_guard_noise(scenario, grid, tables, *, noise_starts: int, noise_seed: int,
                    horizon: float, cache_dir, executor=None, progress=True):
    """The detector's variation between the nodes of the guarded sweep ``tables``
    (`real_score_noise`), fitted on ``noise_starts`` real runs of the controller alone
    from on-runway starts seeded ``noise_seed``: ``(noise, record)``, the record holding
    the fit (mean, sigma, length, runs, ticks, seed); ``(None, record)`` with the reason
    when it cannot be fitted."""
    calibration = on_runway_starts(grid, noise_starts, noise_seed,
                                   half_width=scenario.environment.half_width)
    try:
        noise, fit = real_score_noise(scenario, grid, tables[SCORE_PORT], calibration,
                                      duration=horizon, cache_dir=cache_dir, executor=executor,
                                      progress=progress)
    except ValueError as e:
        return None, {"error": str(e), "runs": noise_starts, "seed": noise_seed}
    return noise, {**dc.asdict(noise), **fit, "seed": noise_seed}


def guard_check(scenario, grid, tables, fallbacks, *, starts: int, seed: int, horizon: float,
                mission_limit, cache_dir, executor=None, progress=True, noise_starts: int = 0,
                noise_seed: int = 4000, noise_seeds: int = 1) -> dict:
    """Every fallback and the controller alone in the real Drake loops from ``starts``
    seeded on-runway starts, beside the tables' figures from the same starts; with
    ``noise_starts``, also beside the tables with the detector's variation between
    nodes (`reach.score_noise`) fitted on that many other real runs of the controller
    alone (starts and noise seeded ``noise_seed``; with ``noise_seeds`` > 1 the tables
    are also rolled out with the noise seeded ``noise_seed + 1, ...``, kept per fallback
    as ``table_with_noise_by_seed``). A fit that fails is recorded with its reason and
    the check goes on."""
    if noise_seeds < 1:
        raise ValueError(f"noise_seeds must be >= 1, got {noise_seeds}")
    points = on_runway_starts(grid, starts, seed, half_width=scenario.environment.half_width)
    table = fallback_rollouts(scenario, grid, tables, horizon, fallbacks, starts=points,
                              mission_limit=mission_limit)
    real = {f: real_missions(scenario, points, fallback=None if f == UNGUARDED else f,
                             duration=horizon, mission_limit=mission_limit, cache_dir=cache_dir,
                             executor=executor, progress=progress)
            for f in [UNGUARDED, *fallbacks]}
    check = {"starts": len(points), "seed": seed,
             "fallbacks": {f: {"table": liveness_figures(table[UNGUARDED], table[f]),
                               "real": liveness_figures(real[UNGUARDED], real[f])}
                           for f in fallbacks}}
    if not noise_starts:
        return check
    noise, check["score_noise"] = fit_guard_noise(
        scenario, grid, tables, noise_starts=noise_starts, noise_seed=noise_seed,
        horizon=horizon, cache_dir=cache_dir, executor=executor, progress=progress)
    if noise is None:
        return check
    noisy = [fallback_rollouts(scenario, grid, tables, horizon, fallbacks, starts=points,
                               mission_limit=mission_limit, score_noise=noise,
                               seed=noise_seed + k, alone=table[UNGUARDED])
             for k in range(noise_seeds)]
    for f in fallbacks:
        figures = [liveness_figures(table[UNGUARDED], n[f]) for n in noisy]
        check["fallbacks"][f]["table_with_noise"] = figures[0]
        if noise_seeds > 1:
            check["fallbacks"][f]["table_with_noise_by_seed"] = figures
    return check


def noisy_guard_figures(check, scenario, grid, tables, horizon, fallbacks, points: int, *,
                        mission_limit, alone=None):
    """The guard's figures on the grid again with the score noise that ``check`` (a
    `guard_check` record) fitted, seeded as its check: ``(liveness, curves)``, the
    `liveness_figures` of each fallback at the scenario's threshold and the trade-off
    curves (`tradeoff_curves`, when ``points``); ``({}, {})`` when the check fitted no
    noise (no check, no noise runs, or a failed fit)."""
    fit = (check or {}).get("score_noise")
    if not fit or "error" in fit:
        return {}, {}
    noise = ScoreNoise(sigma=fit["sigma"], length=fit["length"], mean=fit["mean"])
    kw = dict(mission_limit=mission_limit, score_noise=noise, seed=fit["seed"])
    runs = fallback_rollouts(scenario, grid, tables, horizon, fallbacks, alone=alone, **kw)
    liveness = {f: liveness_figures(runs[UNGUARDED], runs[f]) for f in fallbacks}
    curves = (tradeoff_curves(scenario, grid, tables, horizon, fallbacks, points,
                              alone=runs[UNGUARDED], **kw) if points else {})
    return liveness, curves


def budget_threshold(scenario, grid, tables, fallback: str, budget: float, *, starts: int,
                     seed: int, horizon: float, mission_limit, noise_starts: int,
                     noise_seed: int, cache_dir, executor=None, progress=True) -> dict:
    """A flag budget turned into this environment's detector threshold, without labels:
    `flag_budget_threshold` for ``fallback`` from ``starts`` on-runway starts seeded
    ``seed``, in the tables with the score noise fitted on ``noise_starts`` real runs of
    the controller alone (`fit_guard_noise`; without it when 0 or when the fit fails).
    Its record, with the scenario's own threshold beside it and how the noise fit went."""
    noise, fit = None, None
    if noise_starts:
        noise, fit = fit_guard_noise(scenario, grid, tables, noise_starts=noise_starts,
                                     noise_seed=noise_seed, horizon=horizon, cache_dir=cache_dir,
                                     executor=executor, progress=progress)
    points = on_runway_starts(grid, starts, seed, half_width=scenario.environment.half_width)
    chosen = flag_budget_threshold(scenario, grid, tables, horizon, fallback, budget,
                                   starts=points, mission_limit=mission_limit,
                                   score_noise=noise, seed=noise_seed)
    return {**chosen, "seed": seed, "score_noise": noise is not None, "score_noise_fit": fit,
            "scenario_threshold": scenario.monitor.threshold}


def real_loop_check(run: Run, scenario, grid, tables, env) -> dict:
    """`guard_check` with the run file's ``guard`` settings."""
    guard = run.spec.guard
    return guard_check(scenario, grid, tables, guard.strategies, starts=guard.check_starts,
                       seed=guard.check_seed, horizon=run.spec.horizon,
                       mission_limit=guard.mission_limit, cache_dir=run.path("outcomes"),
                       executor=run.executor, progress=run.progress,
                       noise_starts=guard.noise_starts, noise_seed=guard.noise_seed)


def guard_environment(run: Run, env) -> dict:
    spec, trained = run.spec, run.outputs["train"]
    scenario = run.scenario_for(env)
    scenario.monitor.detector = str(run.path(trained["detector"]))
    scenario.monitor.threshold = float(trained["threshold"])
    scenario.duration = spec.horizon
    scenario = resolved(scenario)
    grid = run.grid_for(env)
    fallbacks = spec.guard.strategies
    tables = sweep_guarded(scenario, grid, cache_dir=run.sweep_cache, executor=run.executor,
                           progress=run.progress)
    budget = None
    if spec.guard.flag_budget is not None:          # the threshold, set here without labels
        guard = spec.guard
        budget = budget_threshold(scenario, grid, tables, guard.strategies[0], guard.flag_budget,
                                  starts=guard.flag_budget_starts, seed=guard.flag_budget_seed,
                                  horizon=spec.horizon, mission_limit=guard.mission_limit,
                                  noise_starts=guard.noise_starts, noise_seed=guard.noise_seed,
                                  cache_dir=run.path("outcomes"), executor=run.executor,
                                  progress=run.progress)
        scenario.monitor.threshold = budget["threshold"]
    on_grid = fallback_rollouts(scenario, grid, tables, spec.horizon, fallbacks,
                                mission_limit=spec.guard.mission_limit)
    volumes = {k: float(v.failed.mean()) for k, v in on_grid.items()}
    liveness = {f: liveness_figures(on_grid[UNGUARDED], on_grid[f]) for f in fallbacks}
    perfect = fallback_rollouts(scenario, grid, tables, spec.horizon, fallbacks, threshold=0.0,
                                scores=perfect_detector_scores(run.value_function(env.name), grid),
                                mission_limit=spec.guard.mission_limit, alone=on_grid[UNGUARDED])
    perfect_liveness = {f: liveness_figures(perfect[UNGUARDED], perfect[f]) for f in fallbacks}
    slices = plot_failure_sets({k: v.failed for k, v in on_grid.items()}, grid, spec.horizon,
                               py=spec.slice_py, half_width=env.half_width,
                               path=run.path(f"figures/guard_{env.name}.png"),
                               title=f"{env.name}: failing start states (grey), detector at "
                                     f"threshold {scenario.monitor.threshold:.3g}")
    curves = tradeoff_curves(scenario, grid, tables, spec.horizon, fallbacks,
                             spec.guard.tradeoff_points, mission_limit=spec.guard.mission_limit,
                             alone=on_grid[UNGUARDED]) if spec.guard.tradeoff_points else {}
    check = (real_loop_check(run, scenario, grid, tables, env)
             if spec.guard.check_starts else None)
    noisy_liveness, noisy = noisy_guard_figures(
        check, scenario, grid, tables, spec.horizon, fallbacks, spec.guard.tradeoff_points,
        mission_limit=spec.guard.mission_limit, alone=on_grid[UNGUARDED])
    operating = {f: tradeoff_row(liveness[f], scenario.monitor.threshold) for f in fallbacks}
    tradeoff = (plot_tradeoff(curves, operating=operating, alone=volumes[UNGUARDED],
                              noisy_curves=noisy,
                              noisy_operating={f: tradeoff_row(v, scenario.monitor.threshold)
                                               for f, v in noisy_liveness.items()},
                              path=run.path(f"figures/tradeoff_{env.name}.png"),
                              title=f"{env.name}: failures against liveness as the detector "
                                    f"threshold sweeps (star: threshold "
                                    f"{scenario.monitor.threshold:.3g})")
                if curves else None)
    run_record = showcase_run(run, scenario, on_grid, grid, env)
    # Both loops side by side in alternating blocks; the median per-round ratio (the VM drifts).
    shown = copy.deepcopy(scenario)
    shown.monitor = shown.monitor.with_fallback(
        run_record.get("strategy") or (fallbacks[0] if fallbacks else "slow_down"))
    alone, guarded_rate = paired_rates(make_closed_loop_diagram(shown), make_guarded_diagram(shown),
                                       rounds=3, duration=spec.guard.online_seconds,
                                       period=scenario.controller.period)
    return {"threshold": scenario.monitor.threshold, "flag_budget": budget,
            "volumes": volumes, "liveness": liveness,
            "liveness_with_noise": noisy_liveness,
            "perfect_detector": perfect_liveness,
            "tradeoff": curves, "tradeoff_with_noise": noisy,
            "tradeoff_figure": run.rel(tradeoff) if tradeoff else None,
            "check": check, "figure": run.rel(slices), "run": run_record,
            "online": {"alone_ticks_per_s": float(np.median(alone)),
                       "guarded_ticks_per_s": float(np.median(guarded_rate)),
                       "ratio": float(np.median(np.asarray(guarded_rate) / np.asarray(alone))),
                       "image": [scenario.camera.height, scenario.camera.width]}}


def stage_guard(run: Run) -> dict:
    out = {}
    if run.application.fallback_rollouts is None:      # nothing to roll the fallbacks out on
        run.log(f"[guard] skipped: the application '{run.application.name}' has no fallback "
                f"rollouts")
        return out
    for env in run.spec.guard_environments():
        # content keys: a detector or BRT rebuilt with other bytes guards again
        key = digest(run.content_key("train"), run.content_key(f"solve_{env.name}"),
                     run.spec.guard, run.spec.scenario.monitor, run.spec.horizon)
        out[env.name] = run.stage(f"guard_{env.name}", key,
                                  lambda env=env: guard_environment(run, env))
    return out


def incremental(run: Run) -> dict:
    spec, config = run.spec, run.spec.incremental
    env = config.environment
    progress = run.bar()
    train = spec.training_environments()
    mined = mine_anomalies(list(zip(train, run.datasets(train))), config.anomalies,
                           np.random.default_rng(config.seed))
    base = resolved(run.scenario_for(env)).controller.checkpoint
    path = run.path(f"incremental/taxinet_{digest(config, run.outputs['dataset'], file_hash(base))}.pt")
    seconds = None
    if not path.exists():
        seconds = fine_tune_taxinet(base, mined, config, spec.scenario.camera, path,
                                    progress=progress)["fine_tune_seconds"]
    meta = {**load_taxinet(path)[2], "fine_tune_seconds": seconds}
    after = {**sweep_env(run, env, checkpoint=path),
             **solve_env(run, env, checkpoint=path, label=" fine-tuned")}
    before_vf, after_vf = run.value_function(env.name), ValueFunction.load(run.path(after["value"]))
    grid = before_vf.grid
    saved = (before_vf.values.ravel() <= 0) & (after_vf.values.ravel() > 0)
    star = grid.states(robust_starts(saved, grid, 1))
    figure = plot_brt_slices({"vanilla TaxiNet": before_vf, "fine-tuned TaxiNet": after_vf},
                             py=spec.slice_py, half_width=env.half_width,
                             path=run.path(f"figures/incremental_{env.name}.png"),
                             points=[("start (saved by fine-tuning)", star, "m*")] if len(star)
                             else None)
    result = {"environment": env.name, "checkpoint": run.rel(path),
              "before": run.outputs["solve"][env.name]["brt_fraction"],
              "after": after["brt_fraction"], "after_record": after, "figure": run.rel(figure),
              "fine_tune": {k: meta.get(k) for k in ("mined_states", "replayed_states",
                                                      "mined_per_environment",
                                                      "mined_error_before", "mined_error_after",
                                                      "fine_tune_seconds")}}
    if len(star):
        trajectories = []
        for label, checkpoint in (("vanilla TaxiNet", base), ("fine-tuned TaxiNet", path)):
            scenario = run.scenario_for(env, checkpoint)
            t = simulate(make_closed_loop_diagram(scenario), initial_state=star[0],
                         period=scenario.controller.period,
                         duration=spec.horizon, half_width=env.half_width)
            trajectories.append((t, f"{label}{' (fails)' if t.failed else ''}"))
        result["star"] = {"start": [float(v) for v in star[0]],
                          "vanilla_fails": trajectories[0][0].failed,
                          "fine_tuned_fails": trajectories[1][0].failed,
                          "figure": run.rel(plot_runway_top_view(
                              trajectories, half_width=env.half_width,
                              path=run.path(f"figures/incremental_run_{env.name}.png"),
                              title=f"{env.name}: from the starred start"))}
    return result


def stage_incremental(run: Run) -> dict:
    config = run.spec.incremental
    if not config.enabled:
        return {}
    key = digest(config, run.content_key("dataset"),
                 run.content_key(f"solve_{config.environment.name}"))
    return run.stage("incremental", key, lambda: incremental(run))
