"""``reachwatch taxinet ...`` and ``reachwatch simulate``."""

import dataclasses as dc
import io
from pathlib import Path

import numpy as np

from reachwatch.diagrams import (REFERENCE_TAXINET, initial_state_vector,
                                 make_closed_loop_diagram, simulate)
from reachwatch.diagrams.plots import plot_runway_top_view
from reachwatch.taxi import simulate_guarded
from reachwatch.systems import SKIES, RUNWAYS, Environment
from reachwatch.systems.files import atomic_write_bytes
from reachwatch.training.taxinet_eval import evaluate_taxinet, format_reports
from reachwatch.training.taxinet_train import TaxiNetTrainConfig, train_taxinet

from .console import bar, log
from .commands import count, positive_int, scenario_from_args


def add_parsers(sub):
    taxinet = sub.add_parser("taxinet", help="train or evaluate the TaxiNet controller")
    tsub = taxinet.add_subparsers(dest="taxinet_command", required=True, metavar="ACTION")
    train = tsub.add_parser("train", help="render the nominal set (KMWH 9 h clear) and "
                            "train TaxiNet; reproduces the shipped reference checkpoint "
                            "with the defaults")
    train.add_argument("--out", default=str(REFERENCE_TAXINET), help="checkpoint path")
    train.add_argument("--samples", type=positive_int, default=TaxiNetTrainConfig.samples)
    train.add_argument("--epochs", type=positive_int, default=TaxiNetTrainConfig.epochs)
    train.add_argument("--seed", type=int, default=0)
    train.add_argument("--arch", choices=["tiny", "cnn"], default="tiny")
    train.set_defaults(func=train_command)

    evaluate = tsub.add_parser("evaluate", help="estimation error and closed-loop failure "
                               "rate on every catalog environment")
    evaluate.add_argument("--checkpoint", default=str(REFERENCE_TAXINET))
    evaluate.add_argument("--scenario", help="scenario YAML for camera/controller settings")
    evaluate.add_argument("--samples", type=positive_int, default=200,
                          help="random states per environment for the estimation error")
    evaluate.add_argument("--starts", type=count, default=100,
                          help="closed-loop starts per environment (0 skips)")
    evaluate.add_argument("--runways", nargs="+", default=list(RUNWAYS))
    evaluate.add_argument("--hours", nargs="+", type=float, default=[9.0, 17.0, 21.0])
    evaluate.add_argument("--seed", type=int, default=0)
    evaluate.add_argument("--out", help="also write the table here (Markdown)")
    evaluate.set_defaults(func=evaluate_command)

    sim = sub.add_parser("simulate", help="run the closed loop from the scenario's start "
                         "state; write the trajectory (CSV, NPZ) and a top-view plot")
    sim.add_argument("--scenario", help="scenario YAML (default: built-in defaults)")
    sim.add_argument("--out", required=True, help="output folder")
    sim.add_argument("--pipeline", choices=["nominal", "guarded"], default="nominal",
                     help="guarded: also run the detector + fallback switch (needs "
                          "pipeline.detector in the scenario); writes a Fig.-6 plot and a "
                          "Meshcat replay (.html)")
    sim.add_argument("--no-meshcat", action="store_true", help="skip the HTML replay")
    sim.set_defaults(func=simulate_command)


def train_command(args):
    config = TaxiNetTrainConfig(samples=args.samples, epochs=args.epochs, seed=args.seed)
    if args.arch == "cnn":
        config.model.arch = "cnn"
        config.preprocess = dc.replace(config.preprocess, kind="resize", crop=[0, 0.3, 1, 1],
                                       height=48, width=96)
    metadata = train_taxinet(config, args.out, progress=bar)
    log.info(f"wrote {args.out}")
    log.info(f"validation (nominal condition): {metadata['validation']}")


def evaluate_command(args):
    base = scenario_from_args(args)
    environments = [Environment(r, h, s) for r in args.runways for h in args.hours for s in SKIES]
    reports = evaluate_taxinet(base, environments, checkpoint=args.checkpoint,
                               samples=args.samples, starts=args.starts, seed=args.seed,
                               progress=lambda it: bar(it, leave=False, desc="rollouts"))
    table = format_reports(reports)
    log.info(table)
    if args.out:
        atomic_write_bytes(args.out, (table + "\n").encode())


def simulate_command(args):
    scenario = scenario_from_args(args)
    out = Path(args.out)
    if args.pipeline == "guarded":
        nominal, guarded, paths = simulate_guarded(scenario, out,
                                                   meshcat_html=not args.no_meshcat)
        log.info(f"TaxiNet alone {'failed' if nominal.failed else 'stayed on the runway'}; "
              f"guarded {'failed' if guarded.failed else 'stayed on the runway'} "
              f"(min speed {guarded.speed.min():.2f} m/s, {int(guarded.anomaly.sum())} "
              f"flagged ticks); wrote {', '.join(map(str, paths))}")
        return
    diagram = make_closed_loop_diagram(scenario)
    trajectory = simulate(diagram, initial_state=initial_state_vector(scenario.initial_state),
                          duration=scenario.duration,
                          half_width=scenario.environment.half_width)
    name = scenario.environment.name
    columns = np.column_stack([trajectory.time, trajectory.state[:, :2],
                               np.rad2deg(trajectory.state[:, 2]), trajectory.estimate])
    text = io.StringIO()
    np.savetxt(text, columns, delimiter=",", fmt="%.6f",
               header="t_s,px_m,py_m,theta_deg,px_hat_m,theta_hat_deg", comments="")
    atomic_write_bytes(out / f"{name}_trajectory.csv", text.getvalue().encode())
    buffer = io.BytesIO()
    np.savez(buffer, time=trajectory.time, state=trajectory.state,
             estimate=trajectory.estimate, half_width=trajectory.half_width,
             failed=trajectory.failed, failure_time=trajectory.failure_time)
    atomic_write_bytes(out / f"{name}_trajectory.npz", buffer.getvalue())
    plot = plot_runway_top_view([(trajectory, "TaxiNet")],
                                half_width=trajectory.half_width,
                                path=out / f"{name}_trajectory.png",
                                title=f"{name}: {'FAILED at %.2f s' % trajectory.failure_time if trajectory.failed else 'stayed on the runway'}")
    log.info(f"{'failed' if trajectory.failed else 'stayed on the runway'}; wrote "
          f"{out / (name + '_trajectory.csv')}, .npz and {plot}")
