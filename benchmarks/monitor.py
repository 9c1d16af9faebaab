"""The monitor over the image history on environments it has never seen: every
variant trained on recorded real-loop runs of a random environment family's training
environments, calibrated on others of the family (Platt scaling, then a conformal
threshold bounding the expected miss rate on a new environment), judged on held-out
environments of the family (and, with ``--nights``, on the paper's held-out night
environments, outside the family's guarantee): misses, needless flags, AUROC of
"fails within 4 s", ECE, Brier, beside the oracle monitor and the controller's
prediction error; with ``--guarded-runs`` also in the guarded real loop with braking.
The study is `reachwatch.pipeline.monitor_study` (``monitor: {kind: history}`` in a
run file runs the same); this prints its tables.

    python benchmarks/monitor.py --seed 4 --train 1 --calibrate 1 --held-out 1 --alpha 0.5 \\
        --runs 6 --duration 2 --within 1 --size 16 24 --epochs 1 --head-epochs 2  # smoke, ~1 min
"""

import argparse
import dataclasses as dc
import time
from pathlib import Path

from reachwatch.diagrams import load_scenario
from reachwatch.pipeline.executor_option import add_executor_argument
from reachwatch.pipeline.executors import make_executor
from reachwatch.pipeline.memory import return_large_blocks
from reachwatch.pipeline.monitor_sections import markdown_tables
from reachwatch.pipeline.monitor_study import MonitorStudySpec, run_monitor_study
from reachwatch.systems import INPUT_NORMS, Environment, RandomEnvironments
from reachwatch.training.history_train import LR_SCHEDULES


def _rule(parser, text):
    k, _, n = text.partition("/")
    if not (k.isdigit() and n.isdigit()):
        parser.error(f"--flag-rules takes K/N pairs such as 2/3, got {text!r}")
    return [int(k), int(n)]


