"""The online stages of ``reachwatch run``: guard (the guarded loop's failure
sets, a real nominal-vs-guarded run, the online rate) and incremental (TaxiNet
fine-tuned on mined anomalies, the held-out BRT recomputed)."""

import numpy as np
from scipy.ndimage import uniform_filter

from reachwatch.diagrams import (file_hash, initial_state_vector, load_taxinet,
                                 make_closed_loop_diagram, make_guarded_diagram, paired_rates,
                                 simulate)
from reachwatch.diagrams.plots import plot_runway_top_view
from reachwatch.diagrams.scenario import InitialState
from reachwatch.reach import ValueFunction
from reachwatch.taxi import UNGUARDED, failure_sets, resolved, simulate_guarded, sweep_guarded
from reachwatch.taxi.plots import plot_brt_slices, plot_failure_sets
from reachwatch.training.incremental import fine_tune_taxinet, mine_anomalies

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


def guard_environment(run: Run, env) -> dict:
    spec, trained = run.spec, run.outputs["train"]
    scenario = run.scenario_for(env)
    scenario.monitor.detector = str(run.path(trained["detector"]))
    scenario.monitor.threshold = float(trained["threshold"])
    scenario.duration = spec.horizon
    scenario = resolved(scenario)
    grid = run.grid_for(env)
    tables = sweep_guarded(scenario, grid, cache_dir=run.sweep_cache, executor=run.executor,
                           progress=run.progress)
    failures = failure_sets(scenario, grid, tables, spec.horizon, spec.guard.strategies)
    volumes = {k: float(v.mean()) for k, v in failures.items()}
    slices = plot_failure_sets(failures, grid, spec.horizon, py=spec.slice_py,
                               half_width=env.half_width,
                               path=run.path(f"figures/guard_{env.name}.png"),
                               title=f"{env.name}: failing start states (grey), detector at "
                                     f"threshold {scenario.monitor.threshold:.3g}")
    # A start the tables say the guard saves, checked in the real Drake loops.
    best = min(spec.guard.strategies, key=lambda s: volumes[s]) if spec.guard.strategies else None
    tried, chosen = [], None
    scenario.monitor.strategy = best or scenario.monitor.strategy
    nominal_diagram, guarded_diagram = (make_closed_loop_diagram(scenario),
                                        make_guarded_diagram(scenario))
    if best is not None:
        contexts = [d.CreateDefaultContext() for d in (nominal_diagram, guarded_diagram)]
        for node in robust_starts(failures[UNGUARDED] & ~failures[best], grid,
                                  spec.guard.candidates):
            x0 = grid.states([node])[0]
            runs = [simulate(d, initial_state=x0, duration=spec.horizon,
                             period=scenario.controller.period,
                             half_width=env.half_width, context=c)
                    for d, c in zip((nominal_diagram, guarded_diagram), contexts)]
            tried.append({"start": [float(v) for v in x0], "nominal_fails": runs[0].failed,
                          "guarded_fails": runs[1].failed})
            if runs[0].failed and not runs[1].failed:
                chosen = x0
                break
    run_record = {"strategy": best, "tried": tried, "confirmed": chosen is not None}
    if tried:
        scenario.initial_state = _state(chosen if chosen is not None else tried[0]["start"])
        nominal, guarded, paths = simulate_guarded(scenario, run.path("figures"),
                                                   meshcat_html=spec.guard.meshcat_html)
        run_record.update(start=[float(v) for v in initial_state_vector(scenario.initial_state)],
                          nominal_fails=nominal.failed, guarded_fails=guarded.failed,
                          lowest_speed=float(np.min(guarded.speed)),
                          flagged_ticks=int(np.sum(np.asarray(guarded.anomaly) >= 0.5)),
                          files=[run.rel(p) for p in paths])
    # Both loops side by side in alternating blocks; the median per-round ratio (the VM drifts).
    alone, guarded_rate = paired_rates(nominal_diagram, guarded_diagram, rounds=3,
                                       duration=spec.guard.online_seconds,
                                       period=scenario.controller.period)
    return {"threshold": scenario.monitor.threshold, "volumes": volumes,
            "figure": run.rel(slices), "run": run_record,
            "online": {"alone_ticks_per_s": float(np.median(alone)),
                       "guarded_ticks_per_s": float(np.median(guarded_rate)),
                       "ratio": float(np.median(np.asarray(guarded_rate) / np.asarray(alone))),
                       "image": [scenario.camera.height, scenario.camera.width]}}


def stage_guard(run: Run) -> dict:
    out = {}
    for env in run.spec.guard_environments():
        key = digest(run.records["train"]["key"], run.records[f"solve_{env.name}"]["key"],
                     run.spec.guard, run.spec.scenario.monitor, run.spec.horizon)
        out[env.name] = run.stage(f"guard_{env.name}", key,
                                  lambda env=env: guard_environment(run, env))
    return out


def incremental(run: Run) -> dict:
    spec, config = run.spec, run.spec.incremental
    env = config.environment
    progress = run.bar()
    mined = mine_anomalies(list(zip(spec.train, run.datasets(spec.train))), config.anomalies,
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
    key = digest(config, run.outputs["dataset"], run.records[f"solve_{config.environment.name}"]["key"])
    return run.stage("incremental", key, lambda: incremental(run))
