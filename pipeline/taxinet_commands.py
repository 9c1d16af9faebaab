"""``reachwatch taxinet train`` and ``reachwatch taxinet evaluate``."""

import dataclasses as dc
from pathlib import Path

from .console import bar, log
from .overlays import add_overlay_arguments
from .commands import count, output_file, positive_int, scenario_from_args, seed_number

#: ``TaxiNetTrainConfig``'s samples and epochs, here so that the parser needs no torch
#: (a test keeps them the same).
TRAIN_SAMPLES, TRAIN_EPOCHS = 8000, 200


def add_parsers(sub):
    taxinet = sub.add_parser("taxinet", help="train or evaluate the TaxiNet controller")
    tsub = taxinet.add_subparsers(dest="taxinet_command", required=True, metavar="ACTION")
    train = tsub.add_parser("train", help="render the nominal set (KMWH 9 h clear) and "
                            "train TaxiNet; reproduces the shipped reference checkpoint "
                            "with the defaults")
    train.add_argument("--out", required=True, help="checkpoint path to write (never the "
                       "shipped reference checkpoint)")
    train.add_argument("--samples", type=positive_int, default=TRAIN_SAMPLES,
                       help=f"rendered images, a tenth kept for validation (default: "
                       f"{TRAIN_SAMPLES})")
    train.add_argument("--epochs", type=positive_int, default=TRAIN_EPOCHS,
                       help=f"training epochs (default: {TRAIN_EPOCHS})")
    train.add_argument("--seed", type=seed_number, default=0,
                       help="seed of the sampled states and of the training")
    train.add_argument("--arch", choices=["tiny", "cnn"], default="tiny",
                       help="tiny: the reference TinyTaxiNet (default); cnn: a small CNN on "
                       "a resized crop")
    train.set_defaults(func=train_command)

    evaluate = tsub.add_parser("evaluate", help="estimation error and closed-loop failure "
                               "rate on every catalog environment")
    evaluate.add_argument("--checkpoint", default=None,
                          help="TaxiNet checkpoint (default: the shipped reference TaxiNet)")
    evaluate.add_argument("--scenario", help="scenario YAML for camera/controller settings")
    add_overlay_arguments(evaluate)
    evaluate.add_argument("--samples", type=positive_int, default=200,
                          help="random states per environment for the estimation error (default: 200)")
    evaluate.add_argument("--starts", type=count, default=100,
                          help="closed-loop starts per environment (0 skips; default: 100)")
    evaluate.add_argument("--runways", nargs="+", default=None,
                          help="catalog runways (default: all of them)")
    evaluate.add_argument("--hours", nargs="+", type=float, default=[9.0, 17.0, 21.0],
                          help="local hours of day (default: 9 17 21), each under every sky")
    evaluate.add_argument("--seed", type=seed_number, default=0,
                          help="seed of the sampled states and the closed-loop starts")
    evaluate.add_argument("--out", help="also write the table here (Markdown)")
    evaluate.set_defaults(func=evaluate_command)


def train_command(args):
    from reachwatch.diagrams import REFERENCE_TAXINET
    from reachwatch.taxi.taxinet_train import TaxiNetTrainConfig, train_taxinet
    out = Path(args.out)
    if out.resolve() == REFERENCE_TAXINET.resolve():
        raise ValueError(f"--out {args.out} is the shipped reference TaxiNet, which the "
                         f"defaults reproduce and the tests compare with; write elsewhere")
    if out.is_dir():
        raise ValueError(f"--out {args.out} is a folder; name the checkpoint file to write")
    output_file(out)                        # its folder can be written, before the training
    config = TaxiNetTrainConfig(samples=args.samples, epochs=args.epochs, seed=args.seed)
    if args.arch == "cnn":
        config.model.arch = "cnn"
        config.preprocess = dc.replace(config.preprocess, kind="resize", crop=[0, 0.3, 1, 1],
                                       height=48, width=96)
    metadata = train_taxinet(config, args.out, progress=bar)
    log.info(f"wrote {args.out}")
    log.info(f"validation (nominal condition): {metadata['validation']}")


def evaluate_command(args):
    from reachwatch.diagrams import REFERENCE_TAXINET, load_taxinet
    from reachwatch.systems import RUNWAYS, SKIES, Environment
    from reachwatch.systems.files import atomic_write_bytes
    from reachwatch.taxi.taxinet_eval import evaluate_taxinet, format_reports
    base = scenario_from_args(args)
    runways = args.runways or list(RUNWAYS)
    checkpoint = args.checkpoint or str(REFERENCE_TAXINET)
    environments = [Environment(r, h, s) for r in runways for h in args.hours for s in SKIES]
    for env in environments:                # a bad --runways or --hours fails before any work
        try:
            env.validate()
        except ValueError as e:
            raise ValueError(f"--runways / --hours: {e}") from None
    load_taxinet(checkpoint)                # a missing or wrong --checkpoint, before any render
    if args.out:
        output_file(args.out)
    reports = evaluate_taxinet(base, environments, checkpoint=checkpoint,
                               samples=args.samples, starts=args.starts, seed=args.seed,
                               progress=lambda it: bar(it, leave=False, desc="rollouts"))
    table = format_reports(reports)
    log.info(table)
    if args.out:
        atomic_write_bytes(args.out, (table + "\n").encode())
