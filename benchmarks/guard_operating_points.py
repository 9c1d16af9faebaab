"""Which operating points of the guard keep the aircraft moving? For one guarded scenario
(an environment, a detector and its threshold), every combination of detector
threshold, fallback, k-of-n flag rule, resume acceleration and braking deceleration
(``brake`` fallbacks only) rolled out in the
guarded sweep's tables with the detector's variation between nodes (the score noise
of `reach.score_noise`, fitted on real runs of the controller alone, as the guard
stage does), from seeded random on-runway starts: the failures cut at the same
distance against the needless stops (starts the controller alone survives that end
stopped), beside the share of control ticks flagged: what a flag budget would fix
without labels (the threshold at which the guard flags that share of its ticks). It
ends with the best cut among the points within ``--max-needless`` and the fewest
needless stops among the points reaching ``--min-cut``: what to check in the real loop
next (``guard_fidelity.py``), or the measurement that no point of this detector gets
there.

Table rollouts only (no rendering beyond the sweep and the noise fit, both cached
under ``--cache``).

    python benchmarks/guard_operating_points.py --scenario S.yaml [--shape 21 11 21]
        [--scales 0.75 1 1.5 2.5 4] [--fallbacks brake,slow_down,slow_down+dead_reckoning]
        [--rules 1/1,3/5] [--resume 0,1] [--decelerations 1] [--starts 600] [--seed 7000]
        [--noise-seeds 1] [--flag-budgets 0.05,0.1]

With ``--flag-budgets`` each point's threshold is not a multiple of the scenario's but
the one at which that point flags the given share of its ticks, bisected in the same
tables with the score noise of the first noise seed (what ``guard.flag_budget`` does).

Braking harder lets a flag raised later still stop the aircraft in time: from 5 m/s,
1 m/s^2 takes 5 s and 12.5 m to stop, 3 m/s^2 1.7 s and 4.2 m. Whether a deceleration is
one the vehicle can hold is the user's call; the figures only say what it would buy.
"""

import copy
import itertools
import time

import numpy as np

from guard_common import guard_parser, guarded_setup
from reachwatch.pipeline.executors import open_executor
from reachwatch.pipeline.online_stages import fit_guard_noise
from reachwatch.reach.liveness import liveness_figures
from reachwatch.systems.switch import fallback_parts
from reachwatch.taxi import (UNGUARDED, TaxiApplication, taxi_fallback_rollouts, on_runway_starts,
                             sweep_guarded)


def rule(text):
    k, _, n = text.partition("/")
    return int(k), int(n)


def brake(deceleration):
    """A point's braking deceleration as printed: '-' for a fallback that does not brake."""
    return "-" if deceleration is None else f"{deceleration:g}"


def braking(deceleration):
    """The same in a summary line: nothing for a fallback that does not brake."""
    return "" if deceleration is None else f", brake {deceleration:g} m/s^2"


