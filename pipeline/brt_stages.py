"""The BRT stages of ``reachwatch run``: sweep every environment's closed loop over
the solved box, then refine the table adaptively (``refine``) and solve the BRT
(robust where the swept output varies fast, with ``robust``), keeping the level and
variant real-loop runs find best with ``map_selection``.
Each reads the records of the stages before it and returns JSON-able outputs; the
sweeps and refinements are chunked and cached by content, so a killed stage
resumes where it stopped."""

import io
import time

import numpy as np

from reachwatch.reach import (compare_verdicts, min_target_along_rollouts, select_map,
                             sign_agreement, solve_brt)
from reachwatch.reach.fingerprint import modules_source_digest
from reachwatch.reach.robust import control_bounds
from reachwatch.reach.sweep import cached_table_digest
from reachwatch.systems.checks import device_kind
from reachwatch.systems.files import atomic_write_bytes

from .keys import digest
from .stages import Run
from .together import each_environment


def sweep_env(run: Run, env, *, checkpoint=None) -> dict:
    """Sweep ``env``'s closed loop over the grid (chunks cached in ``sweeps/``)."""
    scenario, grid = run.scenario_for(env, checkpoint), run.solved_grid_for(env)
    started = time.time()
    table = run.application.sweep(scenario, grid, cache_dir=run.sweep_cache,
                                  executor=run.executor, progress=run.progress)
    return {"sweep": table.key, "states": int(grid.size), "rendered": int(table.computed),
            "sweep_seconds": round(time.time() - started, 1)}


def sweep_rate(record) -> str:
    """States per second of the states a sweep rendered; "cached" when it rendered none."""
    rendered = record.get("rendered", record["states"])
    if not rendered:
        return "cached"
    return f"{rendered / max(record['sweep_seconds'], 0.1):.0f}"


def solve_env(run: Run, env, *, checkpoint=None, label="") -> dict:
    """Solve ``env``'s BRT from its (cached) sweep, refined adaptively ``refine.levels``
    times; check it against RK4 rollouts of the (refined) table from every node, plot
    a slice. The refined steering table is saved beside the value function. With
    ``map_selection``, the level and robust variant kept is the one real-loop runs
    found best (`select_map_by_runs`)."""
    spec = run.spec
    scenario, grid = run.scenario_for(env, checkpoint), run.solved_grid_for(env)
    table = run.application.sweep(scenario, grid, cache_dir=run.sweep_cache,
                                  executor=run.executor, progress=False)
    dynamics = run.application.dynamics(scenario)
    control_port = run.application.probe(scenario).control_port
    solved = [0.0]

    def solve(table, spread=spec.robust.min_spread_deg):
        started = time.time()
        # each level's table (refined ones too) checked, named by environment and port
        vf = solve_brt(table.grid, dynamics, table[control_port], horizon=spec.horizon,
                       where=f"{env.name}: {control_port}",
                       accuracy=spec.accuracy, period=scenario.controller.period,
                       periods_per_step=spec.periods_per_step,
                       control_bounds=control_bounds(table, control_port, spread,
                                                     neighbourhood=spec.robust.neighbourhood))
        solved[0] += time.time() - started
        return vf
    refine = spec.refine
    started = time.time()
    levels = run.application.refine(
        scenario, table, solve=solve, levels=refine.levels, band=refine.band,
        variation=None if refine.variation_deg is None else np.deg2rad(refine.variation_deg),
        cache_dir=run.sweep_cache, executor=run.executor, progress=run.progress)
    refine_seconds = time.time() - started - solved[0]
    key = table.key                            # the sweep's (`Application.sweep_key`)
    vf, table = levels[-1].solution, levels[-1].table
    spread = spec.robust.min_spread_deg
    chosen = None
    if spec.map_selection.starts:
        chosen, vf, table, spread = select_map_by_runs(run, env, scenario, levels, solve)
    grid, steering = table.grid, table[control_port]
    vf.metadata.update(environment=env.name, sweep=key, refine_levels=refine.levels,
                       robust_min_spread_deg=spread)
    name = f"{key}_{spec.horizon:g}s_{spec.accuracy}" + (
        f"_refined{refine.levels}_{digest(refine)[:8]}" if refine.levels else "") + (
        f"_robust_{digest(spec.robust)[:8]}" if spec.robust.enabled else "") + (
        f"_selected_{digest(spec.map_selection)[:8]}" if chosen else "")
    if chosen:
        vf.metadata.update(map_selection=chosen["kept"])
    path = vf.save(run.path(f"brt/value_{name}.npz"))
    out = {"value": run.rel(path), "brt_fraction": vf.brt_fraction,
           "brt_fraction_box": vf.brt_fraction_of(run.grid_for(env)), "grid": list(grid.shape),
           "nodes_rendered": [lv.rendered for lv in levels]}
    if chosen:
        out["map_selection"] = chosen
    if refine.levels:
        buffer = io.BytesIO()
        rendered = np.ones(grid.shape, bool) if table.rendered is None else table.rendered
        np.savez(buffer, steering=steering, rendered=rendered, lo=grid.lo, hi=grid.hi)
        out["table"] = run.rel(atomic_write_bytes(run.path(f"brt/table_{name}.npz"),
                                                  buffer.getvalue()))
        out["refine_seconds"] = round(refine_seconds, 1)
    reference = min_target_along_rollouts(grid, dynamics, steering, grid.states(),
                                          horizon=spec.horizon, hold=scenario.controller.period)
    figure = run.application.plot_slices(
        {f"{env.name}{label}": vf}, scenario=scenario, at=spec.slice_py,
        path=run.path(f"figures/brt_{env.name}{label.replace(' ', '_')}.png"))
    return {**out, "rollout_agreement": sign_agreement(vf.values.ravel(), reference),
            "solve_seconds": round(solved[0], 2), "figure": run.rel(figure)}


