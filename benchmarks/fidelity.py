"""How true are BRT verdicts and labels? For a day and a night environment: sweep and
solve the BRT on each uniform grid (with each solver step length), run the real Drake closed loop (rendering every
tick) from fresh seeded on-runway starts, and score each label source against it,
with the renders each one costs and 95 % Wilson intervals.

Label cost is in rendered frames per label of a 1000-state dataset, beyond the map.

- ``brt``: V(x0) <= 0; costs only the map's renders.
- ``hybrid``: an audit of ``--audit`` other on-runway states measures the largest
  |V| of a wrong verdict; the band is ``--band``, widened to ``--band-factor`` times
  that, and the map is trusted when the audit found no false-safe verdict and the band
  is at most ``--max-band`` m. The verdict
  at a check start is then its real outcome where the hybrid rule would roll out
  (|V| < band, and every V > 0 if the map is not trusted), the BRT's elsewhere. Its
  cost is the audit plus the rolled-out share.
- ``hyb>traj``: ``hybrid`` with ``distrusted: trajectory``: where the audit trusts the
  map, the hybrid's row; where it does not, the environment is labelled by runs read
  along (``trajectory``), so the verdict at a fresh start is its real outcome, at the
  audit's frames plus the frames per label that ``--trajectory-starts`` runs of
  horizon + ``--extend`` s measure (uniform states of the paper box, as a dataset
  draws them; run only for an environment whose audit distrusts some map).
- ``rollout``: the real outcome itself (exact by construction: the same
  deterministic loop); costs every start's frames.

With ``--robust-spread D [D ...]``, each map is also solved robustly (`reach.robust`):
where the steering ranges over more than D deg across a node's neighbours, the solver
takes its worst value in that range; its rows are marked ``+RD`` and cost no renders.

With ``--refine L``, each grid is also refined adaptively ``L`` levels
(`reach.refine`): each level halves the spacing and renders new nodes only in the
cells where the BRT's boundary passes within ``--refine-band`` m or the steering
varies by more than ``--refine-variation`` deg across the cell; its row counts every
node rendered (``+rL`` in the grid column).

Each environment's map is then chosen among all of these by the hybrid audit's runs
(`reach.select_map`: fewest false-unsafe + ``--select-weight`` x false-safe verdicts
there, then fewest renders) and its verdicts on the check starts, which the choice
never saw, are printed as the ``selected`` row: a procedure, not a setting tuned to
the check.

Real runs are cached by content under ``--cache`` (a re-run is free, a killed one
resumes).

    python benchmarks/fidelity.py [--run-file scenarios/demo.yaml]
        [--day KMWH:9:clear] [--night KSFO:21:overcast] [--grids 11 5 11 21 9 21]
        [--periods-per-step 4 40] [--starts 100] [--audit 30] [--band 2.0] [--cache DIR]
        [--trajectory-starts 20] [--extend 8] [--stride 8]
        [--refine 2] [--refine-band 1.0] [--refine-variation 5] [--robust-spread 15 20]
        [--plot fidelity.png]
        [--theta-deg 28] [--py-max 250] [--exit-fails theta]

``--theta-deg`` and ``--py-max`` widen the solved box (the check starts stay in the
paper's box); ``--exit-fails`` makes leaving the box on those axes within the horizon
a failure in the solver instead of clamping (`reach.solve_brt`'s ``exit_fails``).
"""

import argparse
import copy
import dataclasses as dc
import functools
import time
from pathlib import Path

import numpy as np

from reachwatch.diagrams import CONTROL_PORT
from reachwatch.pipeline.evaluate_commands import parse_environment
from reachwatch.pipeline.spec import load_run_spec
from reachwatch.reach import compare_verdicts, select_map, solve_brt
from reachwatch.systems.files import cache_root
from reachwatch.taxi import (dynamics_for, on_runway_starts, paper_grid, refine_closed_loop,
                             steering_bounds, sweep_closed_loop)