def main():
    p = guard_parser(__doc__, fallbacks="brake,slow_down,slow_down+dead_reckoning",
                     starts=600, seed=7000, noise_seeds=1)
    p.add_argument("--scales", type=float, nargs="+", default=[0.75, 1.0, 1.5, 2.5, 4.0],
                   help="thresholds as multiples of the scenario's (capped at 0.99)")
    p.add_argument("--rules", default="1/1,3/5", help="k-of-n flag rules, k/n")
    p.add_argument("--resume", default="0,1", help="resume accelerations, m/s^2")
    p.add_argument("--decelerations", default=None,
                   help="braking decelerations, m/s^2 (default: the scenario's)")
    p.add_argument("--flag-budgets", default=None,
                   help="instead of --scales: shares of ticks flagged, each point's threshold "
                        "bisected to flag that share (comma-separated, each in (0, 1))")
    p.add_argument("--max-needless", type=float, default=0.10)
    p.add_argument("--min-cut", type=float, default=0.50)
    args = p.parse_args()
    scenario, grid, cache, fallbacks = guarded_setup(p, args)
    try:
        rules = [rule(r) for r in args.rules.split(",") if r]
        resumes = [float(r) for r in args.resume.split(",") if r]
        decelerations = ([scenario.monitor.brake_deceleration] if args.decelerations is None
                         else [float(d) for d in args.decelerations.split(",") if d])
    except ValueError:
        p.error(f"--rules is k/n,k/n,..., --resume and --decelerations lists of numbers; got "
                f"'{args.rules}', '{args.resume}', '{args.decelerations}'")
    try:
        budgets = ([float(b) for b in args.flag_budgets.split(",") if b]
                   if args.flag_budgets is not None else None)
    except ValueError:
        budgets = [float("nan")]
    if budgets is not None and not (budgets and all(0 < b < 1 for b in budgets)):
        p.error(f"--flag-budgets is a list of shares in (0, 1), got '{args.flag_budgets}'")
    if not decelerations or min(decelerations) <= 0:
        p.error(f"--decelerations must be numbers > 0 m/s^2, got '{args.decelerations}'")
    horizon, B = float(scenario.duration), scenario.environment.half_width
    started = time.perf_counter()
    with open_executor(args.executor) as executor:
        tables = sweep_guarded(scenario, grid, cache_dir=cache / "sweeps", executor=executor)
        noise, fit = fit_guard_noise(scenario, grid, tables, noise_starts=args.calibration_starts,
                                     noise_seed=args.calibration_seed, horizon=horizon,
                                     cache_dir=cache / "outcomes", executor=executor)
    if noise is None:
        raise SystemExit(f"the score-noise fit failed: {fit['error']}")
    starts = on_runway_starts(grid, args.starts, args.seed, half_width=B)
    print(f"guard operating points: {scenario.environment.name}, grid {args.shape}, "
          f"{args.starts} starts (seed {args.seed}), horizon {horizon:g} s, same distance up "
          f"to {args.mission_limit:g} x the horizon; score noise mean {noise.mean:+.3f}, sigma "
          f"{noise.sigma:.3f}, length {noise.length:.2f} m from {fit['runs']} real runs; "
          f"{args.noise_seeds} noise seed(s)")
    print(f"{'threshold':>9s}  {'fallback':26s} {'rule':>4s} {'resume':>6s} {'brake':>5s}  "
          f"{'cut %':>6s} "
          f"{'needless stops %':>16s} {'ended stopped %':>15s} {'flagged ticks %':>15s}")
    alone, rows = None, []
    points = [(scale, fallback, rule_, resume, deceleration)
              for scale, fallback, rule_, resume in itertools.product(budgets or args.scales,
                                                                      fallbacks, rules, resumes)
              for deceleration in (decelerations if fallback_parts(fallback)[0] == "brake"
                                   else [None])]
    for scale, fallback, (k, n), resume, deceleration in points:
        guarded = copy.deepcopy(scenario)
        if deceleration is not None:
            guarded.monitor.brake_deceleration = deceleration
        guarded.monitor.flags_needed, guarded.monitor.flag_window = k, n
        guarded.monitor.resume_acceleration = resume
        guarded.monitor.validate()
        if budgets:                       # "scale" is the point's flag budget
            try:
                threshold = TaxiApplication().flag_budget_threshold(
                    guarded, grid, tables, horizon, fallback, scale, starts=starts,
                    mission_limit=args.mission_limit, score_noise=noise,
                    seed=args.calibration_seed, alone=alone)["threshold"]
            except ValueError as e:
                print(f"flag budget {scale:g}, {fallback} {k}/{n}: {e}")
                continue
        else:
            threshold = min(0.99, scale * scenario.monitor.threshold)
        figures = []
        for seed in range(args.noise_seeds):
            runs = taxi_fallback_rollouts(guarded, grid, tables, horizon, [fallback], starts=starts,
                                     threshold=threshold, mission_limit=args.mission_limit,
                                     score_noise=noise, seed=args.calibration_seed + seed,
                                     alone=alone)
            alone = runs[UNGUARDED]
            figures.append(liveness_figures(runs[UNGUARDED], runs[fallback]))
        cut = float(np.mean([f["same_distance_failure_cut"] for f in figures]))
        needless = float(np.mean([f["needless_stops"]["rate"] for f in figures]))
        stopped = float(np.mean([f["ended_stopped"]["rate"] for f in figures]))
        flagged = float(np.mean([f["flagged_ticks"] or 0.0 for f in figures]))
        rows.append((threshold, fallback, f"{k}/{n}", resume, cut, needless, stopped,
                     deceleration))
        print(f"{threshold:9.3f}  {fallback:26s} {k}/{n:<2d} {resume:6g} "
              f"{brake(deceleration):>5s}  "
              f"{100 * cut:6.1f} "
              f"{100 * needless:16.1f} {100 * stopped:15.1f} {100 * flagged:15.1f}", flush=True)
    print(f"controller alone fails at the same distance from "
          f"{100 * np.mean(alone.failed_same_distance):.1f} % of the starts "
          f"({time.perf_counter() - started:.0f} s)")
    within = [r for r in rows if r[5] <= args.max_needless]
    reaching = [r for r in rows if r[4] >= args.min_cut]
    if within:
        best = max(within, key=lambda r: r[4])
        print(f"best cut with needless stops <= {100 * args.max_needless:g} %: {100 * best[4]:.1f} % "
              f"({best[1]}, threshold {best[0]:.3f}, rule {best[2]}, resume {best[3]:g}"
              f"{braking(best[7])}; needless {100 * best[5]:.1f} %)")
    if reaching:
        best = min(reaching, key=lambda r: r[5])
        print(f"fewest needless stops with a cut >= {100 * args.min_cut:g} %: "
              f"{100 * best[5]:.1f} % ({best[1]}, threshold {best[0]:.3f}, rule {best[2]}, "
              f"resume {best[3]:g}{braking(best[7])}; cut {100 * best[4]:.1f} %)")
    met = [r for r in within if r[4] >= args.min_cut]
    print(f"points meeting both (cut >= {100 * args.min_cut:g} %, needless <= "
          f"{100 * args.max_needless:g} %): {len(met)} of {len(rows)}")


if __name__ == "__main__":
    main()
