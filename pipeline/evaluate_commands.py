"""``reachwatch evaluate``: the paper's Table 2 with baselines (``reachwatch run`` up
to its evaluate stage, configured from the command line)."""

import argparse
import collections.abc
import dataclasses as dc
import importlib

from .console import log
from .executor_option import add_executor_argument
from .overlays import add_overlay_arguments
from .commands import (RunFileDefault, count, grid_nodes, positive_int, scenario_from_args,
                       seed_number, solved_py, solved_theta)


class LibraryNames(collections.abc.Sequence):
    """The names ``module.attribute`` holds (a registry's live names), read when first
    asked for, so that building the parser (``--help``) imports none of the library."""

    def __init__(self, module: str, attribute: str):
        self._where = (module, attribute)

    def _names(self) -> tuple:
        module, attribute = self._where
        return tuple(getattr(importlib.import_module(module), attribute))

    def __getitem__(self, index):
        return self._names()[index]

    def __len__(self):
        return len(self._names())

    def __contains__(self, name):
        return name in self._names()

    def __repr__(self):
        return repr(self._names())


#: The registered label sources (`reachwatch.training.labels.LABEL_SOURCES`).
LABEL_SOURCES = LibraryNames("reachwatch.training.labels", "LABEL_SOURCES")


def label_source_name(text: str) -> str:
    """``--labels``: a registered label source (read only when one is given, not by
    ``--help``, whose choices argparse would list)."""
    if text not in LABEL_SOURCES:
        raise argparse.ArgumentTypeError(f"invalid label source '{text}' (choose from "
                                         f"{', '.join(LABEL_SOURCES)})")
    return text


#: What the parser shows of the library, here so that building it needs no torch (a
#: test keeps it the same as ``reachwatch.training``'s): the ``--distrusted`` choices.
DISTRUSTED_CHOICES = ("rollout", "trajectory")


def parse_environment(text: str, flag: str = "environment"):
    """``RUNWAY:HOUR:SKY`` (e.g. ``KSFO:17:overcast``) -> a validated `Environment`; a
    ValueError in one line naming ``flag`` (the option that gave it) and ``text``."""
    from reachwatch.systems import Environment
    parts = text.split(":")
    if len(parts) != 3:
        raise ValueError(f"{flag} '{text}' must read RUNWAY:HOUR:SKY, e.g. KMWH:9:clear")
    try:
        hour = float(parts[1])
    except ValueError:
        raise ValueError(f"{flag} '{text}': hour '{parts[1]}' is not a number") from None
    try:
        return Environment(parts[0], hour, parts[2]).validate()
    except ValueError as e:
        raise ValueError(f"{flag} '{text}': {e}") from None


def _names(envs):
    return [f"{e.runway}:{e.hour:g}:{e.sky}" for e in envs]


def add_parsers(sub):
    p = sub.add_parser("evaluate", help="BRTs, BRT-labelled datasets, the anomaly detector, "
                       "baselines and the paper's Table 2 on held-out environments")
    p.add_argument("--scenario", help="scenario YAML for camera/controller settings")
    add_overlay_arguments(p)
    p.add_argument("--train", nargs="+", default=None,
                   help="training environments RUNWAY:HOUR:SKY (default: "
                   "training_environments(), the paper's 12)")
    p.add_argument("--test", nargs="+", default=None,
                   help="held-out environments (default: test_environments(), the paper's "
                   "18 held-out environments)")
    # every default below is the run file's (`RunFileDefault`), as --help says
    p.add_argument("--shape", type=grid_nodes, nargs=3, default=RunFileDefault("grid"),
                   help="BRT grid (default: %(default)s)")
    p.add_argument("--samples", type=positive_int, default=RunFileDefault("dataset.samples"),
                   help="images per environment (default: %(default)s)")
    p.add_argument("--arch", choices=["small_cnn", "efficientnet_b0"],
                   default=RunFileDefault("detector.detector.arch"),
                   help="anomaly detector architecture (default: %(default)s)")
    p.add_argument("--input-size", type=positive_int, nargs=2, metavar=("H", "W"),
                   default=RunFileDefault(("dataset.height", "dataset.width")),
                   help="the detector's input image size in pixels (default: %(default)s)")
    p.add_argument("--pretrained", default=RunFileDefault("detector.pretrained_path"),
                   help="local EfficientNet-B0 ImageNet state_dict file (never downloaded; "
                   "default: %(default)s)")
    p.add_argument("--epochs", type=positive_int, default=RunFileDefault("detector.epochs"),
                   help="detector training epochs (default: %(default)s)")
    p.add_argument("--threshold", type=float, default=RunFileDefault("detector.threshold"),
                   help="decision threshold when --target-recall is 0 (default: %(default)s)")
    p.add_argument("--target-recall", type=float,
                   default=RunFileDefault("detector.target_recall"),
                   help="operate at the highest threshold reaching this recall on the "
                        "training validation split (0: use --threshold; default: %(default)s)")
    p.add_argument("--ensemble", type=count, default=RunFileDefault("ensemble.seeds", len),
                   help="TaxiNets in the ensemble baseline (default: as many as %(default)s)")
    p.add_argument("--seed", type=seed_number,
                   default=RunFileDefault(("dataset.seed", "detector.seed"), _one_seed),
                   help="seed of the datasets' samples and of the detector's training "
                   "(default: %(default)s)")
    p.add_argument("--labels", type=label_source_name, metavar="SOURCE",
                   default=RunFileDefault("dataset.labels.source"),
                   help="label source: brt (the BRT), rollout (the real loop from every "
                   "state), hybrid (rollouts where the BRT is not trusted), trajectory (the "
                   "real loop's runs and the states they pass through), or another "
                   "registered one (see docs/concepts.md#label-sources; default: "
                   "%(default)s)")
    p.add_argument("--distrusted", choices=DISTRUSTED_CHOICES,
                   default=RunFileDefault("dataset.labels.distrusted"),
                   help="with --labels hybrid: where the audit distrusts the map, roll out "
                   "every sample it calls safe, or label by runs read along (trajectory; "
                   "default: %(default)s)")
    p.add_argument("--check-starts", type=count, default=RunFileDefault("fidelity.starts"),
                   help="real-loop runs per environment checking the BRT and the labels "
                   "(0: no check; default: %(default)s)")
    p.add_argument("--solved-theta-deg", type=solved_theta, metavar="DEG",
                   default=RunFileDefault("solved_theta_deg"),
                   help="sweep and solve over |theta| <= DEG (the paper's box: 28; default: "
                   "%(default)s)")
    p.add_argument("--solved-py-max", type=solved_py, metavar="M", default=PAPER_PY_MAX,
                   help="sweep and solve over py <= M: the paper's box ends at 250 m, and a "
                   "check start near it runs past within the horizon (default: %(default)s, "
                   "room for the default 8 s at 5 m/s)")
    p.add_argument("--max-box-exits", type=float,
                   default=RunFileDefault("fidelity.max_box_exits"),
                   help="refuse BRT labels where more than this share of the checked runs "
                   "leave the solved box (default: %(default)s)")
    add_executor_argument(p, default="inline")
    p.add_argument("--out", required=True, help="output folder (reused: finished work is skipped)")
    p.set_defaults(func=evaluate_command)


