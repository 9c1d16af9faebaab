"""``reachwatch sweep`` and ``reachwatch brt``."""

import io
import time
from pathlib import Path

from .console import log, progress_enabled
from .executor_option import add_executor_argument
from .overlays import add_overlay_arguments
from .commands import (RunFileDefault, count, grid_nodes, horizon_seconds, non_negative_float, number_type,
                       output_folder, positive_float, positive_int, scenario_from_args,
                       seed_number, solved_py, solved_theta)

#: ``reachwatch.reach.ACCURACIES``' names, here so that the parser needs no torch (a
#: test keeps the two the same).
ACCURACIES = ("high", "low", "semi_lagrangian", "very_high")


def _grid_args(parser):
    parser.add_argument("--scenario", help="scenario YAML (environment, camera, controller)")
    add_overlay_arguments(parser)
    parser.add_argument("--shape", type=grid_nodes, nargs=3, default=RunFileDefault("grid"),
                        metavar=("NPX", "NPY", "NTHETA"),
                        help="grid nodes over the solved box (paper: 101 101 101; default: "
                        "%(default)s)")
    parser.add_argument("--solved-theta-deg", type=solved_theta, metavar="DEG",
                        default=RunFileDefault("solved_theta_deg"),
                        help="sweep and solve over |theta| <= DEG (the paper's box: 28); at "
                        "night the loop turns far past 28 deg within the horizon (default: "
                        "%(default)s)")
    parser.add_argument("--solved-py-max", type=solved_py, metavar="M",
                        default=RunFileDefault("solved_py_max"),
                        help="sweep and solve over py <= M (the paper's box: 250); a start "
                        "near 250 runs past it within the horizon (default: %(default)s)")
    parser.add_argument("--out", required=True, help="output folder")
    add_executor_argument(parser)
    parser.add_argument("--cache", default=None, help="sweep cache folder "
                        "(default: $REACHWATCH_CACHE/sweeps or ~/.cache/reachwatch/sweeps)")
    parser.add_argument("--chunk-size", type=positive_int, default=1024,
                        help="grid states per cached chunk (default: 1024)")


def add_parsers(sub):
    s = sub.add_parser("sweep", help="evaluate the closed loop's steering (and TaxiNet "
                       "estimate) at every grid state; cached and resumable")
    _grid_args(s)
    s.set_defaults(func=sweep_command)
    b = sub.add_parser("brt", help="sweep, solve the HJB-VI, write the value function and "
                       "slice plots, print BRT volume and agreement with rollouts")
    _grid_args(b)
    b.add_argument("--accuracy", choices=sorted(ACCURACIES), default=RunFileDefault("accuracy"),
                   help="HJB-VI scheme: semi_lagrangian (dynamic programming on the "
                   "sampled-data loop), low (first-order upwind, Euler), high / very_high "
                   "(WENO5, TVD-RK2 / RK3); default: %(default)s")
    b.add_argument("--periods-per-step", type=positive_int,
                   default=RunFileDefault("periods_per_step"),
                   help="semi_lagrangian: control periods per step; each step interpolates V "
                   "once, so fewer, longer steps blur a coarse grid's BRT less (default: "
                   "%(default)s)")
    b.add_argument("--horizon", type=horizon_seconds, default=RunFileDefault("horizon"),
                   help="s (default: %(default)s)")
    b.add_argument("--refine", type=number_type(int, 0, False, "a whole number in [0, 5]",
                                                most=5), default=RunFileDefault("refine.levels"),
                   help="adaptive refinement levels: each halves the spacing and renders new "
                   "nodes only where the BRT's boundary passes within --refine-band (default: "
                   "%(default)s)")
    b.add_argument("--refine-band", type=positive_float, default=RunFileDefault("refine.band"),
                   help="m (default: %(default)s)")
    b.add_argument("--robust-spread", type=non_negative_float, metavar="DEG",
                   default=RunFileDefault("robust.min_spread_deg"),
                   help="solve a robust BRT: where the swept steering ranges over more than "
                   "DEG across a node's neighbours, take its worst value in that range "
                   "(default: %(default)s; null: no robust BRT)")
    b.add_argument("--drake-starts", type=count, default=0,
                   help="also check the BRT against the real Drake closed loop (rendering "
                   "every tick) from this many seeded random on-runway starts, with 95 %% "
                   "Wilson intervals; each start costs a full-horizon simulation, so 50 "
                   "take minutes (default: 0, no check; cached and resumable)")
    b.add_argument("--seed", type=seed_number, default=RunFileDefault("fidelity.seed"),
                   help="seed of the --drake-starts starts (default: %(default)s)")
    b.set_defaults(func=brt_command)


def real_loop_fidelity(*args, **kwargs):
    """`reachwatch.taxi.real_loop_fidelity`, imported when a command runs (and
    replaceable here, as a test of the ``brt`` command does)."""
    from reachwatch.taxi import real_loop_fidelity
    return real_loop_fidelity(*args, **kwargs)


def _sweep(args):
    from reachwatch.systems.files import cache_root
    from reachwatch.taxi import paper_grid, sweep_closed_loop

    from .executors import open_executor
    scenario = scenario_from_args(args, controller=True)
    grid = paper_grid(scenario.environment.half_width, tuple(args.shape),
                      theta_deg=args.solved_theta_deg, py_max=args.solved_py_max)
    started = time.time()
    with open_executor(args.executor) as executor:
        output_folder(args.out)             # a bad --out fails before the sweep
        table = sweep_closed_loop(scenario, grid, cache_dir=args.cache or cache_root() / "sweeps",
                                  executor=executor, chunk_size=args.chunk_size)
    return scenario, grid, table, time.time() - started