from reachwatch.taxi.grid import AXES
from reachwatch.taxi.fidelity import real_outcomes, real_paths
from reachwatch.training.labels import (LabelSpec, audited_band, hybrid_rolls_out,
                                        trajectory_samples)


def interval(f, name):
    rate, lo, hi = f.rate(name)
    return f"{100 * rate:5.1f} [{100 * lo:4.1f}, {100 * hi:5.1f}]"


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--run-file", default="scenarios/demo.yaml", help="camera, controller, horizon")
    p.add_argument("--day", default="KMWH:9:clear", help='"" skips the day environment')
    p.add_argument("--night", default="KSFO:21:overcast")
    p.add_argument("--grids", type=int, nargs="+", default=[11, 5, 11, 21, 9, 21],
                   help="uniform grid shapes, three numbers each")
    p.add_argument("--periods-per-step", type=int, nargs="+", default=[4, 40],
                   help="semi_lagrangian solver steps to compare (control periods per step)")
    p.add_argument("--starts", type=int, default=100, help="real-loop check starts per environment")
    p.add_argument("--audit", type=int, default=30, help="hybrid audit states per environment")
    p.add_argument("--band", type=float, default=2.0, help="hybrid band (m)")
    p.add_argument("--band-factor", type=float, default=2.0,
                   help="hybrid: widen the band to this times the audit's largest error")
    p.add_argument("--max-band", type=float, default=6.0,
                   help="hybrid: distrust the map when the widened band exceeds this (m)")
    p.add_argument("--trajectory-starts", type=int, default=20,
                   help="runs that measure the frames per label read along runs (hyb>traj)")
    p.add_argument("--extend", type=float, default=8.0, help="hyb>traj: runs last the horizon + this (s)")
    p.add_argument("--stride", type=int, default=8, help="hyb>traj: read every stride-th tick")
    p.add_argument("--cache", default=None, help="sweep and rollout cache (default: the user cache)")
    p.add_argument("--refine", type=int, default=0, help="adaptive refinement levels of each grid")
    p.add_argument("--refine-band", type=float, default=1.0, help="refine where |V| boundary within (m)")
    p.add_argument("--refine-variation", type=float, default=None,
                   help="refine where the steering varies more than this across a cell (deg)")
    p.add_argument("--robust-spread", type=float, nargs="*", default=[],
                   help="also solve each map robustly where the steering ranges over more "
                   "than each of these deg across a node's neighbours (no renders)")
    p.add_argument("--select-weight", type=float, default=2.0,
                   help="a false-safe audit verdict weighs this many false-unsafe ones when "
                   "the audit picks each environment's map (reach.select_map)")
    p.add_argument("--plot", default=None, metavar="PNG",
                   help="also draw each map's agreement and false-safe share against its renders")
    p.add_argument("--theta-deg", type=float, default=28.0, help="solved box: |theta| up to (deg)")
    p.add_argument("--py-max", type=float, default=250.0, help="solved box: py up to (m)")
    p.add_argument("--exit-fails", nargs="*", default=[], choices=AXES,
                   help="axes where leaving the solved box is a failure (default: clamp)")
    args = p.parse_args()
    if len(args.grids) % 3:
        p.error("--grids takes three numbers per grid")
    spec = load_run_spec(args.run_file)
    cache = cache_root() if args.cache is None else Path(args.cache)
    curves = {}
    print(f"{'environment':22s} {'grid/pps':12s} {'source':8s} {'map renders':>11s} "
          f"{'frames/label':>12s} {'agreement % [95 % CI]':>22s} "
          f"{'false-safe %':>18s} {'false-unsafe %':>18s}")
    for text in [t for t in (args.day, args.night) if t]:      # "" skips one
        env = parse_environment(text)
        scenario = copy.deepcopy(spec.scenario)
        scenario.environment = env
        B = env.half_width
        base = paper_grid(B, (3, 3, 3))
        starts = on_runway_starts(base, args.starts, 1000, half_width=B)
        audit = on_runway_starts(base, args.audit, 2000, half_width=B)
        started = time.time()
        check = real_outcomes(scenario, starts, grid=base, duration=spec.horizon,
                              cache_dir=cache / "outcomes")
        audited = real_outcomes(scenario, audit, grid=base, duration=spec.horizon,
                                cache_dir=cache / "outcomes")
        seconds = time.time() - started
        real, frames = check.failed, check["ticks"]
        curve = curves.setdefault(env.name, [])
        first = len(curve)
        trajectory_cost = functools.cache(functools.partial(
            frames_per_label_read_along, scenario, base, spec.horizon, args, cache))
        variants = [(shape, pps) for shape in np.reshape(args.grids, (-1, 3))
                    for pps in args.periods_per_step]
        for shape, pps in variants:
            grid = paper_grid(B, tuple(int(n) for n in shape), theta_deg=args.theta_deg,
                              py_max=args.py_max)
            table = sweep_closed_loop(scenario, grid, cache_dir=cache / "sweeps", progress=True)

            def solve(table, pps=int(pps), spread=None):
                return solve_brt(table.grid, dynamics_for(scenario), table[CONTROL_PORT],
                                 horizon=spec.horizon, period=scenario.controller.period,
                                 periods_per_step=pps,
                                 control_bounds=steering_bounds(table, spread),
                                 exit_fails=[AXES.index(a) for a in args.exit_fails])
            variation = (None if args.refine_variation is None
                         else np.deg2rad(args.refine_variation))
            levels = refine_closed_loop(scenario, table, solve=solve, levels=args.refine,
                                        band=args.refine_band, variation=variation,
                                        cache_dir=cache / "sweeps")
            for level in levels:
                curve.append(score(env, level, pps, starts, audit, audited, real, frames, args,
                                   trajectory_cost))
                for spread in args.robust_spread:
                    robust = dc.replace(level, solution=solve(level.table, spread=spread))
                    curve.append(score(env, robust, pps, starts, audit, audited, real, frames,
                                       args, trajectory_cost, variant=f"+R{spread:g}"))
        candidates = curve[first:]
        kept = select_map([a for *_, a in candidates], costs=[r for _, r, *_ in candidates],
                          false_safe_weight=args.select_weight)
        name, rendered, f, a = candidates[kept]
        print(f"{env.name:22s} {name:12s} selected by the audit's {a.n} runs ({a.false_safe} "
              f"false-safe, {a.false_unsafe} false-unsafe there) among {len(candidates)} maps: "
              f"{rendered} renders, agreement {interval(f, 'agree')}, false-safe "
              f"{interval(f, 'false_safe')}, false-unsafe {interval(f, 'false_unsafe')} "
              f"on the {f.n} check starts")
        print(f"{'':22s} {len(starts)} check runs: {int(real.sum())} failures, "
              f"{100 * np.mean(check['left_box']):.0f} % left the paper box, "
              f"{int(frames.sum())} frames, {seconds:.0f} s with the audit "
              f"(0 s when cached), max |theta| {np.rad2deg(check['max_abs_theta'].max()):.0f} deg")
    if args.plot:
        plot_curves(curves, args.plot)
        print(f"wrote {args.plot}")


