"""Detector variants on the datasets of a finished `reachwatch run`: each variant of the
run file's detector settings is trained on the run's training environments, its
threshold chosen the way the run file says, and scored on every held-out environment.
Prints one line per variant and held-out environment, then per variant, for each group
of held-out environments (the run file's listed ones, its random family) and for all
states and those that have not failed yet, the minimum and median of: the share of
images flagged, recall, accuracy, AUROC, the accuracy an oracle threshold reaching 95 %
recall on that environment would give (what the ranking allows). Also how many
environments reach 95 % recall and accuracy, and in how many the detector's AUROC beats
every baseline (TaxiNet's prediction error and the ensemble's variance, as in Table 2).

Train with more than one seed (``--seeds 0,1``) before calling a variant better: on
8 training and 8 held-out environments at the demo's settings, two seeds of the same
settings moved the median share flagged from 61 % to 34 % and the worst recall from
82 % to 48 %, while AUROC moved by 1-3 points.

    python benchmarks/detector_variants.py --run out/demo [--variants all] [--seeds 0]
        [--work out/demo/variants] [--json variants.json]

Variants are named overrides of the run file's ``detector`` block (see VARIANTS);
``train_environments: f`` keeps the first share ``f`` of the run file's training
environments (at least one); ``adapt_batchnorm`` keeps the run file's weights and
re-estimates the BatchNorm statistics on each held-out environment's images (`adapted`).
Checkpoints are cached in ``--work`` by content, so a killed study resumes.
"""

import argparse
import copy
import dataclasses as dc
import json
import time
from pathlib import Path

import numpy as np
import torch

from reachwatch.diagrams import load_detector
from reachwatch.pipeline.keys import digest
from reachwatch.pipeline.spec import load_run_spec
from reachwatch.systems.detector import detector_input
from reachwatch.taxi import TaxiApplication, dynamics_for
from reachwatch.training.baselines import estimate_error_of
from reachwatch.training.dataset import load_dataset
from reachwatch.training.detector_train import (THRESHOLD_CHOICE, held_out_operating_threshold,
                                                operating_threshold, train_detector)
from reachwatch.training.evaluation import (NOT_FAILED, Detector, evaluate_environment,
                                            target_summary)

#: Named overrides of the run file's detector settings (nested dicts for ``detector``).
VARIANTS = {
    "run file": {},
    "class balance": {"class_balance": True},
    "no augmentation": {"augment": False},
    "input 48x80": {"detector": {"height": 48, "width": 80}},
    "wide channels": {"detector": {"channels": [32, 64, 128, 192]}},
    "12 epochs": {"epochs": 12},
    "half the environments": {"train_environments": 0.5},
    # With the half above, a learning curve in the number of training environments.
    "a third of the environments": {"train_environments": 1 / 3},
    "two thirds of the environments": {"train_environments": 2 / 3},
    # The threshold from detectors that never saw the group they score (4 groups).
    "left-out-group threshold (every group)": {"threshold_folds": 4},
    "left-out-group threshold (pooled)": {"threshold_folds": 4, "threshold_rule": "pooled"},
    # The run file's weights, with the BatchNorm statistics re-estimated on each held-out
    # environment's unlabelled images (AdaBN): on all of them, or only on those a
    # nominally taxiing aircraft sees (|px| < B/4, |theta| < 10 deg), which the monitor
    # could collect in service. The threshold stays the unadapted one.
    "batch norm per environment (all images)": {"adapt_batchnorm": "all"},
    "batch norm per environment (nominal images)": {"adapt_batchnorm": "nominal"},
}
ORACLE_RECALL = 0.95


def variant_config(base, override: dict, environments: int):
    """``(DetectorTrainConfig, how many of the ``environments`` training environments
    to keep)``."""
    override = copy.deepcopy(override)
    override.pop("adapt_batchnorm", None)       # applied at scoring time (`adapted`)
    share = override.pop("train_environments", 1.0)
    nested = override.pop("detector", {})
    config = dc.replace(base, detector=dc.replace(base.detector, **nested), **override)
    return config.validate(), max(1, int(round(share * environments)))