#: ``--solved-py-max``'s default: the paper's box end (250 m) and the 40 m the default
#: horizon (8 s) covers at the default 5 m/s, as the paper's run file has it. The run
#: file's own default (250) leaves the real-loop check no room, and the check would refuse
#: the command's defaults.
PAPER_PY_MAX = 290.0


def _one_seed(seeds):
    """The run file's dataset and detector seeds, which ``--seed`` sets both of."""
    if len(set(seeds)) != 1:
        raise ValueError(f"--seed sets dataset.seed and detector.seed, whose defaults "
                         f"differ ({seeds}); give --seed")
    return seeds[0]


def target_text(rows, groups, config) -> str:
    """The report's Table 2 against the target (`target_section`) as Markdown for the
    console; empty when ``rows`` hold no detector rows."""
    from .detector_sections import target_section
    from .report import Page
    page = Page("target")
    target_section(page, rows, groups, config)
    return "\n".join(page.md[1:])          # after the page's title


def evaluate_spec(args):
    """The `RunSpec` that ``reachwatch evaluate``'s arguments describe."""
    from reachwatch.systems import DetectorConfig, test_environments, training_environments
    from reachwatch.training.dataset import DatasetSpec
    from reachwatch.training.detector_train import DetectorTrainConfig
    from reachwatch.training.labels import LabelSpec

    from .spec import EnsembleSpec, FidelitySpec, IncrementalConfig, RunSpec
    height, width = args.input_size
    detector = DetectorConfig(arch=args.arch, height=height, width=width)
    spec = RunSpec(
        name="evaluate", scenario=scenario_from_args(args, controller=True),
        train=[parse_environment(t, "--train")
               for t in args.train or _names(training_environments())],
        test=[parse_environment(t, "--test")
              for t in args.test or _names(test_environments())],
        grid=list(args.shape), solved_theta_deg=args.solved_theta_deg,
        solved_py_max=args.solved_py_max,
        dataset=DatasetSpec(samples=args.samples, seed=args.seed, height=height, width=width,
                            labels=LabelSpec(source=args.labels,
                                                distrusted=args.distrusted)),
        fidelity=FidelitySpec(starts=args.check_starts, max_box_exits=args.max_box_exits),
        detector=DetectorTrainConfig(detector=detector, epochs=args.epochs, seed=args.seed,
                                     threshold=args.threshold, target_recall=args.target_recall,
                                     pretrained_path=args.pretrained),
        ensemble=EnsembleSpec(seeds=list(range(1, args.ensemble + 1)) if args.ensemble >= 2
                              else []),
        incremental=IncrementalConfig(enabled=False))
    return spec


def evaluate_command(args):
    from reachwatch.training.evaluation import markdown_table

    from .executors import open_executor
    from .run import run_pipeline
    spec = evaluate_spec(args)
    detector = spec.detector.detector
    with open_executor(args.executor) as executor:
        run = run_pipeline(spec, args.out, executor=executor, until="evaluate")
    rows = run.outputs["evaluate"]["rows"]
    log.info(markdown_table(rows))
    target = target_text(rows, spec.held_out_groups(), spec.detector)
    if target:
        log.info(target)
    log.info(f"wrote {args.out}/table2.md, table2.csv and figures/ "
          f"(configuration: {dc.asdict(spec.dataset)}, detector {dc.asdict(detector)})")