def sweep_command(args):
    import numpy as np

    from reachwatch.diagrams import CONTROL_PORT, ESTIMATE_PORT
    from reachwatch.reach.solver import check_controls
    from reachwatch.systems.files import atomic_write_bytes
    from reachwatch.taxi import dynamics_for
    scenario, grid, table, seconds = _sweep(args)
    buffer = io.BytesIO()
    estimate = {"estimate": table[ESTIMATE_PORT]} if ESTIMATE_PORT in table.tables else {}
    np.savez(buffer, lo=grid.lo, hi=grid.hi, shape=grid.shape,
             steering_angle=table[CONTROL_PORT][..., 0], **estimate)
    path = atomic_write_bytes(Path(args.out) / f"sweep_{table.key}.npz", buffer.getvalue())
    rate = (f"{table.computed / max(seconds, 0.1):.1f} states/s" if table.computed
            else "all cached")
    log.info(f"{grid.size} states ({table.computed} rendered) in {seconds:.1f} s ({rate}); "
             f"wrote {path}")
    try:        # written all the same: the table is what the controller did
        check_controls(grid, dynamics_for(scenario), table[CONTROL_PORT],
                       where=f"{scenario.environment.name}: {CONTROL_PORT}")
    except ValueError as e:
        log.warning(f"warning: {e}; `reachwatch brt` refuses this table")


def brt_command(args):
    from reachwatch.diagrams import CONTROL_PORT
    from reachwatch.reach import min_target_along_rollouts, sign_agreement, solve_brt
    from reachwatch.systems.files import cache_join, cache_root
    from reachwatch.taxi import (dynamics_for, on_runway_starts, paper_grid, refine_closed_loop,
                                 steering_bounds)
    from reachwatch.taxi.plots import plot_brt_slices

    from .executors import open_executor
    scenario, grid, table, _ = _sweep(args)
    dynamics = dynamics_for(scenario)
    started = time.time()

    def solve(table):
        return solve_brt(table.grid, dynamics, table[CONTROL_PORT], horizon=args.horizon,
                         where=f"{scenario.environment.name}: {CONTROL_PORT}",
                         accuracy=args.accuracy, period=scenario.controller.period,
                         periods_per_step=args.periods_per_step,
                         control_bounds=steering_bounds(table, args.robust_spread))
    with open_executor(args.executor) as executor:
        levels = refine_closed_loop(scenario, table, solve=solve, levels=args.refine,
                                    band=args.refine_band, executor=executor,
                                    cache_dir=args.cache or cache_root() / "sweeps")
    vf, grid, control = levels[-1].solution, levels[-1].table.grid, levels[-1].table[CONTROL_PORT]
    if args.refine:
        log.info("adaptive refinement: " + " -> ".join(
            f"{'x'.join(map(str, lv.table.grid.shape))} ({lv.rendered} rendered)" for lv in levels))
    solve_s = time.time() - started
    out = Path(args.out)
    name = scenario.environment.name
    vf.metadata.update(environment=name, sweep_key=table.key, solve_seconds=solve_s)
    vf.save(out / f"value_{name}.npz")
    lowest = min_target_along_rollouts(grid, dynamics, control, grid.states(),
                                       horizon=args.horizon, progress=None)
    log.info(f"{name}: grid {list(grid.shape)}, accuracy {args.accuracy}, solve{' and refine' if args.refine else ''} {solve_s:.1f} s")
    if args.robust_spread is not None:
        log.info(f"robust BRT: the steering takes its worst value in its neighbours' range at "
                 f"the {100 * vf.metadata['bounded_nodes']:.1f}% of nodes where that range "
                 f"exceeds {args.robust_spread:g} deg")
    log.info(f"BRT volume: {100 * vf.brt_fraction:.2f}% of the grid")
    log.info(f"sign agreement with RK4 rollouts (dt 0.01 s, interpolated control) from every "
          f"node: {100 * sign_agreement(vf.values.ravel(), lowest):.2f}%")
    if args.drake_starts:
        # the check starts stay in the paper's box whatever the solved box
        half_width = scenario.environment.half_width
        starts = on_runway_starts(paper_grid(half_width, (2, 2, 2)), args.drake_starts,
                                  args.seed, half_width=half_width)
        fidelity = real_loop_fidelity(scenario, vf, starts, duration=args.horizon,
                                      cache_dir=cache_join(args.cache or cache_root(), "outcomes"),
                                      progress=progress_enabled())
        log.info(f"the real Drake closed loop (rendering every tick) from random on-runway "
                 f"starts, 95 % Wilson intervals: {fidelity.summary()}")
        if fidelity.box_exits > 0.05 * fidelity.n:
            log.warning(f"{fidelity.box_exits} of {fidelity.n} real runs left the solved box "
                        f"(py or theta) within the horizon: there the table is clamped to its "
                        f"edge and the BRT's verdict is a guess; widen the box (--solved-theta-deg, "
                        f"--solved-py-max)")
    for py in (100.0, 175.0, 250.0):
        plot_brt_slices({name: vf}, py=py, path=out / f"brt_{name}_py{py:.0f}.png",
                        half_width=scenario.environment.half_width)
    log.info(f"wrote {out / f'value_{name}.npz'} and slice plots brt_{name}_py*.png")