@torch.no_grad()
def adapted(model, config, images, batch_size=64):
    """A copy of ``model`` whose BatchNorm running statistics are re-estimated (a plain
    average over every batch) on ``images``, uint8 ``(N, H, W, 3)``; weights unchanged."""
    model = copy.deepcopy(model)
    norms = [m for m in model.modules() if isinstance(m, torch.nn.modules.batchnorm._BatchNorm)]
    if not norms:
        raise ValueError("adapt_batchnorm: the detector has no BatchNorm layer")
    for m in norms:
        m.reset_running_stats()
        m.momentum = None
    model.train()
    for start in range(0, len(images), batch_size):
        model(detector_input(torch.from_numpy(np.asarray(images[start:start + batch_size])),
                             config))
    return model.eval()


#: TaxiNet's prediction error, a baseline of Table 2 (and the ensemble's units)
TAXINET_ERROR = estimate_error_of(TaxiApplication(), "TaxiNet")


def nominal_states(states, half_width):
    """The samples a nominally taxiing aircraft sees: |px| < B/4 and |theta| < 10 deg."""
    return (np.abs(states[:, 0]) < 0.25 * half_width) & (np.abs(np.rad2deg(states[:, 2])) < 10.0)


def score_environment(env, data, detector, scenario):
    """One held-out environment: ``(figures, rows)``, a dict of the detector's figures over
    all states and not-yet-failed, and its Table 2 rows (`evaluate_environment`)."""
    inside = dynamics_for(scenario).target(
        torch.as_tensor(data.states, dtype=torch.float64)).numpy() > 0
    rows, _ = evaluate_environment(data, [detector], subsets={NOT_FAILED: inside},
                                   target_recall=ORACLE_RECALL, estimate_error=TAXINET_ERROR)
    out = {"environment": env.name}
    for states in ("all", NOT_FAILED):
        mine = [r for r in rows if r["states"] == states and r["method"] == detector.name]
        if not mine:
            continue
        row = mine[0]
        baselines = [r["auroc"] for r in rows if r["states"] == states and r["method"] != detector.name]
        out[states] = {"n": row["n"], "positives": row["positives"],
                       "flagged": (row["tp"] + row["fp"]) / row["n"],
                       "recall": row["recall"], "accuracy": row["accuracy"],
                       "auroc": row["auroc"], "best_baseline_auroc": max(baselines, default=np.nan),
                       "accuracy_at_95_recall": row["accuracy_at_target_recall"]}
    return out, rows


def summary_lines(name, rows, groups):
    """One line per group of held-out environments (the run file's listed ones and its
    random family) and subset of states: min / median of the `target_summary` figures,
    how many environments reach 95 % recall and accuracy, and in how many the
    detector's AUROC beats every baseline."""
    lines = []
    for s in target_summary(rows, groups, recall=ORACLE_RECALL, accuracy=0.95):
        parts = [f"{label} {100 * s[key][0]:5.1f}/{100 * s[key][1]:5.1f}" for key, label in (
            ("flagged", "flagged"), ("recall", "recall"), ("accuracy", "accuracy"),
            ("auroc", "auroc"), ("accuracy_at_target_recall", "accuracy_at_95_recall"))]
        beats = "-" if s["beats_baselines"] is None else s["beats_baselines"]
        lines.append(f"{name:<24} {s['group']:<16} {s['states']:<15} min/median: " +
                     "  ".join(parts) + f"  both >= 95 in {s['meet_both']}/{s['environments']}"
                     f"  AUROC beats baselines in {beats}/{s['environments']}")
    return lines


