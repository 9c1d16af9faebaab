"""``reachwatch guard``: failure sets with and without the fallback."""

import argparse
import dataclasses as dc
import json
import time

from .commands import (RunFileDefault, check_detector, count, grid_nodes, horizon_seconds,
                       mission_multiple, open_share, output_folder, positive_int,
                       scenario_from_args, scenario_words, seed_number)
from .console import log
from .executor_option import add_executor_argument
from .overlays import add_overlay_arguments

def add_parsers(sub):
    g = sub.add_parser("guard", help="failure sets (fraction of grid starts that leave the "
                       "runway within the horizon) under the controller alone and under each "
                       "fallback, with their liveness (starts ended stopped, needless stops, "
                       "distance travelled, ticks flagged) and the trade-off as the detector "
                       "threshold sweeps, from one sweep of the guarded diagram")
    g.add_argument("--scenario", required=True, help="scenario YAML with monitor.detector "
                   "(the detector checkpoint the guarded loop runs)")
    add_overlay_arguments(g)
    # every default below is the run file's (`RunFileDefault`), as --help says
    g.add_argument("--shape", type=grid_nodes, nargs=3, default=RunFileDefault("grid"),
                   metavar=("NPX", "NPY", "NTHETA"),
                   help="grid nodes over the paper's box (default: %(default)s)")
    g.add_argument("--horizon", type=horizon_seconds, default=RunFileDefault("horizon"),
                   help="s (default: %(default)s)")
    g.add_argument("--fallbacks", nargs="+", type=_fallback,
                   default=RunFileDefault("guard.strategies"),
                   help="speed strategy, optionally '+' the steering while flagged "
                        "(dead_reckoning; oracle is privileged, a reference only); "
                        "default: %(default)s")
    g.add_argument("--tradeoff-points", type=positive_int,
                   default=RunFileDefault("guard.tradeoff_points"),
                   help="detector thresholds on the trade-off curve (default: %(default)s)")
    g.add_argument("--check-starts", type=count, default=RunFileDefault("guard.check_starts"),
                   help="also run the real Drake loops (alone and each fallback) from this "
                        "many seeded random on-runway starts; cached and resumable (default: "
                        "%(default)s; 0: no real-loop check)")
    g.add_argument("--seed", type=seed_number, default=RunFileDefault("guard.check_seed"),
                   help="seed of the check starts (default: %(default)s)")
    g.add_argument("--noise-starts", type=count, default=RunFileDefault("guard.noise_starts"),
                   help="with --check-starts: fit the detector's variation between grid "
                        "nodes on this many other real runs of the controller alone and show "
                        "the tables with it beside the real loop (0 = no fit; default: "
                        "%(default)s)")
    g.add_argument("--noise-seed", type=seed_number, default=RunFileDefault("guard.noise_seed"),
                   help="seed of the noise fit's starts and of the noise (default: "
                        "%(default)s)")
    g.add_argument("--flag-budget", type=open_share, default=RunFileDefault("guard.flag_budget"),
                   help="set the detector threshold without labels: the one at which the "
                        "first fallback flags this share of its control ticks in the tables "
                        "(with the score noise when --noise-starts fits it), instead of the "
                        "scenario's (default: %(default)s; null: the scenario's)")
    g.add_argument("--flag-budget-starts", type=positive_int,
                   default=RunFileDefault("guard.flag_budget_starts"),
                   help="on-runway starts the flag budget is rolled out from (default: "
                        "%(default)s)")
    g.add_argument("--flag-budget-seed", type=seed_number,
                   default=RunFileDefault("guard.flag_budget_seed"),
                   help="seed of the flag budget's starts (default: %(default)s)")
    g.add_argument("--mission-limit", type=mission_multiple,
                   default=RunFileDefault("guard.mission_limit"),
                   help="also judge failures by distance: runs go on past the horizon, for "
                        "up to this many horizons, until they cover the distance the "
                        "controller alone covers within it (a slower aircraft on the same "
                        "path otherwise fails only later; default: %(default)s)")
    g.add_argument("--out", required=True, help="output folder (guard_ENV.json, the "
                   "failure-set and trade-off plots)")
    add_executor_argument(g)
    g.add_argument("--cache", default=None, help="cache folder of the guarded sweep and the "
                   "real-loop runs (default: $REACHWATCH_CACHE or ~/.cache/reachwatch)")
    g.set_defaults(func=guard_command)


def _fallback(text):
    """A fallback's one name (`Fallback.parse`), as the run file keeps it: a misspelt
    name is a clear error before any work, and spellings of one fallback are one."""
    from reachwatch.systems import Fallback
    try:
        return Fallback.parse(text).name
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def _monitor_settings(monitor) -> str:
    """The monitor settings every fallback shares, as the log shows them."""
    resume = ("at once" if not monitor.resume_acceleration
              else f"at {monitor.resume_acceleration:g} m/s^2")
    return (f"brake {monitor.brake_deceleration:g} m/s^2, speed back {resume}, flags "
            f"{monitor.flags_needed} of {monitor.flag_window}")