def main():
    defaults = MonitorStudySpec()
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenario", default=None, help="scenario file (default: the built-in "
                   "one: the reference TaxiNet, 200x360 camera)")
    p.add_argument("--seed", type=int, default=defaults.family.seed,
                   help="the random environment family")
    for name in ("train", "calibrate", "held_out", "runs", "held_out_runs", "calibration_runs",
                 "epochs", "head_epochs", "guarded_runs", "ensemble"):
        p.add_argument(f"--{name.replace('_', '-')}", type=int, default=getattr(defaults, name))
    for name in ("duration", "within", "alpha"):
        p.add_argument(f"--{name}", type=float, default=getattr(defaults, name))
    p.add_argument("--given-failures", action="store_true",
                   help="fix the threshold on the calibration environments with a warnable "
                        "failing run alone (monitor.given_failures)")
    p.add_argument("--brake", type=float, default=defaults.brake_deceleration,
                   help="braking m/s^2: the fallback")
    p.add_argument("--size", type=int, nargs=2, default=[defaults.height, defaults.width],
                   metavar=("HEIGHT", "WIDTH"), help="frame size the monitor reads")
    p.add_argument("--flag-rules", nargs="+", default=["1/1"], metavar="K/N",
                   help="k-of-n flag rules (flag when K of the last N ticks reach the "
                        "threshold); one, unless --keep choose: then each variant keeps the "
                        "one with the fewest needless flags on the calibration environments")
    p.add_argument("--keep", default=None, metavar="VARIANT",
                   help="the kept monitor: a variant's name (default: the first, the single "
                        "frame), fixed before calibration; 'choose': the variant and rule "
                        "with the fewest needless flags on the calibration environments")
    p.add_argument("--train-seed", type=int, default=defaults.seed,
                   help="the monitors' training seed (weights, batch order, jitter)")
    p.add_argument("--lr-schedule", choices=LR_SCHEDULES, default=defaults.lr_schedule,
                   help="the monitors' learning rate: constant, or cosine (decays to zero "
                        "over each training stage)")
    p.add_argument("--no-augment", action="store_true",
                   help="train the per-frame encoder without colour jitter")
    p.add_argument("--input-norm", choices=INPUT_NORMS, default=defaults.input_norm,
                   help="how the encoder normalises each frame: fixed (the detector's "
                        "constant shift and scale) or per_frame (also by the frame's own mean "
                        "and std)")
    p.add_argument("--pool", type=int, nargs=2, default=defaults.pool, metavar=("ROWS", "COLS"),
                   help="the grid the encoder's last feature map is averaged over (1 1: whole)")
    p.add_argument("--state-targets", type=int, nargs="*", default=None, metavar="I",
                   help="state components the encoder also learns to estimate from the frame "
                        "(default: the application's estimated_state, the taxi's 0 2: "
                        "cross-track error and heading; given with none: off)")
    p.add_argument("--state-weight", type=float, default=defaults.state_weight,
                   help="the weight of that estimate's squared error beside the failure loss")
    p.add_argument("--weight-average", type=float, default=defaults.weight_average,
                   help="the share of each training stage's last epochs whose weights are "
                        "averaged (stochastic weight averaging; 0: off)")
    p.add_argument("--nights", action="store_true",
                   help="also judge on the paper's held-out 21 h environments (KSFO, KEWR)")
    p.add_argument("--detector", default=None, metavar="CHECKPOINT",
                   help="a single-image detector's checkpoint (e.g. a run's "
                        "detectors/detector_brt_*.pt) judged beside the variants on the "
                        "same runs, with a threshold fixed the same way, and in the guarded "
                        "loop")
    add_executor_argument(p)
    p.add_argument("--cache", default="/tmp/reachwatch-monitor-cache")
    p.add_argument("--out", default="/tmp/reachwatch-monitor")
    args = p.parse_args()
    return_large_blocks()         # as the command line: glibc gives freed frames back
    spec = dc.replace(
        defaults, kind="history", family=RandomEnvironments(seed=args.seed), train=args.train,
        calibrate=args.calibrate, held_out=args.held_out, runs=args.runs,
        held_out_runs=args.held_out_runs, calibration_runs=args.calibration_runs,
        duration=args.duration, within=args.within,
        alpha=args.alpha, given_failures=args.given_failures, brake_deceleration=args.brake,
        height=args.size[0], width=args.size[1],
        epochs=args.epochs, head_epochs=args.head_epochs, guarded_runs=args.guarded_runs,
        flag_rules=[_rule(p, r) for r in args.flag_rules], augment=not args.no_augment,
        input_norm=args.input_norm, seed=args.train_seed, lr_schedule=args.lr_schedule,
        ensemble=args.ensemble, keep=args.keep,
        weight_average=args.weight_average, pool=list(args.pool), state_weight=args.state_weight,
        state_targets=None if args.state_targets is None else list(args.state_targets),
        also_held_out=[Environment(r, 21.0, s) for r in ("KSFO", "KEWR")
                       for s in ("clear", "overcast")] if args.nights else [])
    if len(args.flag_rules) > 1 and args.keep != "choose":
        p.error(f"--flag-rules lists {len(args.flag_rules)} rules, and the kept monitor is "
                f"fixed in advance: give one rule, or add --keep choose to choose the variant "
                f"and rule on the calibration environments")
    try:
        spec.validate()
    except ValueError as e:
        p.error(str(e))
    if args.detector and not Path(args.detector).is_file():
        p.error(f"--detector: file not found: {args.detector}")
    scenario = load_scenario(args.scenario) if args.scenario else load_scenario(data="")
    started = time.time()
    try:
        executor, close = make_executor(args.executor)
    except ValueError as e:
        p.error(str(e))
    try:
        result = run_monitor_study(spec, scenario, args.out, cache_dir=args.cache,
                                   executor=executor,
                                   detector=Path(args.detector).resolve() if args.detector
                                   else None)
    except BaseException:
        close(abort=True)
        raise
    close()
    print()
    print(markdown_tables(result))
    print(f"wrote {args.out}/monitor.json in {time.time() - started:.0f} s")


if __name__ == "__main__":
    main()
