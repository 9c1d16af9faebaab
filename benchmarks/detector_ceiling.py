"""How well the run's detector settings can do on one environment when they need not
generalise: trained and tested on that environment's own images.

A held-out environment's figures mix two limits: what the detector can learn from an
image at all (is the state, and so the label, visible in it at this size and network?)
and how far what it learned elsewhere carries over. This benchmark separates them. It
renders one larger BRT-labelled dataset of the environment (same labels, image size and
box as the run's datasets; cached by content, so a second call renders nothing), keeps
its last ``--test-share`` as a test split, and trains the run file's detector on growing
shares of the rest. Each line gives, on the test split: AUROC, the recall and accuracy
at the threshold the training run chose (its own validation split, the run file's
``target_recall``), and the accuracy an oracle threshold reaching 95 % recall on the test
split allows. The run's own detector, trained on the other environments, is scored on
the same split first, for comparison.

    python benchmarks/detector_ceiling.py --run out/demo [--environment KSFO_21h_overcast]
        [--samples 6000] [--test-share 0.25] [--sizes 0.25,0.5,1] [--epochs N] [--seed 0]
        [--work RUN/ceiling]

The labels are the BRT's, as in the run's datasets: the figures say how well the
detector learns the map, not whether the map is right (see the run's fidelity section).
"""

import argparse
import dataclasses as dc
import json
import time
from pathlib import Path

import numpy as np

from reachwatch.diagrams import load_detector
from reachwatch.pipeline.spec import digest, load_run_spec
from reachwatch.pipeline.stages import Run
from reachwatch.reach.value_function import ValueFunction
from reachwatch.training.dataset import build_dataset, load_dataset
from reachwatch.training.detector_train import detector_scores, train_detector
from reachwatch.training.metrics import accuracy_at_recall, auroc, binary_metrics

ORACLE_RECALL = 0.95


def rows_of(data, rows):
    """The `LabelledData` of ``rows`` only (images stay memory-mapped)."""
    return dc.replace(data, images=data.images[rows], states=data.states[rows],
                      values=data.values[rows], labels=data.labels[rows],
                      estimates=data.estimates[rows], ensemble=data.ensemble[rows],
                      sources=None if data.sources is None else data.sources[rows],
                      runs=None if data.runs is None else data.runs[rows])


def figures(labels, scores, threshold):
    """Test-split figures of one detector at its own ``threshold``."""
    at = binary_metrics(labels, scores >= threshold)
    return {"auroc": auroc(labels, scores), "threshold": float(threshold),
            "recall": at.recall, "accuracy": at.accuracy,
            "flagged": float(np.mean(scores >= threshold)),
            "accuracy_at_95_recall": accuracy_at_recall(labels, scores, ORACLE_RECALL)}


def line(name, n_train, f):
    return (f"{name:<34} train {n_train:>6}  AUROC {100 * f['auroc']:5.1f}  recall "
            f"{100 * f['recall']:5.1f}  accuracy {100 * f['accuracy']:5.1f}  flagged "
            f"{100 * f['flagged']:5.1f}  accuracy at 95 % recall {100 * f['accuracy_at_95_recall']:5.1f}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", required=True, type=Path,
                        help="a run directory with finished solve and train stages")
    parser.add_argument("--environment", help="an environment the run solved (default: its "
                        "first held-out one)")
    parser.add_argument("--samples", type=int, default=6000, help="images rendered (default 6000)")
    parser.add_argument("--test-share", type=float, default=0.25,
                        help="share of them kept for testing (default 0.25)")
    parser.add_argument("--sizes", default="0.25,0.5,1",
                        help="shares of the rest to train on, comma-separated (default 0.25,0.5,1)")
    parser.add_argument("--epochs", type=int, help="training epochs (default: the run file's)")
    parser.add_argument("--seed", type=int, default=0, help="dataset and training seed")
    parser.add_argument("--work", type=Path, help="dataset and checkpoint folder "
                        "(default RUN/ceiling)")
    parser.add_argument("--json", type=Path, help="also write every figure here")
    args = parser.parse_args()
    if args.samples < 40:
        parser.error(f"--samples must be at least 40, got {args.samples}")
    if not 0 < args.test_share < 1:
        parser.error(f"--test-share must be between 0 and 1, got {args.test_share}")
    try:
        sizes = [float(s) for s in args.sizes.split(",")]
    except ValueError:
        parser.error(f"--sizes must be comma-separated numbers, got '{args.sizes}'")
    if not all(0 < s <= 1 for s in sizes):
        parser.error(f"--sizes must lie in (0, 1], got {sizes}")
    spec = load_run_spec(args.run / "run.yaml")
    run = Run(spec, args.run, progress=True)
    solved = {e.name: e for e in run.environments()}
    name = args.environment or spec.held_out_environments()[0].name
    if name not in solved:
        parser.error(f"the run has no environment '{name}'; it has {sorted(solved)}")
    env = solved[name]
    records = {}
    for stage in (f"solve_{name}", "train"):
        path = args.run / "stages" / f"{stage}.json"
        if not path.is_file():
            parser.error(f"{args.run} has no finished {stage} stage ({path} is missing)")
        records[stage] = json.loads(path.read_text())["outputs"]
    value_function = ValueFunction.load(args.run / records[f"solve_{name}"]["value"])
    box = None
    if run.solved_grid_for(env) != run.grid_for(env):     # label the paper's box, as the run
        box = run.grid_for(env).lo.tolist(), run.grid_for(env).hi.tolist()
    work = args.work or args.run / "ceiling"
    dataset_spec = dc.replace(spec.dataset, samples=args.samples, seed=args.seed)
    started = time.time()
    data = load_dataset(build_dataset(work / "datasets", run.scenario_for(env), value_function,
                                      dataset_spec, box=box))
    print(f"detector ceiling: {name}, {args.samples} images ({100 * data.labels.mean():.1f} % "
          f"anomalous), rendered or reused in {time.time() - started:.0f} s")
    n_test = max(1, int(round(args.test_share * args.samples)))
    first_test = args.samples - n_test
    test = rows_of(data, np.arange(first_test, args.samples))
    results = {"environment": name, "samples": args.samples, "test": n_test}

    model, detector_config, metadata = load_detector(args.run / records["train"]["detector"])
    scores = detector_scores(model, detector_config, test.images)
    results["run detector"] = figures(test.labels, scores, records["train"]["threshold"])
    print(line("run's detector (other environments)", int(metadata.get("samples", 0)),
               results["run detector"]), flush=True)

    config = spec.detector if args.epochs is None else dc.replace(spec.detector, epochs=args.epochs)
    config = dc.replace(config, seed=args.seed).validate()
    for share in sizes:
        n_train = max(10, int(round(share * first_test)))
        train = rows_of(data, np.arange(n_train))
        path = work / f"detector_{digest(dc.asdict(config), data.folder.name, n_train)}.pt"
        started = time.time()
        if path.exists():
            threshold = load_detector(path)[2]["threshold"]
        else:
            threshold = train_detector([train], config, path)["threshold"]
        model, detector_config, _ = load_detector(path)
        f = figures(test.labels, detector_scores(model, detector_config, test.images), threshold)
        results[f"trained here, {n_train}"] = f
        print(line(f"trained here ({time.time() - started:.0f} s)", n_train, f), flush=True)
    if args.json:
        args.json.write_text(json.dumps(results, indent=1, default=float))


if __name__ == "__main__":
    main()