def guard_spec(args, scenario):
    """The run file the flags describe (`RunSpec`): ``scenario`` as the run's scenario
    and its one guard environment, ``--shape`` as its grid, ``--horizon`` and the
    ``guard`` section from the other flags; every key no flag sets is the run file's
    default."""
    from reachwatch.systems.bounds import check_bounds

    from .spec import GuardSpec, RunSpec
    spec = RunSpec(name="guard", scenario=scenario, test=[scenario.environment],
                   grid=list(args.shape), horizon=args.horizon,
                   guard=GuardSpec(environments=[scenario.environment],
                                   strategies=list(args.fallbacks),
                                   tradeoff_points=args.tradeoff_points,
                                   check_starts=args.check_starts, check_seed=args.seed,
                                   noise_starts=args.noise_starts, noise_seed=args.noise_seed,
                                   flag_budget=args.flag_budget,
                                   flag_budget_starts=args.flag_budget_starts,
                                   flag_budget_seed=args.flag_budget_seed,
                                   mission_limit=args.mission_limit))
    check_bounds(spec.guard, "guard.")
    return spec


def guard_command(args):
    """The run's guard stage (`online_stages.guard_figures` and `guard_plots`) on the
    scenario's environment, at the scenario's detector and threshold, with its figures
    logged and written to ``--out``."""
    from reachwatch.reach.application import load_application
    from reachwatch.reach.liveness import UNGUARDED, percent, same_distance
    from reachwatch.systems.files import atomic_write_bytes, cache_join, cache_root

    from .executors import open_executor
    from .online_stages import guard_figures, guard_plots

    scenario = scenario_from_args(args, controller=True)
    check_detector(scenario, scenario_words(args.scenario))   # before the sweep, not after it
    scenario.monitor = scenario.monitor.with_checkpoint_defaults()  # what the log shows
    spec = guard_spec(args, scenario)
    fallbacks = spec.guard.strategies
    application = load_application(spec.application)
    application.check_guard(scenario, fallbacks, skipped=False)
    grid = application.grid(scenario, tuple(spec.grid))
    cache = args.cache or cache_root()
    started = time.time()
    with open_executor(args.executor) as executor:
        out = output_folder(args.out)
        figures = guard_figures(application, scenario, grid, spec,
                                sweep_cache=cache_join(cache, "sweeps"),
                                outcomes_cache=cache_join(cache, "outcomes"), executor=executor)
    budget, check = figures["budget"], figures["check"] or {}
    volumes, liveness = figures["volumes"], figures["liveness"]
    if budget is not None:
        log.info(f"flag budget {100 * spec.guard.flag_budget:g} % of the ticks of "
                 f"{fallbacks[0]}: threshold {budget['threshold']:.3f} (the scenario's "
                 f"{budget['scenario_threshold']:.3f}), {100 * budget['flagged_ticks']:.1f} % "
                 f"flagged in the tables{' with the score noise' if budget['score_noise'] else ''}")
    name = scenario.environment.name
    log.info(f"{name}, grid {list(grid.shape)}, horizon {spec.horizon:g} s, detector "
             f"{scenario.monitor.detector} (threshold {scenario.monitor.threshold}); "
             f"{_monitor_settings(scenario.monitor)}; {time.time() - started:.1f} s")
    log.info(f"  controller alone: failure set {100 * volumes[UNGUARDED]:.2f}% of the grid")
    for f, v in liveness.items():
        log.info(f"  {f}: failure set {percent(v['failure_set'])}, ended stopped "
                 f"{percent(v['ended_stopped'])}, needless stops {percent(v['needless_stops'])}, "
                 f"distance {v['distance_ratio']:.2f} x alone, ticks flagged "
                 f"{100 * v['flagged_ticks']:.1f}%; {same_distance(v)}")
    for f, v in figures["noisy_liveness"].items():
        log.info(f"  {f}, + score noise: failure set {percent(v['failure_set'])}, ended stopped "
                 f"{percent(v['ended_stopped'])}, needless stops {percent(v['needless_stops'])}; "
                 f"{same_distance(v)}")
    if "score_noise" in check:
        n = check["score_noise"]
        log.info("  score noise between nodes: " + (
            f"not fitted ({n['error']})" if "error" in n else
            f"mean {n['mean']:+.3f}, sigma {n['sigma']:.3f} (logit), correlation length "
            f"{n['length']:.2f} m, from {n['runs']} real runs of the controller alone"))
    for f, both in check.get("fallbacks", {}).items():
        for source in ("table", "table_with_noise", "real"):
            if source not in both:
                continue
            v = both[source]
            log.info(f"  {check['starts']} starts, {source:16s} {f}: alone fails "
                     f"{percent(v['alone_failure_set'])}, guarded fails "
                     f"{percent(v['failure_set'])}, ended stopped {percent(v['ended_stopped'])}, "
                     f"needless stops {percent(v['needless_stops'])}; {same_distance(v)}")
    atomic_write_bytes(out / f"guard_{name}.json", json.dumps(
        {"monitor": dc.asdict(scenario.monitor), "flag_budget": budget, "volumes": volumes,
         "liveness": liveness, "liveness_with_noise": figures["noisy_liveness"],
         "tradeoff": figures["curves"], "tradeoff_with_noise": figures["noisy"],
         "check": check},
        indent=1).encode())
    guard_plots(application, scenario, grid, spec, figures, out)
    log.info(f"wrote {out / f'guard_{name}.json'}, guard_{name}.png and tradeoff_{name}.png")