def select_map_by_runs(run: Run, env, scenario, levels, solve):
    """``(record, value function, table, robust spread)`` of the map real-loop runs of
    ``scenario`` (the one the maps were swept from) find best among every refinement level, each solved as ``robust`` says and robustly with
    each of ``map_selection.robust_spreads_deg`` (`reach.select_map`; the runs are
    cached by content under the run's ``outcomes``, as the fidelity check's)."""
    spec, selection = run.spec, run.spec.map_selection
    own = spec.robust.min_spread_deg
    candidates = []                         # (name, level, value function, spread)
    for i, level in enumerate(levels):
        candidates.append((f"level {i}" + ("" if own is None else f", robust {own:g} deg"),
                           level, level.solution, own))
        for spread in selection.robust_spreads_deg:
            if spread != own:
                candidates.append((f"level {i}, robust {spread:g} deg", level,
                                   solve(level.table, spread), spread))
    starts = run.application.starts(scenario, run.grid_for(env), selection.starts,
                                    selection.seed)
    outcomes = run.application.real_outcomes(
        scenario, starts, grid=run.solved_grid_for(env), duration=spec.horizon,
        cache_dir=run.path("outcomes"), executor=run.executor, progress=run.progress)
    scores = [compare_verdicts(vf.in_brt(starts), outcomes.failed, outcomes["left_box"])
              for _, _, vf, _ in candidates]
    kept = select_map(scores, costs=[level.rendered for _, level, _, _ in candidates],
                      false_safe_weight=selection.false_safe_weight)
    name, level, vf, spread = candidates[kept]
    record = {"starts": selection.starts, "seed": selection.seed, "kept": name,
              "candidates": [{"map": n, "nodes_rendered": int(lv.rendered), **f.as_dict()}
                             for (n, lv, _, _), f in zip(candidates, scores)]}
    return record, vf, level.table, spread


#: The source in a solve record's key: this module, which sets up and writes each solve
#: (its grid, refinement, map selection and plots).
SOLVE_CODE = ("reachwatch.pipeline.brt_stages",)


def sweep_stage_key(run: Run, env) -> str:
    """The key of ``env``'s sweep record: its sweep's content key (no rendering)."""
    return run.application.sweep_key(run.scenario_for(env), run.solved_grid_for(env))


def solve_stage_key(run: Run, env, *, sweep: bool = False) -> str:
    """The key of ``env``'s solve record: the content of the table it solves, its sweep
    as cached now (`cached_table_digest`; None when a chunk is missing or fails its
    checksum, and with ``sweep`` those are swept again first), the solve's settings, and
    `SOLVE_CODE` (the solver itself, in reach/, is loop code: in the sweep's key). An
    edited table is solved again; without ``sweep`` nothing is rendered to find out."""
    spec, size, sweep_key = run.spec, run.solved_grid_for(env).size, sweep_stage_key(run, env)
    table = cached_table_digest(run.sweep_cache, sweep_key, size)
    if table is None and sweep:
        sweep_env(run, env)
        table = cached_table_digest(run.sweep_cache, sweep_key, size)
    return digest(sweep_key, table, spec.horizon, spec.accuracy, spec.periods_per_step,
                  spec.slice_py, {"code": modules_source_digest(*SOLVE_CODE)},
                  device_kind(),            # the solve's device: CUDA where present
                  *([spec.refine] if spec.refine.levels else []),
                  *([spec.robust] if spec.robust.enabled else []),
                  *([spec.map_selection] if spec.map_selection.starts else []))


def stage_sweep(run: Run) -> dict:
    """Sweep every environment the run needs (one record each, keyed by content), all
    their chunks together on the run's executor (`each_environment`; inline, one
    after another)."""
    return each_environment(run, run.environments(), _sweep_record,
                            what="sweep of environment", unit="state")


def _sweep_record(run: Run, env) -> dict:
    return run.stage(f"sweep_{env.name}", sweep_stage_key(run, env),
                     lambda: sweep_env(run, env))


def stage_solve(run: Run) -> dict:
    """The BRT of every environment the run needs, from its sweep."""
    out = {}
    for env in run.environments():
        key = solve_stage_key(run, env, sweep=True)
        out[env.name] = {**run.outputs[f"sweep_{env.name}"], **run.stage(
            f"solve_{env.name}", key, lambda env=env: solve_env(run, env))}
    return out