def plot_curves(curves, path):
    """Agreement and false-safe share of each map's BRT verdicts against the renders
    it cost, one panel per environment, with 95 % Wilson intervals."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, len(curves), figsize=(6 * len(curves), 4.5), squeeze=False)
    for ax, (env, rows) in zip(axes[0], curves.items()):
        renders = np.array([r for _, r, *_ in rows], float)
        for field, label, marker in (("agree", "agreement", "o"), ("false_safe", "false-safe", "x")):
            rates = np.array([f.rate(field) for _, _, f, _ in rows]) * 100
            ax.errorbar(renders, rates[:, 0], yerr=[rates[:, 0] - rates[:, 1],
                                                    rates[:, 2] - rates[:, 0]],
                        fmt=marker, capsize=3, label=label)
        for (name, r, f, _) in rows:
            ax.annotate(name, (r, 100 * f.rate("agree")[0]), fontsize=7, rotation=30,
                        textcoords="offset points", xytext=(3, 3))
        ax.set(xscale="log", xlabel="nodes rendered for the map", ylabel="% of check starts",
               title=f"{env}: BRT verdicts against the real loop")
        ax.grid(alpha=0.3)
        ax.legend(loc="center right")
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def frames_per_label_read_along(scenario, box_grid, horizon, args, cache):
    """Frames per label of ``trajectory`` labels in ``scenario``: ``--trajectory-starts``
    uniform states of ``box_grid``'s box (seed 3000), each run horizon + ``--extend``
    s, every ``--stride``-th tick inside the box labelled (`trajectory_samples`)."""
    lo, hi = box_grid.lo, box_grid.hi
    starts = lo + np.random.default_rng(3000).uniform(size=(args.trajectory_starts, 3)) * (hi - lo)
    labels = LabelSpec("trajectory", extend=args.extend, stride=args.stride)
    run_paths = lambda x: real_paths(scenario, x, grid=box_grid, horizon=horizon,  # noqa: E731
                                     extend=args.extend, stride=args.stride,
                                     cache_dir=cache / "outcomes").fields
    inside = lambda x: np.all((x >= lo) & (x <= hi), axis=1)                 # noqa: E731
    return trajectory_samples(starts, labels, run_paths, inside)[3]["frames_per_label"]


def score(env, level, pps, starts, audit, audited, real, frames, args, trajectory_cost,
          variant=""):
    """One table row per label source for one BRT map (a refinement ``level``;
    ``variant`` names a robust solve of it in the grid column; ``trajectory_cost()``
    the frames per label read along runs). Returns the map's name, its renders and its
    BRT verdicts' `Fidelity` on the check starts and on the audit's."""
    vf, grid = level.solution, level.table.grid
    values = vf.at(starts)
    audit_values = vf.at(audit)
    band, trusted, largest = audited_band(audit_values, audited.failed, band=args.band,
                                          band_factor=args.band_factor, max_band=args.max_band)
    rolled = hybrid_rolls_out(values, band if trusted else args.band, trusted)
    audit_cost = np.sum(audited["ticks"]) / 1000
    hybrid = (np.where(rolled, real, values <= 0), np.sum(frames[rolled]) / len(starts) + audit_cost)
    sources = {
        "brt": (values <= 0, 0.0),
        "hybrid": hybrid,
        "hyb>traj": hybrid if trusted else (real, audit_cost + trajectory_cost()),
        "rollout": (real, float(np.mean(frames)))}
    name = "x".join(map(str, grid.shape)) + f"/{pps}"
    if level.cells is not None:
        name = "x".join(map(str, grid.shape)) + f"r/{pps}"
    name += variant
    for source, (verdicts, cost) in sources.items():
        f = compare_verdicts(verdicts, real)
        if source == "brt":
            map_fidelity = f
        print(f"{env.name:22s} {name:12s} {source:8s} "
              f"{level.rendered:11d} {cost:12.1f} {interval(f, 'agree'):>22s} "
              f"{interval(f, 'false_safe'):>18s} {interval(f, 'false_unsafe'):>18s}")
    print(f"{'':22s} hybrid audit: largest error {largest:.2f} m, "
          f"{f'map trusted, band {band:.2f} m' if trusted else 'map NOT trusted'} "
          f"({int(np.sum(audited.failed & (audit_values > 0)))} false-safe of "
          f"{len(audit)}); rolled out {100 * rolled.mean():.0f} % of the check starts")
    return name, level.rendered, map_fidelity, compare_verdicts(audit_values <= 0, audited.failed)


if __name__ == "__main__":
    main()