def promise_line(name, chosen, results):
    """What a threshold chosen on left-out training groups (`HeldOutThreshold`) promised
    for an unseen environment beside what it got on the held-out ones (all states)."""
    got = np.array([r["all"]["recall"] for r in results if "all" in r], float) * 100
    flagged = np.array([r["all"]["flagged"] for r in results if "all" in r], float) * 100
    p = chosen.promised
    return (f"{name:<24} promised on {len(chosen.per_group)} left-out groups: recall "
            f"{100 * p['min_recall']:5.1f} (lowest group), accuracy "
            f"{100 * p['pooled_accuracy']:5.1f}, flagged {100 * p['flagged']:5.1f}; got on "
            f"{len(got)} held-out: recall min/median {np.nanmin(got):5.1f}/"
            f"{np.nanmedian(got):5.1f}, flagged {np.nanmin(flagged):5.1f}/"
            f"{np.nanmedian(flagged):5.1f}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", required=True, type=Path, help="a finished run directory")
    parser.add_argument("--variants", default="all",
                        help=f"comma-separated names of {list(VARIANTS)}, or all")
    parser.add_argument("--seeds", default="0", help="comma-separated training seeds")
    parser.add_argument("--work", type=Path, help="checkpoint folder (default RUN/variants)")
    parser.add_argument("--json", type=Path, help="also write every figure here")
    args = parser.parse_args()
    names = list(VARIANTS) if args.variants == "all" else args.variants.split(",")
    unknown = [n for n in names if n not in VARIANTS]
    if unknown:
        parser.error(f"unknown variants {unknown}; known: {list(VARIANTS)}")
    record = args.run / "stages" / "dataset.json"
    if not record.is_file():
        parser.error(f"{args.run} has no finished dataset stage ({record} is missing)")
    spec = load_run_spec(args.run / "run.yaml")
    folders = json.loads(record.read_text())["outputs"]["folders"]
    train_envs, test_envs = spec.training_environments(), spec.held_out_environments()
    data = {e.name: load_dataset(args.run / folders[e.name]) for e in train_envs + test_envs}
    work = args.work or args.run / "variants"
    work.mkdir(parents=True, exist_ok=True)
    print(f"detector variants: run {args.run}, {len(train_envs)} training and "
          f"{len(test_envs)} held-out environments, seeds {args.seeds}")
    everything = {}
    for name in names:
        for seed in [int(s) for s in args.seeds.split(",")]:
            config, count = variant_config(dc.replace(spec.detector, seed=seed), VARIANTS[name],
                                           len(train_envs))
            kept = train_envs[:count]
            train = [data[e.name] for e in kept]
            if config.threshold_folds and config.threshold_folds > len(train):
                config = dc.replace(config, threshold_folds=len(train) if len(train) >= 2 else 0)
            # The threshold rule does not change the weights: the checkpoint is shared.
            weights = {k: v for k, v in dc.asdict(config).items() if k not in THRESHOLD_CHOICE}
            tag = digest(weights, [folders[e.name] for e in kept])
            path = work / f"detector_{tag}.pt"
            started = time.time()
            if not path.exists():
                train_detector(train, config, path)
            model, detector_config, _ = load_detector(path)
            chosen = None
            if config.threshold_folds:
                chosen = held_out_operating_threshold(
                    train, config, lambda left, tag=tag: work / f"detector_{tag}_without_"
                    f"{digest(left)}.pt")
                threshold = chosen.threshold
            else:
                threshold = operating_threshold(model, train, config)
            detector = Detector(name, model, detector_config, threshold)
            results, rows = [], []
            for env in test_envs:
                scenario = copy.deepcopy(spec.scenario)
                scenario.environment = env
                scored, mode = detector, VARIANTS[name].get("adapt_batchnorm")
                if mode:
                    images = data[env.name].images
                    if mode == "nominal":
                        images = images[np.flatnonzero(
                            nominal_states(data[env.name].states, env.half_width))]
                    scored = dc.replace(detector, model=adapted(model, detector_config, images))
                r, env_rows = score_environment(env, data[env.name], scored, scenario)
                results.append(r)
                rows += env_rows
                a = r["all"]
                print(f"  {name} seed {seed} {env.name:<28} flagged {100 * a['flagged']:5.1f} "
                      f"(anomalous {100 * a['positives'] / a['n']:5.1f})  recall "
                      f"{100 * a['recall']:5.1f}  accuracy {100 * a['accuracy']:5.1f}  AUROC "
                      f"{100 * a['auroc']:5.1f} (best baseline "
                      f"{100 * a['best_baseline_auroc']:5.1f})", flush=True)
            label = f"{name} (seed {seed})"
            print(f"{label}: {len(kept)} training environments, threshold {threshold:.3g}, "
                  f"{time.time() - started:.0f} s")
            for line in summary_lines(label, rows, spec.held_out_groups()):
                print(line, flush=True)
            if chosen is not None:
                print(promise_line(label, chosen, results), flush=True)
            everything[label] = {"config": dc.asdict(config), "threshold": threshold,
                                 "held_out_threshold": None if chosen is None else dc.asdict(chosen),
                                 "training_environments": [e.name for e in kept],
                                 "environments": results,
                                 "summary": target_summary(rows, spec.held_out_groups(),
                                                           recall=ORACLE_RECALL)}
    if args.json:
        args.json.write_text(json.dumps(everything, indent=1, default=float))


if __name__ == "__main__":
    main()
